"""`driftlab hal-offsets`: LinuxCNC's external axis offsets driven from the current model (a userspace HAL component).

`driftlab hal-offsets (--model F | --api URL --machine ID) [--temps CSV] [--axes xyz] [--period-s 0.1]`

Run on the LinuxCNC machine with LinuxCNC's Python (``loadusr -W driftlab hal-offsets ...`` in a
HAL file, docs/instruments.md): it creates the component ``driftlab-hal`` and corrects each axis
through ``axis.L.eoffset-*`` (``driftlab.compensator.hal_offsets``). Needs LinuxCNC's ``hal``
module, which no package index has: elsewhere it stops with a one-line error. Untested on a real control.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from driftlab.errors import ValidationError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Register `hal-offsets`."""
    p = sub.add_parser(
        "hal-offsets",
        help="LinuxCNC: drive the external axis offsets from the current model (userspace HAL component)",
        description="A userspace HAL component (driftlab-hal) correcting the axes through axis.L.eoffset-*; "
        "wire it in a HAL file (docs/instruments.md). Untested on a real control.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="model document JSON (as printed by `driftlab models show`)")
    src.add_argument("--api", help="driftlab API base URL: the machine's current model, hot-reloaded")
    p.add_argument("--machine", help="machine id (required with --api)")
    p.add_argument("--temps", type=Path, help="temperatures.csv a logger appends to; default with --api: its latest")
    p.add_argument("--axes", default="xyz", help="axis letters to correct (xyz; xyzab for the rotary axes too)")
    p.add_argument("--scale", type=float, default=1e-4, help="eoffset-scale: mm (deg) per count (1e-4)")
    p.add_argument("--period-s", type=float, default=0.1, help="update period (s, 0.1)")
    p.add_argument("--refresh-s", type=float, default=30.0, help="poll the model this often (s, 30)")
    p.add_argument("--name", default="driftlab-hal", help="HAL component name (driftlab-hal)")
    p.add_argument("--machine-file", type=Path, help="machine envelope (travel, max_correction, margin)")
    p.add_argument("--allow-extrapolation", action="store_true", help="apply offsets beyond the fitted range")
    p.add_argument("--periods", type=int, default=None, help="stop after this many periods (a trial run)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    """Create the component and run it until unloaded."""
    # lazy: the compensator's imports stay off `driftlab --help`
    from driftlab.commands.compensate import _model_file, machine_file_envelope
    from driftlab.compensator import hal_offsets
    from driftlab.compensator.stream import ApiModel, ApiTemperatures, CsvTemperatures, StaticModel
    from driftlab.config import get_settings

    if not args.period_s > 0:
        raise ValidationError(f"--period-s must be positive, got {args.period_s}")
    token = get_settings().api_token or None
    models: Any
    if args.model:
        models = StaticModel(_model_file(args.model, args.machine))
    else:
        if not args.machine:
            raise ValidationError("--api needs --machine ID")
        models = ApiModel(args.api, args.machine, token=token)
    if args.temps:
        temps: Any = CsvTemperatures(args.temps)
    elif args.api:
        temps = ApiTemperatures(args.api, args.machine, token=token)
    else:
        raise ValidationError("hal-offsets needs --temps CSV or --api for the temperatures")
    envelope = machine_file_envelope(args.machine_file)
    hal = hal_offsets.import_hal()  # before anything is created: a one-line error off LinuxCNC
    comp = hal_offsets.HalOffsets(
        hal,
        models,
        temps,
        axes=args.axes,
        scale={a.lower(): args.scale for a in args.axes},
        name=args.name,
        envelope=envelope,
        allow_extrapolation=args.allow_extrapolation,
        refresh_s=args.refresh_s,
    )
    comp.run(period_s=args.period_s, periods=args.periods)
    s = comp.state
    applied = ", ".join(f"{a.upper()} {v:+.4f}" for a, v in s.applied.items()) or "none"
    print(
        f"{args.name}: {s.periods} periods, offsets {applied}, {s.faults} fault(s)"
        + (f": {s.fault}" if s.fault else "")
    )
    return 0
