"""`driftlab campaign`: stored campaigns."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from driftlab.commands.daemon import register_status
from driftlab.commands.db import add_db_option
from driftlab.errors import NotFoundError, ValidationError
from driftlab.labels import display_unit, duration
from driftlab.vocabulary import heat_source

if TYPE_CHECKING:
    from driftlab.campaigns.live import ChannelRow, ErrorColumns


def register(sub: argparse._SubParsersAction) -> None:
    """Register `campaign list`."""
    camp = sub.add_parser("campaign", help="stored campaigns")
    campsub = camp.add_subparsers(dest="campaign_command", metavar="CAMPAIGNCOMMAND", required=True)
    lst = campsub.add_parser("list", help="list stored campaigns")
    lst.add_argument("--machine", default=None, help="only this machine's campaigns")
    lst.add_argument("--json", action="store_true", help="one JSON array instead of a table")
    add_db_option(lst)
    lst.set_defaults(func=_list)

    register_status(campsub)
    add_watch(campsub)


def _list(args: argparse.Namespace) -> int:
    """Print the campaigns as a table or JSON."""
    # lazy: this function's imports would add 3.6 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect

    with connect(args.db) as store:
        rows = [c.as_dict() for c in store.campaigns.summaries(args.machine)]
    if args.json:
        print(json.dumps(rows))
        return 0
    header = ("id", "machine_id", "name", "started_at", "status", "source", "channels", "scans", "error_samples")
    table = [header] + [tuple(str(r[k]) for k in header) for r in rows]
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    for row in table:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    return 0


# -- `campaign status ID --watch`: the live page's picture in the terminal --------------------------


def add_watch(campsub: argparse._SubParsersAction) -> None:
    """Add `--watch` and `--interval` to the `campaign status` parser (registered with the daemon's command)."""
    st = campsub.choices["status"]
    plain = st.get_default("func")
    st.add_argument(
        "--watch",
        action="store_true",
        help="follow one campaign in the terminal until it ends (Ctrl-C to leave): stage, progress, "
        "latest temperatures and errors, instrument health",
    )
    st.add_argument("--interval", type=float, default=1.0, metavar="S", help="with --watch: seconds between reads")

    def _status_or_watch(args: argparse.Namespace) -> int:
        """Print the status, or follow it with --watch."""
        return _watch(args) if args.watch else plain(args)

    st.set_defaults(func=_status_or_watch)


def _watch(args: argparse.Namespace) -> int:
    """Follow one campaign with rich Live until it is no longer running; 0 then, or on Ctrl-C."""
    # lazy: this function's imports would add 1.3 s to `driftlab --help` (measured)
    from driftlab.campaigns import live
    from driftlab.campaigns.db import store_engine

    if args.campaign is None:
        raise ValidationError("--watch follows one campaign: give its id or name")
    if args.json:
        raise ValidationError("--watch draws in the terminal; without it, --json prints the status once")
    if not args.interval > 0:
        raise ValidationError(f"--interval must be positive, got {args.interval}")
    engine = store_engine(args.db)
    cid = live.find_campaign(engine, args.campaign)
    if cid is None:
        raise NotFoundError(f"no daemon campaign {args.campaign!r}")
    # lazy, as above: kept off the `driftlab --help` path
    from rich.console import Console

    try:
        watch(engine, cid, Console(), args.interval)
    except KeyboardInterrupt:
        pass
    return 0


def watch(
    engine: Any, campaign_id: int, console: Any, interval_s: float = 1.0, max_frames: int | None = None
) -> dict[str, Any]:
    """Redraw the campaign every ``interval_s`` while it runs (at most ``max_frames`` times); return its last header."""
    # lazy: this function's imports would add 1.4 s to `driftlab --help` (measured)
    from rich.live import Live

    from driftlab.campaigns import live

    chans = live.channels(engine, campaign_id)
    frames = 0
    with Live(console=console, auto_refresh=False, transient=False) as screen:
        while True:
            head = live.header(engine, campaign_id)
            if head is None:
                raise NotFoundError(f"campaign {campaign_id} is no longer in the store")
            t = head["progress"]["time_s"] or 0.0
            errs = live.error_readings(engine, campaign_id, limit=200, since_s=t - 4 * 3600.0)
            screen.update(render(head, chans, errs), refresh=True)
            frames += 1
            if head["status"] != "running" or (max_frames is not None and frames >= max_frames):
                return head
            time.sleep(interval_s)


def _bar(fraction: float, width: int = 30) -> Any:
    """Return a text progress bar of ``width`` cells."""
    # lazy: this function's imports would add 59 ms to `driftlab --help` (measured)
    from rich.text import Text

    n = int(round(max(0.0, min(1.0, fraction)) * width))
    return Text.assemble(("\u2588" * n, "green"), ("\u2591" * (width - n), "dim"))


def render(head: dict[str, Any], chans: Sequence[ChannelRow], errs: ErrorColumns) -> Any:
    """Return the rich renderable of one campaign: stage and progress, temperatures by structure, errors, health."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.console import Group
    from rich.text import Text

    latest = head["latest"] or {}
    return Group(
        _title(head),
        _progress_grid(head),
        _temperatures_table(latest.get("values") or {}, chans),
        _errors_table(errs),
        Text("Instrument health", style="bold"),
        _health_grid(head["health"]),
    )


def _title(head: dict[str, Any]) -> Any:
    """Return the campaign's title line: name, status (or how long it is stale), id, machine and speed."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.text import Text

    stale = head.get("stale_since")
    return Text.assemble(
        (head["name"], "bold"),
        "  ",
        (f"[running, stale since {stale}: the daemon stopped beating]", "bold red")
        if stale
        else (f"[{head['status']}]", "green" if head["status"] == "running" else "cyan"),
        f"  campaign {head['campaign_id']}, machine {head['machine']}, "
        + (
            "instruments"
            if head["mode"] != "sim"
            else f"virtual machine x{head['speed']:g}"
            if head["speed"]
            else "virtual machine, as fast as it goes"
        ),
    )


def _progress_grid(head: dict[str, Any]) -> Any:
    """Return the grid of the stage, its progress, the campaign's progress, what is stored and the latest scan."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.table import Table
    from rich.text import Text

    p = head["progress"]
    top = Table.grid(padding=(0, 2))
    top.add_column(style="dim", justify="right")
    top.add_column()
    if head["stage"]:
        _stage_rows(top, head)
    total_left = (
        "done"
        if head["status"] == "done"
        else f"{duration(p['total_left_s'])} left"
        if p["total_left_s"] is not None
        else "-"
    )
    top.add_row("campaign", Text.assemble(_bar(p["fraction"]), f" {100 * p['fraction']:.1f} %, {total_left}"))
    top.add_row("stored", f"{p['scans']} of {p['n_scans']} scans, {p['points']} of {p['n_points']} sweep points")
    latest = head["latest"] or {}
    top.add_row(
        "latest scan", f"{duration(latest.get('time_s'), clock=True)} into the campaign" if latest else "none yet"
    )
    return top


def _stage_rows(top: Any, head: dict[str, Any]) -> None:
    """Add the current stage's rows to the grid ``top``: what it runs, its setup, and how far it is."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.text import Text

    p, st, stale = head["progress"], head["stage"], head.get("stale_since")
    heat = st["heat_source"] if heat_source(st["heat_source"]) not in ("idle", "off") else "no heat source"
    extra = [f"axis {st['axis']}", heat]
    if st["spindle_rpm"]:
        extra.append(f"spindle {st['spindle_rpm']:.0f} rpm")
    if st["feed_mm_min"]:
        extra.append(f"feed {st['feed_mm_min']:.0f} {'deg/min' if st['axis'] in ('A', 'B') else 'mm/min'}")
    top.add_row(
        "stage",
        Text.assemble((st["name"], "bold"), f"  {st['ordinal'] + 1} of {len(head['stages'])}: ", ", ".join(extra)),
    )
    if st.get("setup"):
        top.add_row("setup", ", ".join(str(v) for v in st["setup"].values() if v))
    frac = p["stage_fraction"] or 0.0
    if head["status"] == "done":
        left = "campaign done"
    elif p["stage_left_s"] is None:  # stale or stopped: nobody runs it, nothing is "left"
        left = f"stale since {stale}" if stale else head["status"]
    else:
        left = duration(p["stage_left_s"])
        if p["stage_left_wall_s"] is not None and head["speed"] not in (None, 1.0):
            left += f" (about {duration(p['stage_left_wall_s'])} wall-clock)"
        left += " of campaign time left"
    top.add_row("in stage", Text.assemble(_bar(frac), f" {100 * frac:.0f} % done, {left}"))


def _temperatures_table(values: dict[str, float | None], chans: Sequence[ChannelRow]) -> Any:
    """Return the latest temperatures by structure (an open thermocouple in red)."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.table import Table
    from rich.text import Text

    temps = Table(title="Latest temperatures (°C) by structure", title_justify="left", expand=False)
    temps.add_column("structure")
    temps.add_column("range", justify="right")
    temps.add_column("thermocouples")
    groups: dict[str, list[ChannelRow]] = {}
    for c in chans:
        groups.setdefault("room" if c["room"] else c["structure"], []).append(c)
    for g in sorted(groups):
        vals = [values.get(c["name"]) for c in groups[g]]
        ok = [v for v in vals if v is not None]
        cells = Text()
        for c, v in zip(groups[g], vals):
            if c["name"] in values and v is None:
                cells.append(f"{c['name']} open  ", style="bold red")
            else:
                cells.append(f"{c['name']} {'-' if v is None else f'{v:.2f}'}  ")
        temps.add_row(g.replace("_", " "), f"{min(ok):.2f} .. {max(ok):.2f}" if ok else "-", cells)
    return temps


def _errors_table(errs: ErrorColumns) -> Any:
    """Return the latest sweep of each axis, term and approach: the value at each position."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.table import Table

    errors = Table(title="Latest error sweeps (value at each position)", title_justify="left")
    errors.add_column("axis/term")
    errors.add_column("approach", justify="center")
    errors.add_column("readings")
    errors.add_column("campaign time", justify="right")
    last: dict[tuple[str, str, int], tuple[int, list[int]]] = {}
    for i in range(len(errs["seq"])):
        key = (errs["axis"][i], errs["term"][i], errs["direction"][i])
        sw = errs["sweep"][i]
        if key not in last or last[key][0] != sw:
            last[key] = (sw, [])
        last[key][1].append(i)
    for (axis, term, d), (_, idx) in sorted(last.items()):
        scale, unit = display_unit(term)
        pos_unit = "deg" if axis in ("A", "B") else "mm"
        readings = "  ".join(
            f"{errs['position'][i]:g} {pos_unit}: {errs['value'][i] * scale:.1f}"
            for i in sorted(idx, key=lambda i: errs["position"][i])
        )
        errors.add_row(
            f"{axis}/{term}", "+" if d > 0 else "-", f"{readings} {unit}", duration(errs["t"][idx[-1]], clock=True)
        )
    if not last:
        errors.add_row("-", "-", "no error readings yet", "-")
    return errors


def _health_grid(h: dict[str, Any]) -> Any:
    """Return the instruments' health: faults, timeouts, retries, open thermocouples and the last faults."""
    # lazy: this function's imports would add 93 ms to `driftlab --help` (measured)
    from rich.table import Table
    from rich.text import Text

    health = Table.grid(padding=(0, 2))
    health.add_column(style="dim", justify="right")
    health.add_column()
    health.add_row("faults", Text(str(h["faults"]), style="yellow" if h["faults"] else "green"))
    health.add_row(
        "timeouts",
        Text(
            f"{h['timeouts']}"
            + (f" (in the last {h['counted_over']} faults)" if h["counted_over"] < h["faults"] else ""),
            style="yellow" if h["timeouts"] else "green",
        ),
    )
    if h["retries"]:  # real counts, or nothing
        health.add_row("retries", ", ".join(f"{k} {v}" for k, v in h["retries"].items()))
    health.add_row(
        "open thermocouples", Text(", ".join(h["open"]) or "none", style="bold red" if h["open"] else "green")
    )
    for f in h["recent"][-3:]:
        health.add_row("", f"{duration(f['t_s'], clock=True)} {f['instrument']} ({f['step']}): {f['message']}")
    return health
