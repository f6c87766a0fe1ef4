"""The ECMS's fuel against its charge keeping, on the training drives only.

For every combination of the grid below (the base equivalence factor ``s0``, the SOC feedback gain ``k_s``,
the coolant feedback gain ``k_mu`` and the share of kinetic energy counted as charge ``regen_fraction``;
the rest as :class:`optimize.causal.ecms.ECMSParams`), the ECMS drives every training cycle (UDDS, HWFET,
US06) at -10 and 0 degC from the default scenario, and three figures are kept: the mean corrected-fuel gap
to Thermal-DP of the same drive, the largest |SOC - SOC_0| at the drives' ends, and the largest at any stop
(the first standstill sample after motion, the drive's end included). A causal controller does not know at
which stop its drive ends, and its decisions up to a stop do not depend on what follows, so the SOC at
each stop is the final SOC of the drive that ends there.

Two rules are applied, each the SDP's (``studies/causal_select/causal_select.py``): among the settings within 0.0075 of
SOC_0 (the 0.01 band less a quarter of it), the least mean gap; ``ends`` judges the drives' ends only,
``stops`` every stop. Held-out drives are never simulated here.

Usage: ``python studies/ecms_select/ecms_select.py [--out reports/ecms-select.json] [--plot FILE.png]`` (about 5
minutes on 2 cores: six Thermal-DP solutions, then 960 ECMS drives); ``--replot REPORT --plot FILE.png``
draws an earlier report again.
"""
from __future__ import annotations

import argparse
import itertools
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

GRID = {"s0": [0.6, 0.7, 0.8, 0.9], "k_s": [5.0, 10.0, 20.0, 40.0, 80.0], "k_mu": [0.0, 0.03],
        "regen_fraction": [0.2, 0.4, 0.6, 0.8]}
SOC_TOL = 0.01
MARGIN = 0.0025
RULES = {"ends": "max_abs_dsoc_end", "stops": "max_abs_dsoc_stop"}


def choose(rows: list, key: str = "max_abs_dsoc_end") -> dict | None:
    ok = [r for r in rows if r[key] <= SOC_TOL - MARGIN]
    return min(ok, key=lambda r: r["mean_gap_pct"]) if ok else None


def stop_indices(v) -> np.ndarray:
    """The first standstill sample after motion, for every stop of a speed trace (the end included when
    the trace ends at rest)."""
    v = np.asarray(v, float)
    return np.flatnonzero((v[1:] == 0.0) & (v[:-1] > 0.0)) + 1


def front(rows: list) -> list:
    """The settings no other beats on both the mean gap and the largest |dSOC| at a stop."""
    def beats(o, r):
        a, b = (o["mean_gap_pct"], o["max_abs_dsoc_stop"]), (r["mean_gap_pct"], r["max_abs_dsoc_stop"])
        return a[0] <= b[0] and a[1] <= b[1] and a != b

    return sorted((r for r in rows if not any(beats(o, r) for o in rows)), key=lambda r: r["max_abs_dsoc_stop"])


def plot(rows: list, committed: dict | None, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calib import save_figure

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.scatter([r["max_abs_dsoc_stop"] for r in rows], [r["mean_gap_pct"] for r in rows], s=12, color="0.6",
               label="a setting (s0, k_s, k_mu, share)")
    f = front(rows)
    ax.plot([r["max_abs_dsoc_stop"] for r in f], [r["mean_gap_pct"] for r in f], "-o", color="C0", ms=4,
            label="best trade-off")
    if committed:
        ax.plot(committed["max_abs_dsoc_stop"], committed["mean_gap_pct"], "s", color="C3", ms=8,
                label="committed ECMS")
    ax.axvline(SOC_TOL - MARGIN, color="k", ls=":", lw=1)
    ax.axvline(SOC_TOL, color="k", ls="--", lw=1, label="charge-sustaining band (and its margin)")
    ax.set_xscale("log")
    ax.set_xlabel("largest |SOC - SOC$_0$| at any stop of the training drives")
    ax.set_ylabel("mean corrected-fuel gap to Thermal-DP (%)")
    ax.set_title("ECMS on UDDS, HWFET, US06 at -10 and 0 degC", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("reports/ecms-select.json"))
    ap.add_argument("--plot", type=Path, help="draw the trade-off (PNG)")
    ap.add_argument("--replot", type=Path, metavar="REPORT", help="only draw --plot from an earlier report")
    a = ap.parse_args(argv)
    if a.replot:
        import json

        if not a.plot:
            raise SystemExit("--replot: give --plot FILE.png")
        d = json.loads(a.replot.read_text())
        plot(d["rows"], d["committed"], a.plot)
        return 0

    from calib import write_json
    from calib.model import default_parameters
    from optimize.causal import AMBIENTS, TRAIN_CYCLES, ECMSParams, drive_ecms
    from optimize.formulations import DPScenario, solve_thermal

    ps = default_parameters()
    mp = ps.model_params()
    runs = [replace(DPScenario(), cycle=c, T_amb=T) for T in AMBIENTS for c in TRAIN_CYCLES]
    ref = {(s.cycle, s.T_amb): solve_thermal(ps, s, None).sim.summary()["fuel_corrected_g"] for s in runs}
    cycles = {(s.cycle, s.T_amb): s.load_cycle() for s in runs}
    rows = []
    for s0, k_s, k_mu, rf in itertools.product(*GRID.values()):
        t0 = time.perf_counter()
        ep = replace(ECMSParams(), s0=s0, k_s=k_s, k_mu=k_mu, regen_fraction=rf)
        drives = []
        for s in runs:
            cyc = cycles[(s.cycle, s.T_amb)]
            sim = drive_ecms(ps, mp, cyc, s, replace(ep, Q_heat_W=s.Q_heat, soc_target=s.soc0))
            summ = sim.summary()
            soc = np.asarray(sim.soc)
            at_stops = soc[stop_indices(cyc.v)] - soc[0]
            drives.append({"cycle": s.cycle, "T_amb": s.T_amb, "fuel_corrected_g": summ["fuel_corrected_g"],
                           "gap_to_dp_pct": 100.0 * (summ["fuel_corrected_g"] / ref[(s.cycle, s.T_amb)] - 1.0),
                           "dsoc": summ["soc_final"] - summ["soc_initial"],
                           "dsoc_stops": (float(at_stops.min()), float(at_stops.max()))})
        row = {"s0": s0, "k_s": k_s, "k_mu": k_mu, "regen_fraction": rf,
               "mean_gap_pct": float(np.mean([d["gap_to_dp_pct"] for d in drives])),
               "max_abs_dsoc_end": float(max(abs(d["dsoc"]) for d in drives)),
               "max_abs_dsoc_stop": float(max(max(abs(x) for x in d["dsoc_stops"] + (d["dsoc"],)) for d in drives)),
               "drives": drives, "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(f"s0 {s0:g}, k_s {k_s:g}, k_mu {k_mu:g}, share {rf:g}: mean gap {row['mean_gap_pct']:+.2f} %, "
              f"max |dSOC| at the ends {row['max_abs_dsoc_end']:.4f}, at any stop {row['max_abs_dsoc_stop']:.4f}",
              flush=True)
    d = ECMSParams()
    committed = next((r for r in rows if all(r[k] == getattr(d, k) for k in GRID)), None)

    def say(what, r):
        print(f"{what}: " + ("none" if r is None else
              f"s0 {r['s0']:g}, k_s {r['k_s']:g}, k_mu {r['k_mu']:g}, share {r['regen_fraction']:g} (mean gap "
              f"{r['mean_gap_pct']:+.2f} %, max |dSOC| at the ends {r['max_abs_dsoc_end']:.4f}, at any stop "
              f"{r['max_abs_dsoc_stop']:.4f})"))

    say("committed setting", committed)
    chosen = {rule: choose(rows, key) for rule, key in RULES.items()}
    for rule, r in chosen.items():
        say(f"chosen judging the {rule}", r)
    print("best trade-off (largest |dSOC| at a stop, mean gap): "
          + ", ".join(f"({r['max_abs_dsoc_stop']:.4f}, {r['mean_gap_pct']:+.2f} %)" for r in front(rows)))
    write_json(a.out, {"grid": GRID, "drives": [f"{s.cycle}@{s.T_amb:g}" for s in runs],
                       "reference_g": {f"{c}@{T:g}": v for (c, T), v in ref.items()},
                       "rule": f"|dSOC| <= {SOC_TOL - MARGIN:g} on every training drive (ends: at its end; stops: "
                               "at every stop), then least mean corrected-fuel gap to Thermal-DP",
                       "rows": rows, "committed": committed, "chosen": chosen,
                       "front": [{k: r[k] for k in list(GRID) + ["mean_gap_pct", "max_abs_dsoc_stop"]}
                                 for r in front(rows)]})
    if a.plot:
        plot(rows, committed, a.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
