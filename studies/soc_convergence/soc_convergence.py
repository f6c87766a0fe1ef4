"""Fuel of Baseline-DP or Thermal-DP against the SOC grid step (the figures of the README's paragraph on
SOC grid convergence).

    .venv/bin/python studies/soc_convergence/soc_convergence.py [--formulation baseline|thermal] [--soc drift|absolute]
        [--interp reach_first|multilinear] [--steps 0.01,0.005,0.0025,0.00125] [--duration S] [--halved]

Default car and scenario (ARTEMIS Urban, -10 degC, valued terminal); prints one JSON line per step:
re-simulated fuel and, for Thermal-DP, fuel minus the valued coolant heat (``dp_objective``). ``--halved``
adds a Thermal-DP run with every grid step halved."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))

from calib.model import default_parameters  # noqa: E402
from optimize.dp import backward_pass, forward_pass  # noqa: E402
from optimize.formulations import (INTERP, SOC_STATE, SOC_STATES, DPGrids, DPScenario, backward_pass_fused,  # noqa: E402
                                   build_problem, dp_objective, resimulate)


def main(argv=None) -> int:
    """Solve the formulation at each SOC step and print its fuel as JSON lines."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--formulation", choices=("baseline", "thermal"), default="baseline")
    ap.add_argument("--soc", choices=SOC_STATES, default=SOC_STATE)
    ap.add_argument("--interp", choices=("reach_first", "multilinear"), default=INTERP)
    ap.add_argument("--steps", default="0.01,0.005,0.0025,0.00125")
    ap.add_argument("--duration", type=float, default=None, help="cut the drive to this many seconds")
    ap.add_argument("--halved", action="store_true", help="Thermal-DP: also every grid step halved")
    a = ap.parse_args(argv)
    p = default_parameters()
    scen = DPScenario(duration_s=a.duration)
    grids = [DPGrids(soc=float(s)) for s in a.steps.split(",")]
    if a.halved:
        grids.append(DPGrids().halved())
    for g in grids:
        t0 = time.perf_counter()
        if a.formulation == "baseline":
            b = build_problem(p, scen, g, 1, warm=True, soc=a.soc, interp=a.interp)
            res = forward_pass(b.prob, backward_pass(b.prob), b.x0)  # the generic engine
            sim = resimulate(b.mp, b.cyc, res.u[:, 0], res.u[:, 1], np.full(b.prob.N, scen.Q_heat), scen, "b")
            obj = sim.fuel_g
        else:
            b = build_problem(p, scen, g, 2, soc=a.soc, interp=a.interp)
            res = forward_pass(b.prob, backward_pass_fused(b.prob), b.x0)  # the fused kernels
            sim = resimulate(p, b.cyc, res.u[:, 0], res.u[:, 1], res.u[:, 2], scen, "t")
            obj = dp_objective(p, sim, scen, 2)
        print(json.dumps({"formulation": a.formulation, "soc": a.soc, "interp": a.interp, "grid": g.to_dict(),
                          "n_states": b.prob.n_states, "fuel_g": round(sim.fuel_g, 3), "objective_g": round(obj, 3),
                          "fuel_corrected_g": round(sim.summary()["fuel_corrected_g"], 3),
                          "soc_final": round(float(sim.soc[-1]), 5), "wall_s": round(time.perf_counter() - t0, 1)}),
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
