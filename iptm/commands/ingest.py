"""``iptm ingest FILE...``: read logs, print each one's channel report, write the canonical table(s)."""
from __future__ import annotations

from pathlib import Path

from calib import IptmError, write_json
from calib.ingest import (
    FORMATS,
    channel_report,
    format_report,
    load_map,
    read_streams,
    to_drivelog,
    write_canonical,
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "ingest",
        help="read CSV/MCAP/CAN/MDF4 logs into the canonical drive-log table",
        description=(
            "Read drive logs (CSV with units in the header, MCAP with JSON topics, candump -L/.asc/.blf/.trc "
            "CAN dumps decoded with a DBC, MDF4), print a channel report per log and write the canonical "
            "table (SI units, uniform time base, NaN across long gaps). CSV columns are recognised by name "
            "(`--list-channels` prints the accepted names) with the unit in brackets: 'coolant_temp [degF]'."
        ),
    )
    p.add_argument("files", nargs="*", metavar="FILE", help="log file(s)")
    p.add_argument("--list-channels", action="store_true",
                   help="print the canonical channels, their units and every accepted column name, then exit")
    p.add_argument("--format", dest="fmt", choices=FORMATS, help="force the format (default: detect)")
    p.add_argument("--dbc", help="DBC for CAN logs (default: the shipped Prius DBC)")
    p.add_argument("--bus", help="CAN logs: the bus to decode with the DBC (default: the one with most frames the "
                                 "DBC knows; frames of other buses are counted in a note)")
    p.add_argument("--map", dest="map_file",
                   help="TOML/JSON map with [columns] (CSV/MDF), [topics.\"/topic\"] (MCAP), [signals] (CAN)")
    p.add_argument("--profile", choices=("d3", "ved", "torque", "carscanner"),
                   help="test-data or app format: d3 (Argonne dynamometer .txt), ved (Vehicle Energy Dataset CSV), "
                        "torque (Torque Pro CSV export), carscanner (Car Scanner CSV export); detected from the "
                        "header when omitted")
    p.add_argument("--vehicle", help="VED: vehicle id (VehId) to read")
    p.add_argument("--trip", help="VED: trip id to read")
    p.add_argument("--rate", type=float, default=1.0, help="output rate, Hz (default 1)")
    p.add_argument("--max-gap", type=float, default=5.0,
                   help="never interpolate across gaps longer than this, s (default 5)")
    p.add_argument("--out", help="output .parquet/.csv file (one input) or folder (default: "
                                 f"{DEFAULT_OUT}/<name>.canonical.parquet, so the logs' folder stays untouched)")
    p.add_argument("--json", metavar="FILE", help="write the channel reports as JSON")
    p.add_argument("--strict", action="store_true",
                   help="refuse damaged logs (default: read what they still hold and say what was lost)")
    p.set_defaults(func=run)


#: Where canonical tables go without --out: the working folder's cache, never next to the input (a log
#: folder, such as the bundled logs/, may be read-only or under version control).
DEFAULT_OUT = ".iptm-cache/canonical"


def _out_path(src: Path, out: str | None, n_inputs: int) -> Path:
    if out is None:
        return Path(DEFAULT_OUT) / (src.name + ".canonical.parquet")
    o = Path(out)
    if o.suffix.lower() in (".parquet", ".csv"):
        if n_inputs > 1:
            raise IptmError(f"--out {out} is a file but {n_inputs} logs were given: pass a folder")
        return o
    return o / (src.name + ".canonical.parquet")


def run(args) -> int:
    import sys

    from calib.ingest import describe_channels

    if args.list_channels:
        print(describe_channels())
        return 0
    if not args.files:
        raise IptmError("no log files given (iptm ingest FILE...; --list-channels shows the accepted column names)")
    maps = load_map(args.map_file) if args.map_file else {"columns": {}, "topics": {}, "signals": {}}
    reports = {}
    for f in args.files:
        src = Path(f)
        streams, meta = read_streams(src, fmt=args.fmt, dbc=args.dbc, column_map=maps["columns"] or None,
                                     topic_map=maps["topics"] or None, signal_map=maps["signals"] or None,
                                     strict=args.strict, profile=args.profile, vehicle=args.vehicle,
                                     trip=args.trip, bus=args.bus)
        if not streams:
            raise IptmError(f"{src}: no samples of any canonical channel")
        log = to_drivelog(streams, meta, rate_hz=args.rate, max_gap_s=args.max_gap)
        rep = channel_report(log, streams, max_gap_s=args.max_gap)
        title = f"{log.label()}  ({meta.format}, {log.duration_s:.1f} s, {len(log.data)} rows at {args.rate:g} Hz)"
        print(format_report(rep, title))
        for note in log.meta.notes:
            if note.startswith("warning: "):
                print(f"iptm ingest: {src.name}: {note}", file=sys.stderr)
            else:
                print(f"  note: {note}")
        out = _out_path(src, args.out, len(args.files))
        write_canonical(log, out)
        print(f"  wrote {out}")
        print()
        reports[str(src)] = {
            "output": str(out),
            "synthetic": meta.synthetic,
            "format": meta.format,
            "duration_s": log.duration_s,
            "channels": rep.reset_index().to_dict(orient="records"),
            "notes": log.meta.notes,
            "damage": log.meta.damage,
        }
    if args.json:
        write_json(args.json, reports)
    return 0
