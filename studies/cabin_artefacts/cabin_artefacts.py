"""Thermal-Cabin-DP's grid artefacts, corrected fuel and mean cabin for one parameter set, grid and cabin
discretisation (the figures of the README's paragraph on grid artefacts).

    .venv/bin/python studies/cabin_artefacts/cabin_artefacts.py [--params FILE] [--grid SPEC] [--cabin bound|absolute]
                                                [--interp reach_first|multilinear|cubic_last]
                                                [--soc drift|absolute] [--no-hold]

Case study scenario (ARTEMIS Urban, -10 degC, valued terminal); prints one JSON line."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))

from iptm.commands.simulate import load_params  # noqa: E402
from optimize.dp import FORWARD_INTERP  # noqa: E402
from optimize.formulations import DPScenario, parse_grid_spec  # noqa: E402
from optimize.formulations import CABIN_INTERP, CABIN_STATE, CABIN_STATES, SOC_STATE, SOC_STATES, solve_thermal_cabin


def main(argv=None) -> int:
    """Solve Thermal-Cabin-DP once and print its figures as one JSON line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--params", default=None, help="parameter set or calibration TOML (default: the 2017 Prius)")
    ap.add_argument("--grid", default=None, help="grid steps, e.g. soc=0.01,tcl=1,tcab=0.5,pbat=500,qheat=50")
    ap.add_argument("--cabin", choices=CABIN_STATES, default=CABIN_STATE)
    ap.add_argument("--interp", choices=FORWARD_INTERP, default=CABIN_INTERP)
    ap.add_argument("--soc", choices=SOC_STATES, default=SOC_STATE, help="SOC state's coordinate")
    ap.add_argument("--no-hold", action="store_true", help="no 'hold the bound' heater control, the heater grid only "
                    "(default: offered with --cabin bound)")
    a = ap.parse_args(argv)
    ps = load_params(a.params)
    t0 = time.perf_counter()
    o = solve_thermal_cabin(ps, DPScenario(), parse_grid_spec(a.grid), cabin=a.cabin, interp=a.interp,
                            soc=a.soc, hold=False if a.no_hold else None)
    s = o.sim.summary()
    art = o.extra["grid_artefacts"]
    below = o.sim.T_cab[1:] - o.T_cab_lb
    print(json.dumps({"grid": parse_grid_spec(a.grid).to_dict(), "cabin": a.cabin, "interp": a.interp, "soc": a.soc,
                      "hold": bool(o.extra["heater_hold"]), "heater_hold_pct": round(o.extra["heater_hold_pct"], 2),
                      "fuel_corrected_g": round(s["fuel_corrected_g"], 3), "fuel_g": round(s["fuel_g"], 3),
                      "T_cab_mean_degC": round(s["T_cab_mean_degC"], 3), "dp_cost_g": round(o.dp_cost, 3),
                      **{k: round(v, 2) for k, v in art.items()},
                      "steps_below_comfort_bound": int(np.sum(below < -1e-9)),
                      "most_below_comfort_bound_mK": round(max(0.0, -1e3 * float(np.min(below))), 2),
                      "t_backward_s": round(o.t_backward, 1), "wall_s": round(time.perf_counter() - t0, 1),
                      "load_1min": round(os.getloadavg()[0], 2)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
