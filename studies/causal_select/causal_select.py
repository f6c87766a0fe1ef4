"""Choose the SDP controller's settings on the training drives only.

For every combination of the grid below (the Markov chain's transition prior ``alpha``, the SDP's
SOC anchor ``w_soc_g_per_s`` and ``soc_bias``, and the controller's share of kinetic energy counted as
charge, ``regen``: ``constant`` 0.5 at every speed, or ``fit``, the line in speed through the training
cycles' stops, :func:`optimize.causal.onestep.fit_stop_regen`), the demand chain is estimated from the training sources
of ``iptm bench causal`` (UDDS, HWFET, US06 and the SYNTHETIC log ``winter_cold_start``), the policy is
built at each ambient, and the controller drives every training cycle at that ambient. Rule: among the
settings that end every training drive within 0.01 of its starting SOC, the least mean corrected-fuel
gap to Thermal-DP of the same drive. Held-out drives are never simulated here.

``--learn-from SET[,SET]`` (sets of ``optimize.causal.compare.DRIVE_SETS``): those drives are added to the
chain's sources, to the stops the regeneration line is fitted to and to the drives the rule judges on:
the settings for a chain that has learnt a car's own trips (``iptm bench causal --own-settings``).

Usage: ``python studies/causal_select/causal_select.py [--learn-from SET] [--out reports/causal-select.json]`` (about
20 minutes on 2 cores). Prints one line per setting and the chosen one.
"""
from __future__ import annotations

import argparse
import itertools
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

GRID = {"alpha": [0.1, 0.3, 1.0], "w_soc_g_per_s": [50.0, 100.0, 200.0], "soc_bias": [0.0, 0.01],
        "regen": ["constant", "fit"]}
SOC_TOL = 0.01
MARGIN = 0.0025  # a quarter of the band


def choose(rows: list) -> dict | None:
    """The rule: settings with every training drive's |dSOC| <= SOC_TOL - MARGIN, then the least mean gap."""
    ok = [r for r in rows if r["max_abs_dsoc"] <= SOC_TOL - MARGIN]
    return min(ok, key=lambda r: r["mean_gap_pct"]) if ok else None


def _union(grids: list) -> dict:
    """The settings tried over several reports, per setting in the order first met."""
    out = {}
    for g in grids:
        for k, vs in g.items():
            out.setdefault(k, [])
            out[k] += [v for v in vs if v not in out[k]]
    return out


def _report(rows: list, out: Path, drives=None, grid=None) -> None:
    from calib import write_json

    best = choose(rows)
    if best is None:
        print(f"no setting ends every training drive within {SOC_TOL - MARGIN:g} of its starting SOC")
    else:
        print(f"chosen: alpha {best['alpha']:g}, w_soc {best['w_soc_g_per_s']:g} g/s, soc_bias {best['soc_bias']:g}, "
              f"regen {best['regen']} ({best['regen_fraction']:.3f}{best['regen_slope_per_mps']:+.4f} v) "
              f"(mean gap {best['mean_gap_pct']:+.2f} %, max |dSOC| {best['max_abs_dsoc']:.4f})")
    write_json(out, {"grid": grid or GRID, "drives": drives, "rule": f"|dSOC| <= {SOC_TOL - MARGIN:g} on every judged drive (the {SOC_TOL:g} "
                     f"band less a margin of {MARGIN:g}), then least mean corrected-fuel gap to Thermal-DP",
                     "rows": rows, "chosen": best})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="reports/causal-select.json")
    ap.add_argument("--rechoose", type=Path, nargs="+", metavar="REPORT",
                    help="apply the rule to the rows of these earlier reports (together)")
    ap.add_argument("--grid", type=json.loads, metavar="JSON",
                    help='the settings to try instead of GRID, e.g. \'{"alpha": [1, 3], "w_soc_g_per_s": [200, 400], '
                         '"soc_bias": [0.01, 0.02], "regen": ["constant", "fit"]}\'')
    ap.add_argument("--learn-from", default="", metavar="SET[,SET]",
                    help="drive sets (e.g. cmap-trip1,cmap-trip2) the chain learns and the rule judges on, besides "
                         "the training drives")
    a = ap.parse_args(argv)
    if a.rechoose is not None:
        ds = [json.loads(p.read_text()) for p in a.rechoose]
        _report([r for d in ds for r in d["rows"]], Path(a.out), ds[0].get("drives"), _union([d.get("grid", {}) for d in ds]))
        return 0

    from calib.ingest import read_log
    from calib.model import default_parameters, simulate
    from iptm.benchmarks.causal import TRAIN_LOG
    from optimize.causal import DemandMarkov, SDPConfig, build_policy
    from calib import IptmError
    from optimize.causal import AMBIENTS, TRAIN_CYCLES, SDPController, drives_of, fit_stop_regen
    from optimize.formulations import DPScenario, solve_thermal

    ps = default_parameters()
    mp = ps.model_params()
    try:
        drives = list(TRAIN_CYCLES) + list(drives_of(a.learn_from, "--learn-from"))
    except IptmError as exc:
        raise SystemExit(str(exc)) from None
    sources = list(TRAIN_CYCLES) + [read_log(TRAIN_LOG)] + drives[len(TRAIN_CYCLES):]
    base = DPScenario()
    ref = {}
    for T in AMBIENTS:
        for c in drives:
            ref[(c, T)] = solve_thermal(ps, replace(base, cycle=c, T_amb=T), None).sim.summary()["fuel_corrected_g"]
    # (regen_fraction, regen_slope_per_mps): half at every speed, or the line fitted to the judged drives' stops
    regen = {"constant": (0.5, 0.0), "fit": fit_stop_regen(mp, drives, base.soc0)}
    print("regen share: " + ", ".join(f"{k} {f0:.3f}{f1:+.4f} v" for k, (f0, f1) in regen.items()), flush=True)
    rows = []
    grid = a.grid or GRID
    missing = [k for k in GRID if k not in grid]
    if missing:
        raise SystemExit(f"--grid: give every setting ({', '.join(missing)} missing)")
    for alpha, w, bias in itertools.product(grid["alpha"], grid["w_soc_g_per_s"], grid["soc_bias"]):
        t0 = time.perf_counter()
        mk = DemandMarkov.estimate(ps, sources, alpha=alpha)
        res = {k: [] for k in grid["regen"]}
        for T in AMBIENTS:
            cfg = replace(SDPConfig(), T_amb=T, Q_heat=base.Q_heat, soc_target=base.soc0, w_soc_g_per_s=w,
                          soc_bias=bias)
            pol = build_policy(ps, mk, cfg, threads=2)
            for kind in grid["regen"]:  # a controller setting: the same tables
                f0, f1 = regen[kind]
                pk = replace(pol, config=replace(cfg, regen_fraction=f0, regen_slope_per_mps=f1))
                for c in drives:
                    scen = replace(base, cycle=c, T_amb=T)
                    s = simulate(ps, scen.load_cycle(), SDPController(mp, pk, T), T_amb=T, soc0=scen.soc0,
                                 T_cl0=scen.T_cl0, T_cab0=scen.T_cab0, Q_heat=scen.Q_heat).summary()
                    res[kind].append({"cycle": c, "T_amb": T, "fuel_corrected_g": s["fuel_corrected_g"],
                                      "gap_to_dp_pct": 100.0 * (s["fuel_corrected_g"] / ref[(c, T)] - 1.0),
                                      "dsoc": s["soc_final"] - s["soc_initial"]})
        for kind in grid["regen"]:
            row = {"alpha": alpha, "w_soc_g_per_s": w, "soc_bias": bias, "regen": kind,
                   "regen_fraction": regen[kind][0], "regen_slope_per_mps": regen[kind][1],
                   "mean_gap_pct": float(np.mean([r["gap_to_dp_pct"] for r in res[kind]])),
                   "max_abs_dsoc": float(max(abs(r["dsoc"]) for r in res[kind])), "drives": res[kind],
                   "seconds": time.perf_counter() - t0}
            row["charge_sustaining"] = row["max_abs_dsoc"] <= SOC_TOL
            rows.append(row)
            print(f"alpha {alpha:<4g} w_soc {w:<5g} soc_bias {bias:<5g} regen {kind:<8}: mean gap to DP "
                  f"{row['mean_gap_pct']:+.2f} %, max |dSOC| {row['max_abs_dsoc']:.4f} "
                  f"({'charge sustaining' if row['charge_sustaining'] else 'NOT'}) [{row['seconds']:.0f} s]", flush=True)
    _report(rows, Path(a.out), drives, grid)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
