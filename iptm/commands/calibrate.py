"""``iptm calibrate``: identify the model from drive logs, with uncertainty and validation."""
from __future__ import annotations

from calib.ingest import FORMATS


def register(sub):
    p = sub.add_parser("calibrate", help="calibrate the model from drive logs (lmfit), with validation",
                       description="Fit battery, fuel, engine-thermal and cabin parameters from one or more drive "
                                   "logs (CSV, MCAP, CAN dumps, MDF4, canonical tables) by maximum a posteriori "
                                   "estimation; report prior and posterior sd, how much the logs informed each "
                                   "parameter, confounded pairs and which drive would inform the rest; validate on "
                                   "held-out logs (channels whose inputs a log lacks are named, not scored), and "
                                   "write the calibration artifact (a parameter file).")
    p.add_argument("logs", nargs="+", metavar="LOG", help="logs to fit")
    p.add_argument("--validate", nargs="+", default=[], metavar="LOG", help="held-out logs to validate on")
    p.add_argument("--params", metavar="BASE", help="prior/base parameter file (default: the default Prius)")
    p.add_argument("--fit", metavar="NAMES", help="comma-separated parameters to estimate (default: all)")
    p.add_argument("--fix", metavar="NAMES", help="comma-separated parameters held at the base value")
    p.add_argument("--out", required=True, metavar="FILE", help="calibration artifact (.toml or .json)")
    p.add_argument("--json", metavar="FILE", help="write the fit and validation figures as JSON")
    p.add_argument("--plots", metavar="DIR", help="write measured-vs-simulated plots of the validation logs and "
                                                "residual diagnostics (residuals, autocorrelation) of every log")
    p.add_argument("--rate", type=float, default=1.0, help="resampling rate in Hz (default 1)")
    p.add_argument("--max-gap", type=float, default=5.0, metavar="S",
                   help="interpolate a channel across gaps up to S seconds (default 5; a channel polled more slowly "
                        "is interpolated up to 2.5 of its own sampling intervals); longer gaps stay unknown")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true",
                   help="refuse damaged logs (default: read what they still hold, say what was lost)")
    p.add_argument("--format", dest="fmt", choices=FORMATS, default=None,
                   help="the format of every LOG (default: detected from its content or extension)")
    p.add_argument("--dbc", help="DBC for CAN logs (default: the shipped Prius DBC)")
    p.add_argument("--bus", help="CAN logs: the bus to decode (default: the one with most frames the DBC knows)")
    p.add_argument("--heater", choices=("off", "estimate"), default=None,
                   help="logs without a heater channel: 'off' declares that the heater did not run (its heat is "
                        "zero); 'estimate' fits one heater draw per log as an unknown input; default: inferred "
                        "from the cabin temperature where it is logged, else estimated")
    p.set_defaults(func=run)


def _names(s):
    return [n.strip() for n in s.split(",") if n.strip()] if s else None


def is_canonical(p) -> bool:
    """A canonical table written by ``iptm ingest --out`` (Parquet, or CSV with its .meta.json)."""
    return p.suffix.lower() == ".parquet" or (p.suffix.lower() == ".csv" and p.with_name(p.name + ".meta.json").exists())


def check_log_format(path, option: str | None):
    """The format of a log the command reads, or a LogFormatError whose fix this command offers: ``option``
    (e.g. "--format") where it has one, else a matching extension."""
    from calib import LogFormatError
    from calib.ingest import detect_format

    try:
        return detect_format(path)
    except LogFormatError as exc:
        if exc.hint is None:  # no such file, a folder, an empty file: nothing to choose
            raise
        fix = (f"give {option} (one of {', '.join(FORMATS)})" if option else
               "name the file with the extension of its format (.csv, .mcap, .log for candump, .asc, .blf, .trc, "
               ".mf4)")
        raise LogFormatError(path, exc.problem, exc.where, fix) from None


def _read(path, rate, strict=False, dbc=None, bus=None, max_gap_s=5.0, fmt=None):
    from pathlib import Path

    from calib.ingest import read_canonical, read_log

    p = Path(path)
    if is_canonical(p):
        return read_canonical(p)
    return read_log(p, fmt=fmt, rate_hz=rate, strict=strict, dbc=dbc, bus=bus, max_gap_s=max_gap_s)


def run(args) -> int:
    import sys
    from pathlib import Path

    from tqdm.auto import tqdm

    from calib.fit import calibrate
    from calib import ParameterError, file_sha256, write_json
    from calib.model import ParameterSet, default_parameters
    from calib.fit import plot_residuals, plot_validation, replay

    ref = ParameterSet.load(args.params) if args.params else None
    known = ref or default_parameters()
    for opt, names in (("--fit", _names(args.fit)), ("--fix", _names(args.fix))):
        for n in names or ():
            if n not in known:  # before the logs are read
                raise ParameterError(f"{opt}: unknown parameter {n!r} ({known.closest_hint(n)})")
    paths = list(args.logs) + list(args.validate)
    for path in paths:  # before the progress bar: a log of unknown format is one message
        if getattr(args, "fmt", None) is None and not is_canonical(Path(path)):
            check_log_format(path, "--format")
    logs, val = [], []
    for i, path in enumerate(tqdm(paths, desc="read logs", disable=args.quiet, leave=False, file=sys.stderr)):
        lg = _read(path, args.rate, getattr(args, "strict", False), getattr(args, "dbc", None),
                   getattr(args, "bus", None), getattr(args, "max_gap", 5.0), getattr(args, "fmt", None))
        if not lg.meta.sha256:
            lg.meta.sha256 = file_sha256(path)
        (logs if i < len(args.logs) else val).append(lg)
    res = calibrate(logs, base=ref, fit=_names(args.fit), fix=_names(args.fix), validate=val or None,
                    progress=not args.quiet, heater=getattr(args, "heater", None))
    res.to_artifact(args.out)
    print(res.report())
    from iptm import present

    print("\n" + present.counts_text(present.parameter_counts(res.params)))
    for line in present.prior_banner(res):
        print(line)
    print(f"\ncalibration artifact: {args.out}")
    if args.plots:
        d = Path(args.plots)
        for lg in val:
            f = d / f"validation_{Path(lg.meta.source).stem}.png"
            plot_validation(replay(lg, res.params), f)
            print(f"plot: {f}")
        for kind, group in (("fitted", logs), ("held_out", val)):
            for lg in group:
                f = d / f"residuals_{kind}_{Path(lg.meta.source).stem}.png"
                plot_residuals(replay(lg, res.params), f, title=f"Residual diagnostics ({kind}): {lg.label()}")
                print(f"plot: {f}")
    if args.json:
        write_json(args.json, res.to_dict())
    return 0
