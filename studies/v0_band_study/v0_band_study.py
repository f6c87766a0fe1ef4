"""Thermal-DP's predicted cost V_0(x0) against its forward-simulated objective, by terminal condition and
grid: where the gap of the ``continued`` terminal (held to a SOC band or not) comes from.

    .venv/bin/python studies/v0_band_study/v0_band_study.py [--cycle nycc] [--ambient 0]

Prints one JSON line per case: the terminal (``valued``; ``continued`` with SOC_N free; with the causal
comparison's band of 0.01) on the paper's grids, then the banded case with the SOC step, the coolant step,
the battery-power step and all three halved. ``gap_pct`` is ``V_0 / objective - 1``; the objective is the
DP's own (``dp_objective``: fuel plus the interpolated terminal cost at the run's final state).
"""
from __future__ import annotations

import argparse
import json
import os
import time

from calib.model import default_parameters
from optimize.formulations import DPGrids, DPScenario, dp_objective, solve_thermal

CASES = [("valued", {}, {}), ("continued, SOC_N free", {"terminal": "continued"}, {}),
         ("continued, band 0.01", {"terminal": "continued", "cont_soc_band": 0.01}, {}),
         ("continued, band 0.01", {"terminal": "continued", "cont_soc_band": 0.01}, {"soc": 0.005}),
         ("continued, band 0.01", {"terminal": "continued", "cont_soc_band": 0.01}, {"tcl": 0.5}),
         ("continued, band 0.01", {"terminal": "continued", "cont_soc_band": 0.01}, {"pbat": 250.0}),
         ("continued, band 0.01", {"terminal": "continued", "cont_soc_band": 0.01},
          {"soc": 0.005, "tcl": 0.5, "pbat": 250.0})]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycle", default="nycc")
    ap.add_argument("--ambient", type=float, default=0.0)
    a = ap.parse_args()
    ps = default_parameters()
    for label, scen_kw, steps in CASES:
        scen = DPScenario(cycle=a.cycle, T_amb=a.ambient, **scen_kw)
        grids = DPGrids(**steps)
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        o = solve_thermal(ps, scen, grids)
        obj = dp_objective(ps, o.sim, scen, 2, grids=grids)
        print(json.dumps({"terminal": label, "grid_steps": steps or "paper", "V0_g": round(o.predicted_cost, 4),
                          "objective_g": round(obj, 4), "gap_pct": round(100 * (o.predicted_cost / obj - 1), 3),
                          "soc_N": round(float(o.sim.soc[-1]), 5), "fuel_g": round(float(o.sim.fuel_g), 3),
                          "time_s": round(time.perf_counter() - t0, 1), "load_1min": round(load, 2)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
