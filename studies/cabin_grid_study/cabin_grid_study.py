"""Thermal-Cabin-DP on the default car and drive on chosen grids: corrected fuel, mean cabin, states,
controls, evaluations, time and the trajectory's grid artefacts (heater chatter, cabin pinned to a node;
:func:`optimize.convergence.trajectory_checks`), one JSON line per grid (the grid-convergence figures of the README's
speed section).

    .venv/bin/python studies/cabin_grid_study/cabin_grid_study.py '{}' '{"tcl": 2, "qheat": 100}' \
        '{"tcl": 2, "qheat": 100, "soc": 0.005}' '{"tcl": 2, "qheat": 100, "tcab": 0.5}' \
        '{"tcl": 2, "qheat": 100, "pbat": 250}'

Each argument is a JSON object of DPGrids steps (missing ones: the paper's defaults).
"""
import json
import os
import sys
import time

from calib.model import default_parameters
from optimize.formulations import DPGrids, DPScenario, solve_formulation


def main(argv):
    if not argv:
        print(__doc__)
        return 2
    ps, scen = default_parameters(), DPScenario()
    solve_formulation("thermal_cabin", ps, DPScenario(duration_s=20.0), DPGrids())  # compile outside the timing
    for spec in argv:
        steps = json.loads(spec)
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        o = solve_formulation("thermal_cabin", ps, scen, DPGrids(**steps))
        s = o.sim.summary()
        print(json.dumps({"grid": steps, "states": o.n_states, "controls": o.n_controls,
                          "t_s": round(time.perf_counter() - t0, 1), "evaluations": o.n_evaluations,
                          "load_1min": round(load, 2), "fuel_g": round(s["fuel_g"], 4),
                          "corrected_g": round(s["fuel_corrected_g"], 4),
                          "T_cab_mean_degC": round(s["T_cab_mean_degC"], 5),
                          "artefacts": {k: round(v, 2) for k, v in o.extra.get("grid_artefacts", {}).items()}}),
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
