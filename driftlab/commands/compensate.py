"""`driftlab compensate`: correct a motion-code program offline, or stream it to the machine (ch. 7.2)."""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict, cast

from driftlab.errors import ValidationError
from driftlab.vocabulary import AXES

if TYPE_CHECKING:
    from driftlab.models.envelope import Envelope

log = logging.getLogger(__name__)

#: the links ``--port`` can stream over
LINKS = ("thesis", "linuxcnc", "dnc")


def register(sub: argparse._SubParsersAction) -> None:
    """Register `compensate`."""
    p = sub.add_parser(
        "compensate",
        help="correct a five-axis program for thermal drift (offline to a file, or streamed to the controller)",
        description=(
            "Offline: driftlab compensate PROGRAM.nc --model FILE|--api URL --machine ID --temps CSV -o OUT.nc. "
            "Streaming: driftlab compensate PROGRAM.nc --api URL --machine ID --port SERIAL_URL."
        ),
    )
    p.add_argument("program", type=Path, help="motion-code program (G0/G1, G90/G91, G21; X Y Z mm, A B deg)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="model document JSON (as printed by `driftlab models show`)")
    src.add_argument("--api", help="driftlab API base URL: the machine's current model (hot-reloaded when streaming)")
    p.add_argument("--machine", help="machine id (required with --api)")
    p.add_argument(
        "--temps", type=Path, help="temperatures.csv (bundle v1 layout); default with --api: its latest scan"
    )
    p.add_argument("-o", "--out", type=Path, help="write the corrected program here (offline)")
    p.add_argument("--port", help="stream to the controller on this serial device or pyserial URL (socket://...)")
    p.add_argument(
        "--link",
        choices=LINKS,
        default="thesis",
        help="how --port talks to the control: dnc (a drip feed with the DC1/DC3 handshake, what shops' "
        "controls read), linuxcnc (linuxcncrsh, 2.9 or master: --port host[:port], each block an MDI command), "
        "thesis (driftlab's own STAT?/BLK/POS? protocol of the virtual controller); default thesis",
    )
    p.add_argument("--baud", type=int, default=9600, help="DNC line speed (default 9600)")
    p.add_argument("--line", help="DNC character format 8N1, 7E1 or 7E2 (default: the profile's)")
    p.add_argument(
        "--profile",
        default="generic",
        help="DNC control family: haas, haas-dc (Setting 14 DC CODES), fanuc, heidenhain, generic (default)",
    )
    p.add_argument(
        "--start",
        help="machine pose before the program: X,Y,Z,A,B (mm, deg; default home, or the controller's "
        "position when streaming with --link thesis; a DNC drip feed has no read-back: home unless given)",
    )
    p.add_argument("--resolution-mm", type=float, default=0.0025, help="linear positioning resolution (0.0025)")
    p.add_argument("--resolution-deg", type=float, default=0.001, help="rotary positioning resolution (0.001)")
    p.add_argument(
        "--hysteresis-steps",
        type=float,
        default=0.0,
        help="send a correction step once it is 0.5 + this many steps from what was sent (0: the nearest step)",
    )
    p.add_argument("--max-segment-mm", type=float, default=5.0, help="split G1 moves longer than this (5 mm)")
    p.add_argument("--max-segment-deg", type=float, default=5.0, help="split G1 rotations larger than this (5 deg)")
    p.add_argument("--low-water", type=int, default=4, help="refill the controller's buffer at this many blocks")
    p.add_argument("--high-water", type=int, default=None, help="fill the buffer up to this many blocks")
    p.add_argument("--refresh-s", type=float, default=30.0, help="poll model and temperatures this often (s)")
    p.add_argument("--max-age-s", type=float, default=120.0, help="correct a waiting block again after this (s)")
    p.add_argument(
        "--machine-file",
        type=Path,
        help="machine envelope (JSON or YAML: travel, max_correction, extrapolation_margin_degC); "
        "needed when the model document carries no travel, and wins over the document's key by key",
    )
    p.add_argument(
        "--allow-extrapolation",
        action="store_true",
        help="compensate even with temperatures beyond the fitted range plus the margin (logged and reported)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    p.set_defaults(func=_run)


def _start(text: str | None) -> tuple[float, ...] | None:
    """Return the start pose from ``X,Y,Z,A,B``."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 5:
        raise ValidationError(f"--start must be five numbers X,Y,Z,A,B, got {text!r}")
    return values


def _model_file(path: Path, machine: str | None) -> Any:
    """Return the ErrorModel of a model document file."""
    # lazy: this function's imports would add 1.6 s to `driftlab --help` (measured)
    from driftlab.compensator.compensate import ErrorModel

    try:
        body = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValidationError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValidationError(f"{path}: not a model document ({' '.join(str(exc).split())})") from None
    if isinstance(body, dict) and isinstance(body.get("document"), dict):
        body = body["document"]
    if not isinstance(body, dict):
        raise ValidationError(f"{path}: not a model document (expected a JSON object)")
    model = ErrorModel.from_document(body)
    if machine and model.machine and model.machine != machine:
        raise ValidationError(f"{path}: model of machine {model.machine}, not {machine}")
    return model


def machine_file_envelope(path: Path | None) -> Envelope | None:
    """Return the envelope of a machine file (JSON, or YAML), or None without one."""
    if path is None:
        return None
    # lazy: this function's imports would add 0.3 s to `driftlab --help` (measured)
    from driftlab.models.envelope import envelope_from_mapping

    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValidationError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValidationError(f"{path}: cannot read the machine file ({type(exc).__name__})") from None
    try:
        if path.suffix.lower() == ".json":
            body = json.loads(text)
        else:
            # lazy, as above: kept off the `driftlab --help` path
            import yaml

            body = yaml.safe_load(text)
    except Exception as exc:  # json.JSONDecodeError, yaml.YAMLError: one line, the file's position only
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else f" line {getattr(exc, 'lineno', '?')}"
        raise ValidationError(f"{path}: not a machine file (unreadable JSON/YAML at{where})") from None
    return envelope_from_mapping(body, str(path))


def _guard(model: Any, args: argparse.Namespace) -> Any:
    """Return the envelope guard of this run; refuse a model with no travel and no machine file."""
    # lazy: this function's imports would add 0.6 s to `driftlab --help` (measured)
    from driftlab.compensator.guard import Guard

    guard = Guard.for_model(
        model, machine_file_envelope(args.machine_file), allow_extrapolation=args.allow_extrapolation
    )
    if guard.envelope is None or not guard.envelope.travel:
        raise ValidationError(
            f"model {model.label} carries no machine travel (its campaigns state no machine.travel and it was "
            "fitted without --machine-file): give --machine-file FILE with the axes' travel "
            "(examples/machines/virtual-machine.yaml for the virtual machine; docs/compensate.md)"
        )
    return guard


def _header(model: Any, document: Mapping[str, Any], tag: str, temps: Any) -> list[str]:
    """Return the header comment of the corrected program: model, temperatures used, driftlab, date."""
    # lazy: this function's imports would add to `driftlab --help`
    import driftlab
    from driftlab.compensator.compensate import TemperatureTable
    from driftlab.compensator.header import program_header, temperature_lines

    channels = list(model.channels)
    if isinstance(temps, TemperatureTable):
        cols = [c for c in channels if c in temps.values.columns]
        lines = temperature_lines({c: temps.values[c].to_numpy(float) for c in cols}, temps.time_s, "CSV ")
    else:
        lines = temperature_lines({c: temps[c] for c in channels if c in temps}, None, "latest API ")
    version = document.get("version")
    return program_header(
        str(document.get("machine") or model.machine),
        None if version is None else int(version),
        tag,
        lines,
        driftlab.__version__,
    )


def _run(args: argparse.Namespace) -> int:
    """Run the offline or streaming compensation."""
    # lazy: this function's imports would add 2.4 s to `driftlab --help` (measured)
    from driftlab.compensator.compensate import (
        TemperatureTable,
        compensate_file,
        decimals_for,
        retain_freed_memory,
    )
    from driftlab.config import get_settings

    retain_freed_memory()

    if args.api and not args.machine:
        raise ValidationError("--api needs --machine ID")
    start = _start(args.start)
    token = get_settings().api_token or None
    decimals = decimals_for(args.resolution_mm, args.resolution_deg)
    if not 0.0 <= args.hysteresis_steps < 0.5:
        raise ValidationError(f"--hysteresis-steps must be in [0, 0.5) steps, got {args.hysteresis_steps}")

    if args.port is None:
        if args.out is None:
            raise ValidationError("offline compensation needs -o OUT.nc (or --port to stream)")
        if args.model:
            model = _model_file(args.model, args.machine)
            # lazy, as above: kept off the `driftlab --help` path
            from driftlab.compensator.header import document_digest

            body = json.loads(args.model.read_text())
            document = body.get("document", body) if isinstance(body, dict) else {}
            tag = f"document sha256 {document_digest(document)}"
        else:
            # lazy, as above: kept off the `driftlab --help` path
            from driftlab.compensator.stream import ApiModel

            source = ApiModel(args.api, args.machine, token=token)
            source.refresh()
            model = source.model
            document, tag = dict(source.document or {}), f"ETag {source.etag or '-'}"
        if args.temps:
            temps: Any = TemperatureTable.read_csv(args.temps)
        elif args.api:
            # lazy, as above: kept off the `driftlab --help` path
            from driftlab.compensator.stream import ApiTemperatures

            temps = ApiTemperatures(args.api, args.machine, token=token).read()
        else:
            raise ValidationError("offline compensation needs --temps CSV (or --api for the latest scan)")
        guard = _guard(model, args)
        header = _header(model, document, tag, temps)
        # the whole program is checked (syntax, envelope, corrections, temperatures) before any output
        # is opened, a piece at a time (constant memory whatever its length)
        result = compensate_file(
            args.program,
            model,
            temps,
            args.out,
            start=start,
            **_grid(args),
            guard=guard,
            header=header,
        )
        summary = {"out": str(args.out), **result.summary()}
        if args.json:
            print(json.dumps(summary))
        else:
            mc = result.max_correction
            print(
                f"wrote {args.out}: {result.blocks} blocks, {result.points} points, model {result.model}, "
                f"temperatures {result.temperatures}; largest correction X {mc['X']} Y {mc['Y']} Z {mc['Z']} mm, "
                f"A {mc['A']} B {mc['B']} deg"
            )
            _report_extrapolation(result.extrapolated)
        return 0
    return _stream(args, start, decimals, token)


class _Grid(TypedDict):
    """The output resolution, step hysteresis and segment lengths of the corrected program, as the compensator
    takes them."""

    resolution_mm: float
    resolution_deg: float
    hysteresis_steps: float
    max_segment_mm: float
    max_segment_deg: float


def _grid(args: argparse.Namespace) -> _Grid:
    """Return the options' output grid (offline and streamed compensation take the same)."""
    return cast(_Grid, {name: getattr(args, name) for name in _Grid.__required_keys__})  # the options of those names


def _report_extrapolation(extrapolated: Mapping[str, Mapping[str, float]]) -> None:
    """Print one line per channel read beyond its fitted range (extrapolation allowed)."""
    for channel, d in extrapolated.items():
        print(
            f"extrapolated: {channel} up to {d['value_degC']:g} degC, {d['beyond_degC']:g} degC outside "
            f"its fitted range {d['min']:g}..{d['max']:g} degC"
        )


def _open_link(args: argparse.Namespace) -> Any:
    """Return the machine link ``--link`` names on ``--port`` (a DNC drip feed with its profile and line settings)."""
    if args.link == "dnc":
        # lazy: kept off the `driftlab --help` path
        from driftlab.daq.dnc import DncLink, line_settings, profile

        prof = profile(args.profile)
        line = args.line or prof.line
        line_settings(line)
        if not 50 <= args.baud <= 4_000_000:
            raise ValidationError(f"--baud must be between 50 and 4000000, got {args.baud}")
        return DncLink.open(args.port, prof, args.baud, line)
    if args.line is not None or args.profile != "generic" or args.baud != 9600:
        raise ValidationError("--baud, --line and --profile are for --link dnc")
    if args.link == "linuxcnc":
        # lazy: the links' imports stay off the offline path
        from driftlab.daq.linuxcnc import LinuxCNCLink

        return LinuxCNCLink.open(args.port)
    from driftlab.daq.machine_link import SerialMachineLink

    return SerialMachineLink.open(args.port)


def _stream(
    args: argparse.Namespace, start: tuple[float, ...] | None, decimals: tuple[int, int], token: str | None
) -> int:
    """Stream the corrected program to the controller, reading it again a piece at a time (constant memory)."""
    # lazy: this function's imports would add 2.3 s to `driftlab --help` (measured)
    from driftlab.compensator.compensate import ErrorModel, FirstPass, Grid, parse_pieces, program_pieces, scan_program
    from driftlab.compensator.stream import (
        ApiModel,
        ApiTemperatures,
        CsvTemperatures,
        StaticModel,
        Streamer,
        check_sendable,
    )

    if args.out is not None:
        raise ValidationError("-o is for offline compensation; with --port the program is streamed")
    models: Any
    if args.model:
        model: ErrorModel = _model_file(args.model, args.machine)
        models = StaticModel(model)
    else:
        models = ApiModel(args.api, args.machine, token=token)
    if args.temps:
        temps: Any = CsvTemperatures(args.temps)
    elif args.api:
        temps = ApiTemperatures(args.api, args.machine, token=token)
    else:
        raise ValidationError("streaming needs --temps CSV or --api for the temperatures")
    # every byte that will go down the line, before the line is even opened: one Latin-1 comment must not
    # stop a part in the middle (a tape line carries printable 7-bit ASCII)
    check_sendable(program_pieces(args.program), str(args.program))
    # the thesis and linuxcnc links read the controller's pose; a drip feed has no read-back (``--start`` or
    # home), and its port is opened only once the whole program has passed the first pass
    link = _open_link(args) if args.link != "dnc" else None
    try:
        if start is None and link is not None:
            pos = link.position()
            start = tuple(pos[a] for a in AXES)
        # the first pass, before any block is sent: the whole program from the controller's pose,
        # against the envelope with the model and temperatures of now (the streamer checks every
        # point again, and every new reading, as it goes)
        models.refresh()
        assert models.model is not None
        guard = _guard(models.model, args)
        scan = scan_program(
            args.program,
            str(args.program),
            decimals,
            start=start,
            max_segment_mm=args.max_segment_mm,
            max_segment_deg=args.max_segment_deg,
            check=FirstPass(guard, models.model, temps.read(), grid=Grid.of(_grid(args))),
        )
        # the second pass of the offline path: pieces parsed with the state the lines before them leave
        pieces = parse_pieces(
            program_pieces(args.program),
            scan,
            str(args.program),
            start=start,
            min_decimals=decimals,
            max_segment_mm=args.max_segment_mm,
            max_segment_deg=args.max_segment_deg,
        )
        streamer = Streamer(
            pieces,
            models,
            temps,
            **_grid(args),
            max_age_s=args.max_age_s,
            refresh_s=min(args.refresh_s, args.max_age_s),
            guard=guard,
        )
        if link is None:
            link = _open_link(args)
        result = streamer.run(link, low_water=args.low_water, high_water=args.high_water)
    finally:
        if link is not None:
            link.close()
    summary = result.summary()
    dnc = getattr(link, "report", None)
    if dnc is not None:
        summary["dnc"] = {
            "chars": dnc.chars,
            "dc3": dnc.dc3,
            "held_s": round(dnc.held_s, 3),
            "longest_hold_s": round(dnc.longest_hold_s, 3),
        }
    if guard.extrapolated:
        summary["extrapolated"] = guard.report()
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"streamed {summary['blocks_sent']} blocks to {args.port}: {summary['model_reloads']} model load(s), "
            f"{summary['recomputed']} block(s) corrected again, latency p99 {summary['latency_ms_p99']} ms"
        )
        _report_extrapolation(guard.report())
    return 0
