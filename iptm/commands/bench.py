"""``iptm bench``: benchmarks that print speed and memory figures (never asserted in tests).

A benchmark whose cases failed has failed: the command exits with status 1 and says which suites failed
and why. A suite reports failed cases as ``failures`` (a list of one-line texts) in its result, printed by
the suite before any figure and without any figure computed from them; a suite that raises fails whole.
"""
from __future__ import annotations

import importlib
import sys

SUITES = {
    "sim": "iptm.benchmarks.sim",
    "epa": "iptm.benchmarks.epa",
    "ingest": "iptm.benchmarks.ingest",
    "calib": "iptm.benchmarks.calib",
    "calib-bundled": "iptm.benchmarks.calib_bundled",
    "dp": "iptm.benchmarks.dp",
    "sweep": "iptm.benchmarks.sweep",
    "fuzz": "iptm.benchmarks.fuzz",
    "causal": "iptm.benchmarks.causal",
    "plan": "iptm.benchmarks.plan",
    "causal-route": "iptm.benchmarks.causal_route",
}
#: The keys of ``optimize.causal.compare.DRIVE_SETS`` (spelt here so that ``--help`` loads no numerics;
#: tests/test_causal_drives.py checks they agree).
DRIVE_SET_NAMES = ("test-cycles", "cmap-trip1", "cmap-trip2", "cmap-trip3", "wltc-high-cmap-trip4")


def register(sub):
    p = sub.add_parser("bench", help="run benchmarks and print time, memory and throughput",
                       description="Benchmarks: sim (simulation speed, EPA table), epa (default car against EPA: warm "
                                   "cycles, warm and cold FTP), ingest (30-min CAN dump), calib (calibration on "
                                   "test cars that are not our model: FASTSim, perturbed synthesiser), "
                                   "calib-bundled (truth recovery on the bundled-size logs), dp (three DP "
                                   "formulations on paper grids), sweep (distributed study speed-up), fuzz (mutated "
                                   "inputs to every reader: read / recovered / clean error / escape counts, and "
                                   "random truncations of valid logs), causal (SDP and ECMS on held-out drives vs DP and "
                                   "rule-based; policy build and step time), plan (drive plans in closed loop on FASTSim and the "
                                   "perturbed plant), causal-route (the ECMS told the route: no route, length only, route; the "
                                   "trip-length error table).")
    p.add_argument("suite", nargs="*", default=["sim", "dp"], help=f"any of {', '.join(SUITES)} or 'all' "
                                                                    "(default: sim dp)")
    p.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke check")
    p.add_argument("--json", metavar="FILE", help="write all figures as JSON")
    p.add_argument("--n", type=int, metavar="N", help="fuzz: mutated inputs per reader (default 10000, --quick 300)")
    p.add_argument("--seed", type=int, default=0, help="fuzz: seed of the mutations (default 0)")
    p.add_argument("--valuation", choices=("corrected", "continuation", "both"), default="corrected",
                   help="causal: how final states are valued: corrected (fuel equivalents of the stored energy, "
                        "default) or continuation (the rule-based controller's fuel over UDDS six times from the final "
                        "state; Thermal-DP with the 'continued' terminal)")
    p.add_argument("--drives", choices=DRIVE_SET_NAMES, default="test-cycles",
                   help="causal: the drives compared on: test-cycles (six published drives, looked at while the "
                        "settings were developed), cmap-trip1 (the first qualifying CMAP trip of eight cars, first "
                        "simulated after the SDP's settings were last chosen), cmap-trip2 (the second trip of seven "
                        "of those cars), cmap-trip3 (the third trip of four) or wltc-high-cmap-trip4 (the WLTC high "
                        "and extra-high phases and a fourth CMAP trip, driven by no controller before the study of "
                        "the ECMS tuned on each drive)")
    p.add_argument("--learn-from", metavar="SET[,SET]",
                   help="causal: also run the SDP on a demand chain that learnt these drive sets too (rows sdp_own), "
                        "e.g. --drives cmap-trip2 --learn-from cmap-trip1: each car's earlier trip")
    p.add_argument("--own-settings", metavar="FILE",
                   help="causal: the settings of sdp_own, the 'chosen' row of a studies/causal_select/causal_select.py report "
                        "(default: the SDP's own)")
    p.add_argument("--halve", action="store_true",
                   help="dp: also solve the converged Thermal-Cabin-DP grid with every step halved (about 32 times "
                        "its time) and print the change")
    p.set_defaults(func=run)


def run(args) -> int:
    from calib import IptmError, write_json

    names = list(SUITES) if "all" in args.suite else args.suite
    for n in names:
        if n not in SUITES:
            raise IptmError(f"unknown benchmark {n!r}; choose from {', '.join(SUITES)} or all")
    results, failed = {}, {}
    for n in names:
        try:
            mod = importlib.import_module(SUITES[n])
        except ModuleNotFoundError as exc:
            if exc.name == SUITES[n]:
                print(f"== {n}: not available in this version")
                continue
            raise
        print(f"== {n}")
        extra = {"n": args.n, "seed": args.seed} if n == "fuzz" else {}
        if n == "causal":
            from optimize.causal import drives_of

            sets = [x for x in (args.learn_from or "").split(",") if x]
            drives_of(sets, "bench causal: --learn-from")
            if args.drives in sets:
                raise IptmError(f"bench causal: --learn-from {args.drives} is also the test set; "
                                "learn from another set than --drives")
            own = None
            if args.own_settings:
                if not sets:
                    raise IptmError("bench causal: --own-settings needs --learn-from (the chain they were chosen for)")
                own = _chosen_settings(args.own_settings)
            extra = {"valuation": args.valuation, "drives": args.drives, "learn_from": sets, "own_settings": own}
        if n == "dp":
            extra = {"halve": args.halve}
        if n == "causal-route":
            extra = {"valuation": args.valuation, "drives": args.drives}
        elif n == "causal" and args.valuation == "both":
            raise IptmError("bench causal: --valuation corrected or continuation (both is for causal-route)")
        try:
            results[n] = mod.run(quick=args.quick, **extra)
        except IptmError:
            raise
        except Exception as exc:  # noqa: BLE001 - a crashed suite is a failed benchmark; the others still run
            msg = (str(exc).strip().splitlines() or [""])[0]
            print(f"FAILED: {n}: {type(exc).__name__}: {msg}", flush=True)
            results[n] = {"failures": [f"{type(exc).__name__}: {msg}"]}
        bad = suite_failures(results[n])
        if bad:
            failed[n] = bad
    if args.json:
        write_json(args.json, results)
    if failed:
        print("iptm bench: FAILED: " + "; ".join(f"{n}: {len(b)} failure(s), first: {b[0]}" for n, b in failed.items()),
              file=sys.stderr)
        return 1
    return 0


def suite_failures(result) -> list[str]:
    """The failures a suite's result reports: its ``failures`` lists and ``calibration_error`` texts, at any
    depth of the result."""
    out = []
    if isinstance(result, dict):
        for k, v in result.items():
            if k == "failures" and isinstance(v, list):
                out += [str(x) for x in v]
            elif k == "calibration_error" and v:
                out.append(f"calibration failed: {v}")
            else:
                out += suite_failures(v)
    elif isinstance(result, list):
        for v in result:
            out += suite_failures(v)
    return out


def _chosen_settings(path: str) -> dict:
    """The ``chosen`` row of a ``studies/causal_select/causal_select.py`` report, or a clear error."""
    import json

    from calib import IptmError
    from optimize.causal import SELECTED

    try:
        row = json.loads(open(path, encoding="utf-8").read()).get("chosen")
    except (OSError, ValueError) as exc:
        raise IptmError(f"--own-settings {path}: cannot read it as JSON ({exc}); give a report of "
                        "studies/causal_select/causal_select.py") from None
    missing = [k for k in SELECTED if not isinstance(row, dict) or k not in row]
    if missing:
        raise IptmError(f"--own-settings {path}: no chosen setting with {', '.join(missing)}; the selection chose "
                        "none, or this is not a report of studies/causal_select/causal_select.py")
    return {k: row[k] for k in SELECTED}
