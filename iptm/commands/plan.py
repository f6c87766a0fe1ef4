"""``iptm plan``: design the drive (road or dyno) that would inform the parameters a calibration left weak."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("plan", help="design a drive that informs the parameters a calibration left weak",
                       description="From a calibration artifact (posterior means and sd), design a drive a driver "
                                   "(or a dynamometer) can follow: standard-cycle segments, stops, a heater on/off "
                                   "schedule and the soak state at the start, chosen by an exhaustive search of a "
                                   "finite design space to minimise the predicted posterior uncertainty of the "
                                   "targeted parameters (D-optimal on the linearised coolant and cabin replays, "
                                   "the rule-based controller deciding engine and battery). Writes the plan CSV and "
                                   "prints the predicted posterior sd (docs/drive_plans.md).")
    p.add_argument("artifact", metavar="ARTIFACT", help="calibration artifact (iptm calibrate --out)")
    p.add_argument("--minutes", type=float, default=20.0, help="length of the plan (default 20)")
    p.add_argument("--ambient", type=float, metavar="C", help="forecast ambient temperature, degC (road plans)")
    p.add_argument("--soak-degC", dest="soak", type=float, nargs="+", metavar="C",
                   help="road: candidate coolant temperatures at the start (default: the ambient, a cold soak); "
                        "dyno: candidate cell soak temperatures (required)")
    p.add_argument("--dyno", action="store_true", help="a dynamometer plan: whole standard cycles from a cell soak")
    p.add_argument("--target", nargs="+", metavar="NAME",
                   help="parameters to inform (default: the two with the largest posterior sd relative to prior)")
    p.add_argument("--criterion", choices=("d", "sd"), default="d",
                   help="d: D-optimal on the targets (default); sd: mean predicted sd relative to now")
    p.add_argument("--no-heater-schedule", action="store_true",
                   help="keep the climate control on throughout (a car whose heater cannot be switched off)")
    p.add_argument("-o", "--out", default="plan.csv", metavar="CSV", help="plan CSV (default plan.csv)")
    p.add_argument("--plot", metavar="PNG", help="write the plan figure")
    p.add_argument("--json", metavar="FILE", help="write the plan summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    import sys

    from tqdm.auto import tqdm

    from calib.design import ArtifactPrior, make_plan, plot_plan, write_plan_csv
    from calib.design import header_lines
    from calib import write_json

    prior = ArtifactPrior.load(args.artifact)
    targets = args.target or prior.weakest()
    bars = []

    def progress(done, total):
        if not bars:  # opened at the first scored design: an input refused before shows no bar
            bars.append(tqdm(desc="score designs", total=total, disable=args.quiet, leave=False, file=sys.stderr))
        bars[0].total = total
        bars[0].update(done - bars[0].n)

    try:
        plan = make_plan(prior, targets, minutes=args.minutes, ambient=args.ambient, soaks=args.soak,
                         dyno=args.dyno, criterion=args.criterion, heater=not args.no_heater_schedule,
                         progress=progress)
    finally:
        for b in bars:
            b.close()
    if not args.target:
        print("targets (largest posterior sd relative to prior): "
              + ", ".join(f"{n} ({100 * prior.ratio(n):.0f} % of prior sd)" for n in targets))
    for line in header_lines(plan):
        print(line)
    s = plan.searched
    print(f"searched: {s['stage1_sequences']} segment sequences, then {s['stage2_candidates']} heater/soak variants of "
          f"the best; {s['infeasible']} infeasible")
    write_plan_csv(plan, args.out)
    print(f"plan: {args.out}")
    if args.plot:
        plot_plan(plan, args.plot)
        print(f"plot: {args.plot}")
    if args.json:
        write_json(args.json, {"design": plan.design.describe(), "targets": plan.table(), "criterion": plan.criterion,
                               "value": plan.value, "searched": {k: v for k, v in s.items()},
                               "noise": {k: {"sd_degC": v[0], "source": v[1]} for k, v in plan.noise.items()},
                               "best": plan.ranking, "csv": args.out})
    return 0
