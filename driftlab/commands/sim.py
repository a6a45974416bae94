"""`driftlab sim`: the ch. 4.5 simulation study and simulated campaigns on the virtual machine."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    """Register `sim thesis` and `sim campaign`."""
    sim = sub.add_parser("sim", help="run the thesis simulation study or a simulated campaign")
    simsub = sim.add_subparsers(dest="sim_command", metavar="SIMCOMMAND", required=True)

    thesis = simsub.add_parser("thesis", help="ch. 4.5 study: 8 h sinusoidal program, with/without compensation")
    thesis.add_argument("--json", type=Path, required=True, help="write the figures here")
    thesis.add_argument("--hours", type=float, default=8.0)
    thesis.add_argument("--seed", type=int, default=0)
    thesis.set_defaults(func=_thesis)

    camp = simsub.add_parser("campaign", help="run a staged campaign on the virtual machine, write a bundle v1")
    camp.add_argument("--scenario", type=Path, required=True, help="scenario YAML (examples/scenarios/)")
    camp.add_argument("--out", type=Path, required=True, help="bundle directory to write")
    camp.add_argument("--hours", type=float, default=None, help="override the scenario's duration")
    camp.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    camp.set_defaults(func=_campaign)


def _thesis(args: argparse.Namespace) -> int:
    """Run the thesis study and write its JSON figures."""
    # lazy: this function's imports would add 0.2 s to `driftlab --help` (measured)
    from driftlab.models.simulation import thesis_study

    result = thesis_study(hours=args.hours, seed=args.seed)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    return 0


def _campaign(args: argparse.Namespace) -> int:
    """Simulate a campaign from a scenario and write it as a bundle v1 directory."""
    # lazy: this function's imports would add 2.4 s to `driftlab --help` (measured)
    from driftlab.campaigns.bundle import write_bundle
    from driftlab.daq.sim.campaign import simulate_campaign
    from driftlab.daq.sim.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    overrides = {k: v for k, v in (("hours", args.hours), ("seed", args.seed)) if v is not None}
    if overrides:
        scenario = scenario.model_copy(update=overrides)
    sim = simulate_campaign(scenario)
    path = write_bundle(args.out, sim.meta, sim.temperatures, sim.conditions, sim.errors)
    print(f"wrote bundle {path} ({len(sim.temperatures)} scans, {len(sim.errors)} error samples)")
    return 0
