"""Baseline-DP's own backward kernel, the formulations' cached forward kernel, and the per-step progress of
the backward pass (short cycles, coarse grids)."""
import dataclasses

import numpy as np
import pytest
from numba import njit

from optimize.dp.engine import DPProblem, backward_pass, forward_pass, solve
from optimize.formulations.scenario import DPGrids, DPScenario
from optimize.formulations.solve import build_problem, solve_baseline, solve_thermal, solve_thermal_cabin

COARSE3 = DPGrids(soc=0.02, tcl=4.0, pbat=2500.0, qheat=200.0)


@pytest.mark.parametrize("scen,soc,interp", [
    (DPScenario(duration_s=120.0), "drift", "reach_first"),
    (DPScenario(duration_s=90.0, terminal="free"), "absolute", "multilinear"),
])
def test_baseline_kernel_is_the_generic_engine_bit_for_bit(params, scen, soc, interp):
    from optimize.formulations.fused import backward_pass_fused

    b = build_problem(params, scen, DPGrids(), 1, warm=True, soc=soc, interp=interp)
    vg = backward_pass(b.prob)
    vf = backward_pass_fused(b.prob)
    assert vf.kernel == "fused-1" and vf.n_evaluations == vg.n_evaluations
    assert np.isfinite(vg.V[0]).any()
    np.testing.assert_array_equal(vg.V, vf.V)
    np.testing.assert_array_equal(vg.L, vf.L)
    rg, rf = forward_pass(b.prob, vg, b.x0), forward_pass(b.prob, vf, b.x0)
    np.testing.assert_array_equal(rg.u_index, rf.u_index)
    assert rg.cost == rf.cost


def test_baseline_solver_runs_its_kernel_and_gives_the_generic_engines_result(params):
    scen = DPScenario(duration_s=80.0)
    f = solve_baseline(params, scen, DPGrids())
    g = solve_baseline(params, scen, DPGrids(), engine="generic")
    assert (f.extra["kernel"], g.extra["kernel"]) == ("fused-1", "generic")
    np.testing.assert_array_equal(f.dp.u_index, g.dp.u_index)
    assert f.fuel_g == g.fuel_g and f.on_thermal.fuel_g == g.on_thermal.fuel_g


@pytest.mark.parametrize("nx,grids", [(1, DPGrids()), (2, DPGrids()), (3, COARSE3)])
def test_cached_forward_kernel_is_the_engines_forward_pass(params, nx, grids):
    from optimize.formulations.fused import backward_pass_fused, forward_hev

    b = build_problem(params, DPScenario(duration_s=40.0, T_cl0=62.0), grids, nx, warm=nx == 1)
    assert b.prob.forward_kernel is forward_hev
    vf = backward_pass_fused(b.prob)
    r1 = forward_pass(b.prob, vf, b.x0)
    r2 = forward_pass(dataclasses.replace(b.prob, forward_kernel=None), vf, b.x0)
    assert r1.feasible and r1.steps_completed == b.prob.N
    np.testing.assert_array_equal(r1.u_index, r2.u_index)
    np.testing.assert_array_equal(r1.x, r2.x)
    assert r1.cost == r2.cost


def _recorder():
    calls = []
    return calls, lambda done, total: calls.append((done, total))


def _check_calls(calls, N):
    done = [d for d, t in calls]
    assert all(t == N for d, t in calls)
    assert done[0] == 0 and done[-1] == N and done == sorted(set(done))
    assert len(calls) >= min(N, 50)  # about every 1 % of the steps


@njit(cache=True)
def _lq(k, x, u, w_k, p, tab, iu, ix, x_next):
    x_next[0] = x[0] + u[0]
    return u[0] * u[0]


def test_engine_solve_reports_progress_and_returns_the_same_result():
    prob = DPProblem(grids=[np.linspace(-2, 2, 41)], controls=np.linspace(-1, 1, 21)[:, None], N=37,
                     transition=_lq, terminal_cost=lambda X: 10 * X[:, 0] ** 2)
    calls, rec = _recorder()
    a, b = solve(prob, x0=[1.3]), solve(prob, x0=[1.3], progress=rec)
    _check_calls(calls, 37)
    np.testing.assert_array_equal(a.V, b.V)
    np.testing.assert_array_equal(a.u_index, b.u_index)


@pytest.mark.parametrize("solver,grids,kw", [
    (solve_baseline, DPGrids(), {}),
    (solve_thermal, DPGrids(), {}),
    (solve_thermal, DPGrids(), {"engine": "fused-exact"}),
    (solve_thermal_cabin, COARSE3, {}),
    (solve_thermal_cabin, COARSE3, {"engine": "fused-exact"}),
])
def test_formulations_report_progress_per_step_part_and_return_the_same_values(params, solver, grids, kw):
    scen = DPScenario(duration_s=60.0, T_cl0=62.0)
    calls, rec = _recorder()
    a = solver(params, scen, grids, **kw)
    b = solver(params, scen, grids, progress=rec, **kw)
    _check_calls(calls, a.dp.u_index.size)
    assert a.extra["kernel"] == b.extra["kernel"]
    np.testing.assert_array_equal(a.dp.V, b.dp.V)
    np.testing.assert_array_equal(a.dp.u_index, b.dp.u_index)
    assert a.fuel_g == b.fuel_g
