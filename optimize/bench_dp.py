"""Benchmark of the generic DP engine on a synthetic 2-state hybrid-like problem.

41 SOC x 101 coolant-temperature states (4141), 3 engine modes x 34 battery powers (102 controls),
1000 steps: about 4.2e8 state-control evaluations in the backward pass, the size of the Thermal-DP
formulation. Run ``python -m optimize.bench_dp`` (``--threads N`` to set numba's thread count).
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from numba import njit

from .dp import DPProblem, cartesian, solve


@njit(cache=True)
def hybrid_step(k, x, u, w_k, p, tab, iu, ix, x_next):  # pragma: no cover - compiled
    """SOC / coolant-temperature toy: w_k = (P_dem [kW], T_amb); u = (mode, P_bat [kW], discharge > 0).

    mode 0 engine off (battery supplies P_dem), 1 engine on, 2 engine idle (for heat, battery drives)."""
    soc = x[0]
    tcl = x[1]
    mode = u[0]
    pbat = u[1]
    pdem = w_k[0]
    if mode == 0.0 or mode == 2.0:
        # the battery covers the demand (up to 1 kW over, dissipated); regen may be partly friction-braked
        if pdem >= 0.0:
            if pbat < pdem or pbat > pdem + 1.0:
                return np.inf
        elif pbat < pdem or pbat > 0.0:
            return np.inf
        peng = 0.3 if mode == 2.0 else 0.0
    else:
        peng = pdem - pbat
        if peng < 0.0 or peng > 60.0:
            return np.inf
    # fuel [g/s] with a cold-engine penalty f_cl(T)
    fcl = 1.0 + 0.004 * (90.0 - tcl) if tcl < 90.0 else 1.0
    fuel = (0.0 if peng == 0.0 else (0.1 + 0.065 * peng + 0.0004 * peng * peng)) * fcl
    x_next[0] = soc - (pbat + 0.02 * pbat * pbat) / p[0]
    tn = tcl + p[1] * fuel * 40.0 - p[2] * (tcl - w_k[1])
    x_next[1] = min(max(tn, 0.0), 100.0)  # block heater / thermostat keep the coolant in [0, 100]
    return fuel


def make_problem(N: int = 1000, n_soc: int = 41, n_tcl: int = 101, n_pbat: int = 34, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(N)
    pdem = np.clip(8 + 10 * np.sin(t / 37.0) + 6 * rng.standard_normal(N), -15, 40)
    pdem = np.round(pdem * 2) / 2  # on the 0.5 kW grid, so engine-off modes can be matched
    w = np.column_stack([pdem, np.full(N, -10.0)])
    controls = cartesian([0.0, 1.0, 2.0], np.linspace(-15, 18, n_pbat) // 0.5 * 0.5)
    params = np.array([3600.0 * 1.3, 0.004, 0.01])  # 1.3 kWh usable battery
    return DPProblem(grids=[np.linspace(0.4, 0.8, n_soc), np.linspace(0, 100, n_tcl)], controls=controls,
                     N=N, w=w, params=params, transition=hybrid_step,
                     terminal_bounds=[(0.6, None), (None, None)], boundary="levelset", clip=False)


def run_engine_bench(N: int = 1000, repeats: int = 2, verbose: bool = True) -> dict:
    """Solve the synthetic problem (first call compiles); report the best of ``repeats`` timed solves."""
    import numba

    prob = make_problem(N)
    t0 = time.perf_counter()
    solve(make_problem(5), x0=[0.6, 70.0])  # compile (or load from cache)
    t_compile = time.perf_counter() - t0
    best = None
    for _ in range(repeats):
        res = solve(prob, x0=[0.6, 70.0])
        if best is None or res.solve_time < best.solve_time:
            best = res
    out = dict(
        n_states=prob.n_states, n_controls=prob.n_controls, N=prob.N, threads=numba.get_num_threads(),
        t_compile_s=t_compile, t_backward_s=best.t_backward, t_forward_s=best.t_forward,
        n_evaluations=best.n_evaluations, evals_per_second=best.evals_per_second,
        ns_per_eval_per_thread=1e9 * best.t_backward * numba.get_num_threads() / best.n_evaluations,
        maxrss_MB=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        cost=best.cost, feasible=best.feasible, soc_N=float(best.x[-1, 0]),
    )
    if verbose:
        for k, v in out.items():
            print(f"{k:>24s}: {v:.4g}" if isinstance(v, float) else f"{k:>24s}: {v}")
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--steps", type=int, default=1000)
    a = ap.parse_args()
    if a.threads:
        import numba

        numba.set_num_threads(a.threads)
    run_engine_bench(N=a.steps)
