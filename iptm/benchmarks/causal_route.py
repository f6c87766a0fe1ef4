"""Benchmark: the ECMS with no route, the trip length only, and the route (length and road classes), on the
held-out drives of the causal benchmark against Thermal-DP and the rule tuned on each drive
(``docs/route_aware.md``: the protocol), with the trip-length error study, the controller step time and
the time to build the per-class co-states.

Thermal-DP and the tuned rule are read from the committed reports ``reports/causal-SET-VALUATION.json``
(``iptm bench causal --drives SET --valuation VALUATION --json FILE``); the ECMS rows are driven here.

``python -m iptm.benchmarks.causal_route [--drives test-cycles] [--valuation both] [--json FILE]``
"""
from __future__ import annotations

import json
import time
from pathlib import Path

ROWS = {"none": "no route", "length": "length only", "route": "route"}


def _reference(drives: str, valuation: str) -> dict:
    from calib import IptmError

    rep = Path("reports") / f"causal-{drives}-{valuation}.json"
    if not rep.is_file():
        raise IptmError(f"{rep}: missing; run `iptm bench causal --drives {drives} --valuation {valuation} "
                        f"--json {rep}` first (it solves Thermal-DP and tunes the rule on every drive)")
    rows = json.loads(rep.read_text())["causal"]["table"]
    return {(r["cycle"], float(r["T_amb"]), r["strategy"]): r for r in rows}


def run(quick: bool = False, valuation: str = "both", drives: str = "test-cycles", robustness: bool = True) -> dict:
    from dataclasses import replace

    import numpy as np

    from calib import IptmError
    from calib import default_parameters
    from optimize.causal import AMBIENTS, DRIVE_SETS, step_timing, valuation_scenario, valued_fuel
    from optimize.causal import GOAL_GAP_PCT, SOC_TOL, VALUATIONS
    from optimize.causal import ENDS_EARLY_AT, KNOWLEDGE, LENGTH_ERRORS, class_costates, drive_route, ended_early, route_of_cycle
    from optimize.causal import RouteECMSController, RouteECMSParams
    from optimize import DPScenario

    vals = VALUATIONS if valuation == "both" else (valuation,)
    if any(v not in VALUATIONS for v in vals) or drives not in DRIVE_SETS:
        raise IptmError(f"bench causal-route: valuation {valuation!r} / drives {drives!r}; choose valuation from "
                        f"both, {', '.join(VALUATIONS)} and drives from {', '.join(DRIVE_SETS)}")
    ps = default_parameters()
    mp = ps.model_params()
    rp = RouteECMSParams()
    cycles = DRIVE_SETS[drives][:1] if quick else DRIVE_SETS[drives]
    ambients = AMBIENTS[:1] if quick else AMBIENTS
    refs = {v: _reference(drives, v) for v in vals}
    print(f"route-aware ECMS {rp.to_dict()}\ndrives ({drives}): {', '.join(cycles)}; ambients "
          f"{', '.join(f'{a:g}' for a in ambients)} degC; Thermal-DP and the rule tuned on the drive from "
          f"reports/causal-{drives}-VALUATION.json", flush=True)
    class_s, build_s = {}, {}
    for T in ambients:
        t0 = time.perf_counter()
        class_s[T] = class_costates(ps, rp, T)
        build_s[T] = time.perf_counter() - t0
        print(f"per-class co-states at {T:g} degC: " + ", ".join(f"{c} {s:.3f}" for c, s in class_s[T].items())
              + f" (built in {build_s[T]:.1f} s)", flush=True)
    rows, drift = [], []
    for v in vals:
        ref = refs[v]
        for T in ambients:
            for c in cycles:
                scen = valuation_scenario(replace(DPScenario(), cycle=c, T_amb=T), v)
                cyc = scen.load_cycle()
                route = route_of_cycle(cyc)
                dp = ref[(c, T, "dp_thermal")]["fuel_corrected_g"]
                rule = ref[(c, T, "rule_tuned")]["fuel_corrected_g"]
                for kn in KNOWLEDGE:
                    sim = drive_route(ps, scen, cyc, route, kn, rp, class_s[T])
                    f = float(valued_fuel(sim, scen, v)[0])
                    if kn == "none":
                        drift.append(f - ref[(c, T, "ecms")]["fuel_corrected_g"])
                    rows.append({"valuation": v, "cycle": c, "T_amb": T, "row": ROWS[kn], "fuel_g": f,
                                 "gap_to_dp_pct": 100.0 * (f / dp - 1.0), "vs_rule_pct": 100.0 * (1.0 - f / rule),
                                 "dsoc": float(sim.soc[-1] - scen.soc0), "route": route.describe()})
    import pandas as pd

    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.max_columns", 20, "display.max_rows", 500):
        print("\nvalued fuel (g); gap to Thermal-DP and saving against the rule tuned on the drive in %; "
              "dsoc = SOC_N - SOC_0")
        print(df.drop(columns="route").to_string(index=False, float_format=lambda x: f"{x:.4f}" if abs(x) < 0.1
                                                   else f"{x:.2f}"))
    print(f"\n'no route' against the report's ecms row: {min(drift):+.3f} to {max(drift):+.3f} g "
          "(non-zero: the model changed since the report)")
    goals = {}
    for (v, r), g in df.groupby(["valuation", "row"], sort=False):
        within, better, cs = g.gap_to_dp_pct <= GOAL_GAP_PCT, g.vs_rule_pct > 0, g.dsoc.abs() <= SOC_TOL
        goals[f"{v}/{r}"] = {"runs": int(len(g)), "within_3pct": int(within.sum()), "better_than_rule": int(better.sum()),
                             "charge_sustaining": int(cs.sum()), "max_gap_pct": float(g.gap_to_dp_pct.max()),
                             "mean_gap_pct": float(g.gap_to_dp_pct.mean()),
                             "dsoc_range": (float(g.dsoc.min()), float(g.dsoc.max()))}
        x = goals[f"{v}/{r}"]
        print(f"{v:12s} {r:12s}: within {GOAL_GAP_PCT:g} % of DP on {x['within_3pct']}/{x['runs']} (max "
              f"{x['max_gap_pct']:.2f} %, mean {x['mean_gap_pct']:.2f} %), better than the tuned rule on "
              f"{x['better_than_rule']}/{x['runs']}, |dSOC| <= {SOC_TOL:g} on {x['charge_sustaining']}/{x['runs']} "
              f"(dSOC {x['dsoc_range'][0]:+.4f} to {x['dsoc_range'][1]:+.4f})")
    robust = []
    if robustness:
        print(f"\ntrip-length error (corrected valuation): announced length x {', x '.join(f'{f:g}' for f in LENGTH_ERRORS)}"
              f"; a trip that ends at {100 * ENDS_EARLY_AT:g} % of its distance (the full route announced). "
              "fuel against the exact length (ended early: against no route on the same short trip), in %")
        for T in ambients:
            for c in cycles:
                scen = replace(DPScenario(), cycle=c, T_amb=T)
                cyc = scen.load_cycle()
                route = route_of_cycle(cyc)
                short = ended_early(cyc, ENDS_EARLY_AT)
                none_short = drive_route(ps, scen, short, route, "none", rp)
                f_ns = valued_fuel(none_short, scen, "corrected")[0]
                for kn in ("length", "route"):
                    exact = drive_route(ps, scen, cyc, route, kn, rp, class_s[T])
                    f_ex = valued_fuel(exact, scen, "corrected")[0]
                    r = {"cycle": c, "T_amb": T, "row": ROWS[kn], "dsoc_exact": float(exact.soc[-1] - scen.soc0),
                         "dsoc_none_ended_early": float(none_short.soc[-1] - scen.soc0)}
                    for f in LENGTH_ERRORS:
                        s = drive_route(ps, scen, cyc, route.scaled(f), kn, rp, class_s[T])
                        r[f"dsoc_x{f:g}"] = float(s.soc[-1] - scen.soc0)
                        r[f"fuel_x{f:g}_pct"] = 100.0 * (valued_fuel(s, scen, "corrected")[0] / f_ex - 1.0)
                    s = drive_route(ps, scen, short, route, kn, rp, class_s[T])
                    r["dsoc_ended_early"] = float(s.soc[-1] - scen.soc0)
                    r["fuel_ended_early_vs_none_pct"] = 100.0 * (valued_fuel(s, scen, "corrected")[0] / f_ns - 1.0)
                    robust.append(r)
        rdf = pd.DataFrame(robust)
        with pd.option_context("display.width", 220, "display.max_columns", 20, "display.max_rows", 500):
            print(rdf.to_string(index=False, float_format=lambda x: f"{x:+.4f}" if abs(x) < 0.1 else f"{x:+.2f}"))
        ds = rdf[[k for k in rdf.columns if k.startswith("dsoc_") and k != "dsoc_none_ended_early"]].abs()
        print(f"largest |dSOC| with a wrong length or an early end: {ds.drop(columns='dsoc_exact').max().max():.4f} "
              f"(goal <= 0.02); the causal ECMS on the trips that end early: "
              f"{rdf.dsoc_none_ended_early.abs().max():.4f}")
    route = route_of_cycle("artemis_urban")
    ctrl = RouteECMSController(mp, route, rp, -10.0, class_s[ambients[0]])
    step = step_timing(ps, ctrl)
    print(f"\ncontroller step (route): median {step['median_s'] * 1e6:.1f} us, p99 {step['p99_s'] * 1e6:.1f} us, "
          f"max {step['max_s'] * 1e3:.2f} ms over {step['calls']} calls (goal < 1 ms)")
    print("building the per-class co-states: " + ", ".join(f"{b:.1f} s at {T:g} degC" for T, b in build_s.items())
          + " (goal < 60 s; the length-only controller builds nothing)")
    return {"settings": rp.to_dict(), "drives": drives, "valuations": list(vals), "table": rows, "goals": goals,
            "robustness": robust, "step": step, "build_s": {str(T): b for T, b in build_s.items()},
            "class_costates": {str(T): s for T, s in class_s.items()},
            "no_route_drift_g": [float(np.min(drift)), float(np.max(drift))]}


def main(argv=None) -> int:
    import argparse

    from calib import IptmError

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drives", default="test-cycles")
    ap.add_argument("--valuation", default="both")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-robustness", action="store_true")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    try:
        res = run(a.quick, a.valuation, a.drives, not a.no_robustness)
    except IptmError as exc:
        print(f"causal_route: error: {exc}")
        return 2
    if a.json:
        from calib import write_json

        write_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
