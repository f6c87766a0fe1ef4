"""Interpolation error of the DP's ``continued`` terminal cost: phi(X) (C tabulated on the sub-grid and
interpolated) against C(X) - C(x_0) evaluated directly, at off-grid final states.

Usage: python studies/continuation_interp/continuation_interp.py [T_AMB] (default -10 degC; default scenario and grids).
"""
from __future__ import annotations

import sys

import numpy as np

from calib.model import continuation_value, default_parameters
from optimize.formulations import DPGrids, DPScenario, build_problem


def main(T_amb: float = -10.0) -> None:
    ps = default_parameters()
    scen = DPScenario(terminal="continued", T_amb=T_amb, duration_s=10.0)
    b = build_problem(ps, scen, DPGrids(), 2)
    phi = b.prob.terminal_cost
    cab = b.extra["T_cab_ref_final"]
    rng = np.random.default_rng(0)
    # off-grid states: 12 with SOC 0.55-0.70, 12 in the causal comparison's band SOC 0.59-0.61; coolant 50-98 degC
    X = np.column_stack([np.concatenate([rng.uniform(0.55, 0.70, 12), rng.uniform(0.59, 0.61, 12)]),
                         rng.uniform(50.0, 98.0, 24)])
    x0 = (scen.soc0, scen.T_cl0, scen.T_cab0)
    direct = continuation_value(ps, X[:, 0], X[:, 1], cab, T_amb=scen.T_amb, Q_heat=scen.Q_heat, ref=x0,
                                cycle=scen.cont_cycle)
    c0 = continuation_value(ps, *x0, T_amb=scen.T_amb, Q_heat=scen.Q_heat, ref=x0, cycle=scen.cont_cycle)
    err = phi(X) - (direct - c0)
    nodes = b.extra["continuation_nodes"]
    print(f"T_amb {T_amb:g} degC, sub-grid {len(nodes[0])} SOC x {len(nodes[1])} coolant nodes, cabin {cab:.2f} degC")
    for (s, t), e, d in zip(X, err, direct - c0):
        print(f"  SOC {s:.4f}  T_cl {t:6.2f}  C-C0 direct {d:8.3f} g  interpolated - direct {e:+.3f} g")
    for name, sl in (("SOC 0.55-0.70", slice(0, 12)), ("SOC 0.59-0.61", slice(12, 24))):
        e = np.abs(err[sl])
        print(f"{name}: max |error| {e.max():.3f} g, mean |error| {e.mean():.3f} g")


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else -10.0)
