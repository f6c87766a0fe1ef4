"""``iptm synth``: write SYNTHETIC drive logs from a known truth parameter set."""
from __future__ import annotations

FORMATS = ("csv", "mcap", "candump", "blf")
EXT = {"csv": ".csv", "mcap": ".mcap", "candump": ".log", "blf": ".blf"}


def register(sub):
    p = sub.add_parser("synth", help="synthesise SYNTHETIC winter drive logs with a known truth",
                       description="Drive the model from a truth parameter set over the bundled winter "
                                   "scenarios and write logs with realistic sensor effects, plus the truth "
                                   "parameters next to them. Every file is labelled SYNTHETIC.")
    p.add_argument("--out", default="logs", metavar="DIR", help="output folder (default logs/)")
    p.add_argument("--seed", type=int, default=2017, help="seed of the truth draw and the sensor noise")
    p.add_argument("--truth", metavar="FILE", help="truth parameter file (default: drawn with --seed)")
    p.add_argument("--scenario", action="append", help="scenario name (repeatable; default all bundled)")
    p.add_argument("--formats", default=None,
                   help="comma-separated: " + ",".join(FORMATS) + " (default all; csv only for --simulator "
                        "fastsim and --perturbed)")
    p.add_argument("--simulator", choices=("model", "fastsim"), default="model",
                   help="model: our model from a truth parameter set (default); fastsim: NREL FASTSim 3's thermal "
                        "Hyundai Sonata hybrid at -7 and 22 degC (needs the fastsim extra)")
    p.add_argument("--perturbed", action="store_true",
                   help="our own plant with structure the fitter does not share (other efficiency curve, "
                        "thermostat range, lagged coolant sensor, biased fuel meter, ordinary drives); the truth "
                        "is written as SYNTHETIC_perturbed_truth.json")
    p.add_argument("--json", metavar="FILE", help="write the list of files and true summaries as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from calib import IptmError, write_json
    from calib.model import ParameterSet
    from calib import BUNDLED, draw_truth, synthesise
    from calib.ingest import write_streams

    if args.simulator == "fastsim" or args.perturbed:
        return _run_other(args)
    fmts = [f.strip() for f in (args.formats or ",".join(FORMATS)).split(",") if f.strip()]
    bad = [f for f in fmts if f not in FORMATS]
    if bad:
        raise IptmError(f"unknown format(s) {bad}; choose from {', '.join(FORMATS)}")
    scen = {s.name: s for s in BUNDLED}
    names = args.scenario or list(scen)
    for n in names:
        if n not in scen:
            raise IptmError(f"unknown scenario {n!r}; bundled: {', '.join(scen)}")
    truth = ParameterSet.load(args.truth) if args.truth else draw_truth(args.seed)
    out = Path(args.out)
    truth_file = out / "truth_params.toml"
    truth.meta["note"] = "SYNTHETIC: the truth from which the logs next to this file were simulated"
    truth.save(truth_file)
    written = {"truth": str(truth_file), "logs": {}}
    for i, n in enumerate(names):
        sim, streams, meta = synthesise(scen[n], truth, seed=args.seed + i)
        files = []
        for f in fmts:
            path = out / f"{n}{EXT[f]}"
            write_streams(streams, meta, path, f)
            files.append(str(path))
        s = sim.summary()
        written["logs"][n] = {"files": files, "true_fuel_g": s["fuel_g"], "duration_s": s["duration_s"],
                              "description": scen[n].description}
        print(f"SYNTHETIC {n}: {s['duration_s']:.0f} s, {s['fuel_g']:.0f} g fuel -> {', '.join(files)}")
    print(f"truth parameters: {truth_file}")
    if args.json:
        write_json(args.json, written)
    return 0


def _run_other(args) -> int:
    """The test cars that are not our model: FASTSim 3 or the perturbed-structure plant (CSV logs)."""
    from calib import IptmError, write_json

    if args.formats and [f.strip() for f in args.formats.split(",") if f.strip()] != ["csv"]:
        raise IptmError("--simulator fastsim and --perturbed write CSV logs only (engine and battery power "
                        "channels have no MCAP/CAN layout): use --formats csv")
    if args.simulator == "fastsim" and args.perturbed:
        raise IptmError("choose one of --simulator fastsim and --perturbed")
    if args.truth or args.scenario:
        raise IptmError("--truth and --scenario apply to --simulator model only")
    if args.perturbed:
        from testcars.synth_perturbed import write_perturbed_logs

        info = write_perturbed_logs(args.out, seed=args.seed)
    else:
        from testcars.synth_fastsim import write_fastsim_logs

        info = write_fastsim_logs(args.out, seed=args.seed)
    if args.json:
        write_json(args.json, info)
    return 0
