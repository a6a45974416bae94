"""What the scheduler tests share: a campaign opened in a store with the simulated rig and clock to run it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy.engine import Engine

from driftlab.campaigns import schema as sc
from driftlab.campaigns.acquisition import CampaignHandle, StoreSink, open_campaign
from driftlab.campaigns.clock import SimClock
from driftlab.campaigns.db import store_engine
from driftlab.campaigns.plan import Plan
from driftlab.daemon.rig import InstrumentRig
from driftlab.daemon.run import sim_clock
from driftlab.daemon.simrig import build_sim_rig, scenario_meta
from driftlab.daq.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
CLEAN = ROOT / "examples" / "scenarios" / "clean.yaml"


@dataclass
class SimRun:
    """A new campaign of a plan in a store, its sink, and the virtual machine's rig on a flat-out clock."""

    engine: Engine
    handle: CampaignHandle
    sink: StoreSink
    clock: SimClock
    rig: InstrumentRig


def sim_run(plan: Plan, url: str) -> SimRun:
    """Open a new campaign of `plan` in the store at `url` and the simulated rig to run it as fast as it goes."""
    engine = store_engine(url)
    meta = scenario_meta(None)
    handle = open_campaign(engine, plan, meta["channels"], meta["room_channels"], resume=False, origin={})
    clock = sim_clock(plan, handle.cursor, math.inf)
    rig = build_sim_rig(plan, load_scenario(CLEAN), clock, list(meta["channels"]))
    return SimRun(engine, handle, StoreSink(engine, plan, handle), clock, rig)


def plant_reading(run: SimRun, time_s: float, channel: str = "T7") -> None:
    """Store a reading the cursor still lists as to do (a reading the run will find already there)."""
    with run.engine.begin() as conn:
        conn.execute(
            sc.TemperatureSample.__table__.insert().values(
                campaign_id=run.handle.campaign_id,
                channel_id=run.handle.channel_ids[channel],
                time_s=time_s,
                value=1.0,
                campaign_start_day=run.handle.start_day,
            )
        )
