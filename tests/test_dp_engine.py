"""Tests of the generic DP engine (optimize.dp): analytic optima, exhaustive enumeration, the level-set
boundary method, grid convergence, determinism across thread counts."""
from __future__ import annotations

import itertools

import numba
import numpy as np
import pytest
from numba import njit

from optimize.dp.engine import DPProblem, backward_pass, cartesian, forward_pass, interpolate, solve


# ----------------------------------------------------------------------------------------------------
# transitions (module level so numba can cache them)
# ----------------------------------------------------------------------------------------------------
@njit(cache=True)
def linear_quadratic(k, x, u, w_k, p, tab, iu, ix, x_next):
    """x+ = A x + B u, stage cost x'Qx + u'Ru; p = (A, B, Q, R) as 2-D arrays."""
    A, B, Q, R = p
    n = x.shape[0]
    m = u.shape[0]
    c = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += A[i, j] * x[j]
            c += x[i] * Q[i, j] * x[j]
        for j in range(m):
            s += B[i, j] * u[j]
        x_next[i] = s
    for i in range(m):
        for j in range(m):
            c += u[i] * R[i, j] * u[j]
    return c


@njit(cache=True)
def twostatesys(k, x, u, w_k, p, tab, iu, ix, x_next):
    """DPM's `twostatesys` (Elbert, Ebbesen & Guzzella 2013), exact discretisation; p = (exp(-Ts/2), Ts)."""
    et = p[0]
    x_next[0] = et * x[0] - 2.0 * (et - 1.0) * u[0] * u[1]
    x_next[1] = et * x[1] - 2.0 * (et - 1.0) * u[0] * (1.0 - u[1])
    return (u[0] + 0.1 * abs(u[1] - 0.5)) * p[1]


@njit(cache=True)
def integer_table(k, x, u, w_k, p, tab, iu, ix, x_next):
    """Integer dynamics x+ = x + u + w_k, stage cost from a table p[k, iu, x0, x1] (inf = masked).

    Uses the precomputed per-step table when on grid (tab[iu, 0] is the step's cost offset)."""
    i0 = int(x[0])
    i1 = int(x[1])
    x_next[0] = x[0] + u[0] + w_k[0]
    x_next[1] = x[1] + u[1] + w_k[1]
    return p[k, iu, i0, i1] + tab[iu, 0]


@njit(cache=True)
def integer_precompute(k, w_k, p, tab):
    for iu in range(tab.shape[0]):
        tab[iu, 0] = (k + iu) % 3  # a per-step, per-control extra cost


# ----------------------------------------------------------------------------------------------------
# 1. analytic optima
# ----------------------------------------------------------------------------------------------------
def _riccati(A, B, Q, R, QN, N):
    P = QN
    for _ in range(N):
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ (A - B @ K)
    return P


def _lq_problem(A, B, Q, R, QN, N, n_x, n_u, half=2.0, u_max=1.5):
    grids = [np.linspace(-half, half, n_x)] * A.shape[0]
    controls = cartesian(*([np.linspace(-u_max, u_max, n_u)] * B.shape[1]))
    return DPProblem(grids=grids, controls=controls, N=N, transition=linear_quadratic,
                     params=(A, B, Q, R), terminal_cost=lambda X: np.einsum("si,ij,sj->s", X, QN, X))


def test_scalar_lq_matches_riccati_and_error_shrinks():
    A, B, Q, R = np.eye(1), np.eye(1), np.zeros((1, 1)), np.eye(1)
    QN = 10 * np.eye(1)
    N, x0 = 10, np.array([1.3])
    exact = float(x0 @ _riccati(A, B, Q, R, QN, N) @ x0)
    errs = []
    for n_x, n_u in ((41, 51), (161, 201)):
        res = solve(_lq_problem(A, B, Q, R, QN, N, n_x, n_u), x0)
        assert res.feasible and res.steps_completed == N
        assert res.cost >= exact - 1e-12  # forward cost of an admissible sequence: never below optimum
        errs.append(res.cost - exact)
    # interpolation error on the quadratic cost-to-go: ~20 % at dx = 0.1, ~1.2 % at dx = 0.025
    assert errs[0] < 0.25 * exact
    assert errs[1] < 0.02 * exact
    assert errs[1] < 0.1 * errs[0]


def _twostate_analytic(Ts, N):
    """Discrete-time optimum of twostatesys from x0 = (0, 0) with x_N >= (0.5, 0.5), u continuous:
    u2 = 0.5 and u1 = 1 on the last steps (LP: later inputs decay less), one fractional step."""
    et = np.exp(-0.5 * Ts)
    m = 0
    while 1 - et ** (m + 1) < 0.5:
        m += 1
    f = (0.5 - (1 - et ** m)) / ((1 - et) * et ** m)
    assert m + f <= N
    return Ts * (m + f)


def _twostate_problem(Nx, Ts=0.1, T=2.0, boundary="levelset", n_u=21):
    N = int(round(T / Ts))
    u = np.linspace(0, 1, n_u)
    return DPProblem(grids=[np.linspace(0, 1, Nx)] * 2, controls=cartesian(u, u), N=N,
                     params=np.array([np.exp(-0.5 * Ts), Ts]), transition=twostatesys,
                     terminal_bounds=[(0.5, None), (0.5, None)], boundary=boundary)


def test_twostatesys_against_analytic_optimum():
    Ts = 0.1
    exact = _twostate_analytic(Ts, 20)
    assert abs(exact - 2 * np.log(2)) < 1e-3  # continuous-time optimum 2 ln 2 (t_on = 2 + 2 ln 0.5)
    errs = []
    for Nx in (51, 101):
        res = solve(_twostate_problem(Nx, Ts), [0.0, 0.0])
        assert res.feasible
        assert np.all(res.x[-1] >= 0.5 - 1e-9)
        assert res.cost >= exact - 1e-9
        errs.append((res.cost - exact) / exact)
        # bang-bang structure: u1 off at the start, u2 = 0.5 almost everywhere
        assert np.all(res.u[:2, 0] == 0.0) and np.mean(res.u[-5:, 0]) >= 0.8
        assert np.mean(res.u[:, 1] == 0.5) >= 0.8
    # signed levels carry the terminal set back exactly: 1.1 % and 0.7 % above the analytic optimum
    assert errs[0] < 0.02 and errs[1] < 0.01 and errs[1] < errs[0]


# ----------------------------------------------------------------------------------------------------
# 2. exhaustive enumeration on tiny integer problems (DP must be exact)
# ----------------------------------------------------------------------------------------------------
def _integer_problem(rng, N, n0=5, n1=4, mask_frac=0.2, boundary="none", precompute=True):
    controls = cartesian([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0])
    C = rng.integers(0, 10, size=(N, controls.shape[0], n0, n1)).astype(float)
    C[rng.random(C.shape) < mask_frac] = np.inf
    w = rng.integers(-1, 2, size=(N, 2)).astype(float) * (rng.random((N, 2)) < 0.3)
    term = rng.integers(0, 10, size=(n0, n1)).astype(float)
    prob = DPProblem(grids=[np.arange(n0, dtype=float), np.arange(n1, dtype=float)], controls=controls,
                     N=N, w=w, params=C, transition=integer_table, terminal_cost=term,
                     terminal_bounds=[(2.0, None), (None, 2.0)], boundary=boundary,
                     precompute=integer_precompute if precompute else None,
                     table_shape=(controls.shape[0], 1))
    return prob, term


def _brute_force(prob, term, x0):
    """Minimum over all control sequences, simulated with the same (pure-Python) transition."""
    f = integer_table.py_func
    tabs = []
    for k in range(prob.N):
        t = np.zeros(prob.table_shape)
        integer_precompute.py_func(k, prob.w[k], prob.params, t)
        tabs.append(t)
    best = np.inf
    nu = prob.n_controls
    ix = np.full(2, -1)
    for seq in itertools.product(range(nu), repeat=prob.N):
        x = np.array(x0, dtype=float)
        total = 0.0
        for k, iu in enumerate(seq):
            xn = np.empty(2)
            c = f(k, x, prob.controls[iu], prob.w[k], prob.params, tabs[k], iu, ix, xn)
            if not np.isfinite(c) or not (0 <= xn[0] <= 4 and 0 <= xn[1] <= 3):
                total = np.inf
                break
            total += c
            x = xn
        if np.isfinite(total) and x[0] >= 2 and x[1] <= 2:
            best = min(best, total + term[int(x[0]), int(x[1])])
    return best


@pytest.mark.parametrize("boundary", ["none", "levelset"])
def test_exhaustive_enumeration_fixed(boundary):
    rng = np.random.default_rng(1234)
    prob, term = _integer_problem(rng, N=4, boundary=boundary)
    x0 = [1.0, 1.0]
    ref = _brute_force(prob, term, x0)
    res = solve(prob, x0, store_policy=True)
    assert np.isfinite(ref)
    assert res.feasible and res.cost == ref
    assert res.predicted_cost[0] == pytest.approx(ref)  # backward value = forward cost on grid
    assert res.V[0][1, 1] == pytest.approx(ref)
    assert res.policy.shape == (4, 5, 4) and res.policy[0, 1, 1] == res.u_index[0]


def test_exhaustive_enumeration_random_family():
    rng = np.random.default_rng(7)
    n_checked = 0
    for trial in range(12):
        prob, term = _integer_problem(rng, N=3, mask_frac=0.3, boundary=("none", "levelset")[trial % 2],
                                      precompute=True)
        x0 = [float(rng.integers(0, 5)), float(rng.integers(0, 4))]
        ref = _brute_force(prob, term, x0)
        res = solve(prob, x0)
        if np.isfinite(ref):
            n_checked += 1
            assert res.feasible and res.cost == ref, (trial, res.cost, ref)
        else:
            assert not res.feasible
            # the backward pass agrees that no admissible sequence exists
            vf = backward_pass(prob)
            if prob.boundary == "none":
                assert not np.isfinite(vf.V[0][int(x0[0]), int(x0[1])])
            else:
                assert vf.L[0][int(x0[0]), int(x0[1])] > 0
    assert n_checked >= 6


# ----------------------------------------------------------------------------------------------------
# 3. boundary method: hard terminal constraint on a coarse grid
# ----------------------------------------------------------------------------------------------------
def test_levelset_keeps_coarse_grid_feasible_where_inf_penalty_fails():
    exact = _twostate_analytic(0.1, 20)
    naive = solve(_twostate_problem(11, boundary="none"), [0.0, 0.0])
    ls = solve(_twostate_problem(11, boundary="levelset"), [0.0, 0.0])
    # +inf terminal cost on an 11-point grid: the inf corners spread through interpolation and the
    # initial state looks infeasible
    assert not naive.feasible and not np.isfinite(naive.cost)
    # level set: a feasible trajectory meeting x_N >= 0.5 exactly, cost within 5 % of the optimum
    assert ls.feasible and ls.steps_completed == 20
    assert np.all(ls.x[-1] >= 0.5 - 1e-9)
    assert exact - 1e-9 <= ls.cost < 1.05 * exact
    # the signed level at x0 is negative: the set is reachable with margin (about one cell)
    assert ls.L is not None and np.isfinite(ls.V[0][0, 0]) and ls.L[0][0, 0] < 0.0


# ----------------------------------------------------------------------------------------------------
# 4. convergence on a smooth 2-state problem
# ----------------------------------------------------------------------------------------------------
def test_grid_refinement_converges_double_integrator():
    dt = 0.2
    A = np.array([[1.0, dt], [0.0, 1.0]])
    B = np.array([[0.5 * dt * dt], [dt]])
    Q = 0.1 * np.eye(2)
    R = 0.1 * np.eye(1)
    QN = 5.0 * np.eye(2)
    N, x0 = 15, np.array([1.0, -0.3])
    exact = float(x0 @ _riccati(A, B, Q, R, QN, N) @ x0)
    costs = []
    for n_x in (21, 41, 81):
        res = solve(_lq_problem(A, B, Q, R, QN, N, n_x, 81, half=2.0, u_max=2.0), x0)
        assert res.feasible
        costs.append(res.cost)
    d1, d2 = abs(costs[1] - costs[0]), abs(costs[2] - costs[1])
    # roughly second order: relative errors ~12 %, 3 %, 0.8 % on 21, 41, 81 points
    assert d2 < 0.5 * d1 and d2 < 0.03 * exact
    assert exact - 1e-12 <= costs[2] < 1.015 * exact


# ----------------------------------------------------------------------------------------------------
# API details
# ----------------------------------------------------------------------------------------------------
def test_interpolation_rules_nonuniform_and_inf():
    g0 = np.array([0.0, 0.5, 2.0, 3.0])  # non-uniform: binary search
    g1 = np.linspace(-1, 1, 5)
    prob = DPProblem(grids=[g0, g1], controls=np.zeros((1, 1)), N=1, transition=twostatesys)
    X = prob.grid_points()
    lin = (2 * X[:, 0] - 3 * X[:, 1] + 1).reshape(prob.grid_shape)
    q = np.array([[0.3, 0.1], [1.7, -0.9], [3.0, 1.0], [2.0, 0.5]])
    np.testing.assert_allclose(interpolate(prob, lin, q), 2 * q[:, 0] - 3 * q[:, 1] + 1, rtol=1e-12)
    assert np.all(np.isinf(interpolate(prob, lin, [[3.1, 0.0], [0.0, -1.01], [np.nan, 0.0]])))
    V = lin.copy()
    V[1, 2] = np.inf
    out = interpolate(prob, V, [[0.5, 0.5], [0.5, 0.0], [0.25, 0.25], [0.5 + 1e-14, 0.5]])
    assert np.isfinite(out[0]) and np.isinf(out[1]) and np.isinf(out[2]) and np.isfinite(out[3])


def test_deterministic_across_thread_counts_and_dataframe():
    prob = _twostate_problem(21, boundary="levelset")
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        r1 = solve(prob, [0.05, 0.02])
        numba.set_num_threads(old)
        r2 = solve(prob, [0.05, 0.02])
    finally:
        numba.set_num_threads(old)
    np.testing.assert_array_equal(r1.V, r2.V)
    np.testing.assert_array_equal(r1.u_index, r2.u_index)
    assert r1.cost == r2.cost and r1.n_evaluations == 20 * 21 * 21 * 441
    df = r1.to_pandas()
    assert list(df.columns) == ["k", "x0", "x1", "u0", "u1", "u_index", "stage_cost"]
    assert len(df) == 21 and np.isclose(df["stage_cost"].sum(), r1.cost - r1.terminal_cost)
    assert r1.solve_time > 0 and r1.evals_per_second > 0


@njit(cache=True)
def counting(k, x, u, w_k, p, tab, iu, ix, x_next):
    """x+ = x, cost 0; counts its calls in p[0], records the table's shape in p[1:3] and the smallest grid
    index it was given in p[3]."""
    p[0] += 1.0
    p[1] = tab.shape[0]
    p[2] = tab.shape[1]
    if ix[0] < p[3]:
        p[3] = ix[0]
    x_next[0] = x[0]
    return 0.0


@njit(cache=True)
def index_check(k, x, u, w_k, p, tab, iu, ix, x_next):
    """x+ = x, cost 0 on integer grids (node value = grid index): counts its calls in p[0] and, in p[1], the
    calls whose grid index differs from the node in some dimension."""
    p[0] += 1.0
    for d in range(x.shape[0]):
        x_next[d] = x[d]
        if ix[d] != x[d]:
            p[1] += 1.0
            break
    return 0.0


def _counting_problem(N=3, n=100, nu=2):
    p = np.array([0.0, 9.0, 9.0, 0.0])
    return DPProblem(grids=[np.linspace(0.0, 1.0, n)], controls=np.zeros((nu, 1)), N=N, transition=counting,
                     params=p), p


def _on_one_thread(fn, *args):
    """``fn(*args)`` with numba on one thread (then the thread count as it was): the counting transition
    increments a shared counter, which parallel threads would race on."""
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        return fn(*args)
    finally:
        numba.set_num_threads(old)


def test_backward_pass_evaluates_each_state_control_pair_once_per_step():
    """One thread, 100 nodes: the backward pass splits the states into 8 chunks of 13; every (state,
    control) pair is evaluated exactly once per step, as n_evaluations reports, with the node's grid
    index; without a precompute hook the table is an empty (0, 0) array."""
    prob, p = _counting_problem()
    _on_one_thread(backward_pass, prob)
    assert p[0] == 3 * 100 * 2
    assert (p[1], p[2], p[3]) == (0.0, 0.0, 0.0)


def test_backward_pass_gives_each_node_its_grid_index_in_every_dimension():
    """Three states on the integer grids 0..3, 0..2, 0..4 (60 nodes, strides 15, 5, 1): the backward pass
    hands the transition, at every node, the node's own grid index in each dimension (the node (2, 1, 3)
    is state 2 x 15 + 1 x 5 + 3 = 38 and gets ix = (2, 1, 3))."""
    p = np.zeros(2)
    prob = DPProblem(grids=[np.arange(4.0), np.arange(3.0), np.arange(5.0)], controls=np.zeros((2, 1)), N=2,
                     transition=index_check, params=p)
    _on_one_thread(backward_pass, prob)
    assert (p[0], p[1]) == (2 * 60 * 2, 0.0)


def test_solve_time_is_the_backward_plus_the_forward_pass_time():
    """A result with a 2.0 s backward and a 0.5 s forward pass took 2.5 s; 1000 evaluations in the 2.0 s
    backward pass are 500 per second; the DataFrame carries the same total."""
    from optimize.dp.engine import DPResult

    N = 2
    h = DPResult(t=np.arange(N + 1), x=np.zeros((N + 1, 1)), u=np.zeros((N, 1)), u_index=np.zeros(N, np.int64),
                 stage_cost=np.ones(N), terminal_cost=0.0, cost=2.0, predicted_cost=np.ones(N), feasible=True,
                 terminal_level=0.0, steps_completed=N, V=np.zeros((N + 1, 3)), L=None, policy=None,
                 t_backward=2.0, t_forward=0.5, n_evaluations=1000)
    assert h.solve_time == 2.5 and h.evals_per_second == 500.0
    assert h.to_pandas().attrs["solve_time"] == 2.5


def test_forward_pass_gives_the_transition_grid_index_minus_one():
    """The forward pass runs from the true (off-grid) state: every grid index it passes is -1."""
    prob, p = _counting_problem()
    res = _on_one_thread(solve, prob, [0.55])
    assert res.feasible and p[3] == -1.0
    # the backward pass, then per step one evaluation per control and one more of the chosen control
    assert p[0] == res.n_evaluations + 3 * (2 + 1)


def test_problem_defaults_are_empty_arrays():
    """No exogenous inputs: an (N, 0) array; no parameters: an empty float64 array."""
    prob = DPProblem(grids=[np.linspace(0.0, 1.0, 3)], controls=np.zeros((1, 1)), N=4, transition=counting)
    assert prob.w.shape == (4, 0) and prob.params.shape == (0,) and prob.params.dtype == np.float64


def test_terminal_level_is_the_distance_to_the_box_in_grid_steps():
    """Grid step 0.1, box [0.3, 0.7]: 3 steps outside at 0, 0 on the boundary, -2 in the middle."""
    prob = DPProblem(grids=[np.linspace(0.0, 1.0, 11)], controls=np.zeros((1, 1)), N=1, transition=counting,
                     terminal_bounds=[(0.3, 0.7)])
    np.testing.assert_allclose(prob.terminal_level([[0.0], [0.3], [0.5], [0.7], [1.0]]), [3, 0, -2, 0, 3],
                               atol=1e-12)


def test_levelset_terminal_boundary_reached_exactly_is_feasible():
    """x+ = x + u on the integers 0..4, cost u^2, terminal set x >= 2 from x0 = 0 in two steps: only
    u = (1, 1) ends in the set, exactly on its boundary (level 0): feasible, cost 2."""
    A, B, Q, R = np.eye(1), np.eye(1), np.zeros((1, 1)), np.eye(1)
    prob = DPProblem(grids=[np.arange(5.0)], controls=np.array([[-1.0], [0.0], [1.0]]), N=2,
                     transition=linear_quadratic, params=(A, B, Q, R), terminal_bounds=[(2.0, None)],
                     boundary="levelset")
    res = solve(prob, [0.0])
    assert res.feasible and res.cost == 2.0 and res.x[-1, 0] == 2.0


def test_levelset_terminal_set_missed_by_a_fraction_of_a_step_is_infeasible():
    """x+ = x + u, u in {0, 0.5} on the grid 0..4 (step 1), terminal set x >= 1.5 from x0 = 0 in one step:
    the best reachable end is 0.5, one grid step short of the set (level 1.0); a forward pass that ends
    outside the set is reported infeasible, whatever its level (here 1.0, then 0.5 with the set at 1.0)."""
    A, B, Q, R = np.eye(1), np.eye(1), np.zeros((1, 1)), np.eye(1)
    prob = DPProblem(grids=[np.arange(5.0)], controls=np.array([[0.0], [0.5]]), N=1,
                     transition=linear_quadratic, params=(A, B, Q, R), terminal_bounds=[(1.5, None)],
                     boundary="levelset")
    res = solve(prob, [0.0])
    assert res.x[-1, 0] == 0.5  # the least level: as close to the set as the controls allow
    assert prob.terminal_level([[0.5]])[0] == pytest.approx(1.0)
    assert not res.feasible
    # half as far short (level 0.5, still outside): infeasible too
    prob2 = DPProblem(grids=[np.arange(5.0)], controls=np.array([[0.0], [0.5]]), N=1,
                      transition=linear_quadratic, params=(A, B, Q, R), terminal_bounds=[(1.0, None)],
                      boundary="levelset")
    res2 = solve(prob2, [0.0])
    assert res2.x[-1, 0] == 0.5 and prob2.terminal_level([[0.5]])[0] == pytest.approx(0.5)
    assert not res2.feasible


def test_levelset_boundary_reached_then_a_dearer_control_inside_keeps_the_cheaper():
    """One step, controls +1 (cost 1) then +2 (cost 4), terminal set x >= 2: from x = 1, +1 lands on the
    boundary (level 0) and +2 inside (level -1): both reach the set, the cheaper is kept, V = 1. From 0 only
    +2 reaches it (V = 4); from 4 both leave the grid (V = inf)."""
    A, B, Q, R = np.eye(1), np.eye(1), np.zeros((1, 1)), np.eye(1)
    prob = DPProblem(grids=[np.arange(5.0)], controls=np.array([[1.0], [2.0]]), N=1,
                     transition=linear_quadratic, params=(A, B, Q, R), terminal_bounds=[(2.0, None)],
                     boundary="levelset")
    vf = backward_pass(prob)
    np.testing.assert_array_equal(np.asarray(vf.V).reshape(2, 5)[0], [4.0, 1.0, 1.0, 1.0, np.inf])


def test_result_built_without_timings_reports_none():
    """A DPResult made by hand (not by solve) has zero times and evaluations, and no evaluation rate."""
    import dataclasses

    from optimize.dp.engine import DPResult

    r = solve(_twostate_problem(11), [0.05, 0.02])
    kw = {f.name: getattr(r, f.name) for f in dataclasses.fields(r)
          if f.name not in ("t_backward", "t_forward", "n_evaluations")}
    h = DPResult(**kw)
    assert (h.t_backward, h.t_forward, h.n_evaluations, h.solve_time) == (0.0, 0.0, 0, 0.0)
    assert np.isnan(h.evals_per_second) and h.cost == r.cost


def test_result_repr_leaves_out_the_value_level_and_policy_tables():
    """The repr of a result stays a few lines: the per-node tables V, L and policy are not printed."""
    r = solve(_twostate_problem(11), [0.05, 0.02])
    text = repr(r)
    assert text.startswith("DPResult(t=")
    for name in ("V", "L", "policy"):
        assert f" {name}=" not in text and f"({name}=" not in text
    for name in ("cost", "feasible", "steps_completed", "n_evaluations"):
        assert f" {name}=" in text


def test_result_plot(tmp_path):
    """The result draws itself: one panel per state and control plus the cumulative cost, saved atomically."""
    r = solve(_twostate_problem(11), [0.05, 0.02])
    fig = r.plot(tmp_path / "dp.png")
    assert len(fig.axes) == 2 + 2 + 1 and (tmp_path / "dp.png").stat().st_size > 0
    line = fig.axes[-1].lines[0]
    assert line.get_ydata()[-1] == pytest.approx(r.cost - r.terminal_cost)


def test_malformed_problem_inputs_are_refused_each_with_its_message():
    g = [np.linspace(0, 1, 3)]
    one = dict(controls=np.zeros((1, 1)), transition=twostatesys)
    cases = [
        (dict(grids=[np.array([0.0, 0.0, 1.0])], N=1, **one), "grid 0 must be strictly increasing"),
        (dict(grids=[np.array([0.0])], N=1, **one), "grid 0 must be strictly increasing with at least 2"),
        (dict(grids=g, N=2, w=np.zeros((3, 1)), **one), "w must have N=2 rows, got 3"),
        (dict(grids=g, N=2, boundary="bogus", **one), "boundary must be"),
        (dict(grids=g, N=0, **one), "N must be >= 1"),
        (dict(grids=g, N=1, controls=np.zeros((0, 1)), transition=twostatesys), "non-empty"),
        (dict(grids=g, N=1, controls=np.zeros((2, 1, 1)), transition=twostatesys), "non-empty"),
        (dict(grids=g, N=1, table_shape=(3,), **one), "table_shape must be 2-D"),
    ]
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            DPProblem(**kw)
    # 1-D controls and inputs are one column each; N = 1 and the default table shape are accepted
    p = DPProblem(grids=g, controls=np.array([-1.0, 0.0, 1.0]), N=1, w=np.array([2.0]), transition=twostatesys)
    assert p.controls.shape == (3, 1) and p.w.shape == (1, 1) and p.w[0, 0] == 2.0 and p.N == 1
    assert DPProblem(grids=g, N=1, **one).w.shape == (1, 0)
    # the terminal data and the initial state must fit the grid
    for n in (2, 4):
        with pytest.raises(ValueError, match="one value per grid state"):
            DPProblem(grids=g, N=1, terminal_cost=np.zeros(n), **one).terminal_arrays()
    box = DPProblem(grids=g, N=1, terminal_bounds=[(0.0, 1.0), (0.0, 1.0)], boundary="levelset", **one)
    with pytest.raises(ValueError, match="one \\(lo, hi\\) per state"):
        box.terminal_arrays()
    with pytest.raises(ValueError, match="x0 must have 2 entries"):
        solve(_twostate_problem(5), [0.05])


# ----------------------------------------------------------------------------------------------------
# 5. terminal sets with standstill stretches (every control moves the state by less than one cell)
# ----------------------------------------------------------------------------------------------------
_DRIVE_U = np.arange(-2, 5) * 1e-3   # charge change per driving step
_DRAIN = 3e-4                        # accessory drain per standstill step (engine off: the only control)


@njit(cache=True)
def hev_like(k, x, u, w_k, p, tab, iu, ix, x_next):
    """A charge-sustaining toy hybrid: driving steps (w_k[0] = 1) change the charge by u at a convex fuel
    cost; at standstill the engine is off and the accessories drain 3e-4 whatever the control."""
    if w_k[0] > 0.5:
        x_next[0] = x[0] + u[0]
        return 1.0 + 300.0 * u[0] + 5e4 * u[0] * u[0]
    x_next[0] = x[0] - 3e-4
    return 0.0


# D followed by four standstill steps, six times: on the 1e-3 grid each standstill step moves 0.3 cells
_PATTERN = np.tile([1.0, 0.0, 0.0, 0.0, 0.0], 6)


def _hev_like_problem(h, boundary="levelset"):
    return DPProblem(grids=[np.round(np.linspace(0.4, 0.8, int(round(0.4 / h)) + 1), 12)],
                     controls=_DRIVE_U[:, None], N=_PATTERN.size, w=_PATTERN[:, None], transition=hev_like,
                     terminal_bounds=[(0.599, 0.601)], boundary=boundary)


def _hev_like_exhaustive(x0):
    """Least cost over every control sequence ending in [0.599, 0.601] (vectorised enumeration)."""
    x = np.array([x0])
    c = np.zeros(1)
    for drive in _PATTERN:
        if drive:
            x = (x[:, None] + _DRIVE_U[None, :]).ravel()
            c = (c[:, None] + (1.0 + 300.0 * _DRIVE_U + 5e4 * _DRIVE_U ** 2)[None, :]).ravel()
        else:
            x = x - _DRAIN
    ok = (x >= 0.599 - 1e-9) & (x <= 0.601 + 1e-9)
    return float(c[ok].min()) if ok.any() else np.inf


@pytest.mark.parametrize("x0", [0.595, 0.6, 0.603])
def test_levelset_exact_with_standstill_stretches(x0):
    """Terminal band [0.599, 0.601] (two cells of the 1e-3 grid, as in DPM's parallel-HEV example),
    standstill steps moving the state 0.3 cells: the level-set answer on the 1e-3 grid is the exhaustive
    optimum, as is the 1e-4 grid (every reachable state a node) with level sets and with +inf. (A level
    clipped to 0 inside the set lost the optimum here: +3.7 % at x0 = 0.595.)"""
    ref = _hev_like_exhaustive(x0)
    assert np.isfinite(ref)
    fine_ls = solve(_hev_like_problem(1e-4), [x0])
    fine_inf = solve(_hev_like_problem(1e-4, "none"), [x0])
    assert fine_ls.feasible and fine_ls.cost == pytest.approx(ref, abs=1e-9)
    assert fine_inf.feasible and fine_inf.cost == pytest.approx(ref, abs=1e-9)
    coarse = solve(_hev_like_problem(1e-3), [x0])
    assert coarse.feasible and 0.599 - 1e-9 <= coarse.x[-1, 0] <= 0.601 + 1e-9
    assert coarse.cost == pytest.approx(ref, abs=1e-9)
    assert coarse.L[0][int(round((x0 - 0.4) / 1e-3))] <= 0.0
    # +inf terminal cost cannot see the band through the interpolation on the coarse grid
    assert not solve(_hev_like_problem(1e-3, "none"), [x0]).feasible


def test_levelset_agrees_with_inf_where_inf_is_feasible():
    n = 0
    for x0 in (0.59, 0.597, 0.6, 0.605):
        for h in (1e-4, 5e-4, 1e-3):
            ls = solve(_hev_like_problem(h), [x0])
            inf = solve(_hev_like_problem(h, "none"), [x0])
            if inf.feasible:
                n += 1
                assert ls.feasible and ls.cost == pytest.approx(inf.cost, abs=1e-9), (x0, h)
    assert n >= 4


# ----------------------------------------------------------------------------------------------------
# 6. 3-state problems (the kernels' own 3-D interpolation path)
# ----------------------------------------------------------------------------------------------------
def _multilinear(X):
    x0, x1, x2 = X[:, 0], X[:, 1], X[:, 2]
    return 1.0 + 2.0 * x0 - 3.0 * x1 + 0.5 * x2 + 0.7 * x0 * x1 - 1.1 * x1 * x2 + 0.4 * x0 * x1 * x2


@pytest.mark.parametrize("uniform", [True, False])
def test_trilinear_interpolation_is_exact_on_multilinear_functions(uniform):
    # multilinear interpolation reproduces any function linear in each coordinate separately
    if uniform:
        grids = [np.linspace(-1, 1, 5), np.linspace(0, 3, 7), np.linspace(-2, 0, 4)]
    else:
        grids = [np.array([-1, -0.7, 0.1, 1.0]), np.array([0, 0.4, 2.0, 3.0]), np.array([-2, -1.5, -0.2, 0.0])]
    prob = DPProblem(grids=grids, controls=np.zeros((1, 1)), N=1, transition=twostatesys)
    V = _multilinear(prob.grid_points()).reshape(prob.grid_shape)
    rng = np.random.default_rng(3)
    Q = np.column_stack([rng.uniform(g[0], g[-1], 200) for g in grids])
    np.testing.assert_allclose(interpolate(prob, V, Q), _multilinear(Q), rtol=0, atol=1e-12)


@njit(cache=True)
def shift3(k, x, u, w_k, p, tab, iu, ix, x_next):
    """x+ = x + u in 3-D; stage cost affine in x with a step-dependent slope, plus a convex control cost."""
    c = 0.0
    for i in range(3):
        x_next[i] = x[i] + u[i]
        c += p[k, i] * x[i]
    return c + p[k, 3] * u[0] * u[0] + p[k, 4] * abs(u[1] - 0.25) + p[k, 5] * (u[2] + 0.1) ** 2


def test_three_state_off_grid_optimum_equals_exhaustive_search():
    # States move by grid multiples from an off-grid start, and every cost is affine in the state, so each
    # cost-to-go is affine and interpolated exactly: the DP must find the enumerated optimum exactly.
    N = 4
    rng = np.random.default_rng(11)
    p = np.column_stack([rng.uniform(-1, 1, (N, 3)), rng.uniform(0.5, 2.0, (N, 3))])
    a = np.array([0.8, -1.3, 0.6])
    controls = cartesian([-0.5, 0.0, 0.5], [0.0, 0.5], [-0.5, 0.5])
    g = np.arange(-3.0, 3.01, 0.5)
    prob = DPProblem(grids=[g, g, g], controls=controls, N=N, transition=shift3, params=p,
                     terminal_cost=lambda X: X @ a)
    x0 = np.array([0.13, -0.37, 0.21])
    best, best_seq = np.inf, None
    xn = np.empty(3)
    for seq in itertools.product(range(len(controls)), repeat=N):
        x, c = x0.copy(), 0.0
        for k, iu in enumerate(seq):
            c += shift3(k, x, controls[iu], np.zeros(0), p, np.zeros((1, 1)), iu, np.zeros(3, np.int64), xn)
            x = xn.copy()
        c += x @ a
        if c < best:
            best, best_seq = c, seq
    res = solve(prob, x0)
    assert res.feasible
    assert res.cost == pytest.approx(best, abs=1e-9)
    assert tuple(res.u_index) == best_seq
    assert res.policy is None  # the policy is stored only on request
    # the value function predicts the optimum from the off-grid start (float32 storage)
    assert res.predicted_cost[0] == pytest.approx(best, abs=1e-4 * (1 + abs(best)))


def test_three_state_lq_matches_riccati_and_error_shrinks():
    A = np.array([[1.0, 0.2, 0.0], [0.0, 1.0, 0.2], [0.0, 0.0, 0.9]])
    B = np.array([[0.0], [0.1], [0.5]])
    Q, R, QN = 0.1 * np.eye(3), np.eye(1), 4.0 * np.eye(3)
    N, x0 = 6, np.array([0.7, -0.45, 0.3])
    exact = float(x0 @ _riccati(A, B, Q, R, QN, N) @ x0)
    errs = []
    for n_x, n_u in ((17, 41), (33, 81)):
        res = solve(_lq_problem(A, B, Q, R, QN, N, n_x, n_u, half=2.0, u_max=2.0), x0)
        assert res.feasible and res.steps_completed == N
        assert res.cost >= exact - 1e-9  # an admissible sequence never beats the optimum
        errs.append(res.cost - exact)
    # interpolation error on the quadratic cost-to-go: 15 % at dx = 0.25, 5 % at dx = 0.125
    assert errs[0] < 0.2 * exact
    assert errs[1] < 0.08 * exact
    assert errs[1] < 0.5 * errs[0]


def test_two_point_grid_is_accepted():
    prob = DPProblem(grids=[np.array([0.0, 1.0])], controls=np.zeros((1, 1)), N=1, transition=linear_quadratic,
                     params=(np.eye(1), np.eye(1), np.eye(1), np.eye(1)))
    assert prob.grid_shape == (2,)


def test_four_state_interpolation_is_exact_on_multilinear_functions():
    # four states take the general (slow) interpolation path
    grids = [np.linspace(-1, 1, 3), np.array([0.0, 0.5, 2.0]), np.linspace(0, 1, 4), np.array([-1.0, 0.0])]
    prob = DPProblem(grids=grids, controls=np.zeros((1, 1)), N=1, transition=twostatesys)

    def f(X):
        return 1.0 + X[:, 0] - 2.0 * X[:, 1] * X[:, 3] + 0.3 * X[:, 2] + 0.5 * X[:, 0] * X[:, 1] * X[:, 2] * X[:, 3]

    V = f(prob.grid_points()).reshape(prob.grid_shape)
    rng = np.random.default_rng(5)
    Q = np.column_stack([rng.uniform(g[0], g[-1], 100) for g in grids])
    np.testing.assert_allclose(interpolate(prob, V, Q), f(Q), rtol=0, atol=1e-12)


def _bilinear_times_quadratic(X):
    x0, x1, x2 = X[:, 0], X[:, 1], X[:, 2]
    return (1.0 + 2.0 * x0 - 3.0 * x1 + 0.7 * x0 * x1) * (0.5 - 1.3 * x2 + 2.1 * x2 ** 2)


def _cubic_exact_on_quadratics(grids, seed, n):
    """The cubic along the last axis reproduces a function multilinear in the first two states and quadratic
    in the last at ``n`` random points; multilinear interpolation misses it. Returns (prob, V)."""
    prob = DPProblem(grids=grids, controls=np.zeros((1, 1)), N=1, transition=twostatesys)
    V = _bilinear_times_quadratic(prob.grid_points()).reshape(prob.grid_shape)
    rng = np.random.default_rng(seed)
    Q = np.column_stack([rng.uniform(g[0], g[-1], n) for g in grids])
    exact = _bilinear_times_quadratic(Q)
    np.testing.assert_allclose(interpolate(prob, V, Q, interp="cubic_last"), exact, rtol=0, atol=1e-11)
    assert np.max(np.abs(interpolate(prob, V, Q) - exact)) > 1e-2
    return prob, V


def test_cubic_last_interpolation_is_exact_on_quadratics_along_the_last_axis():
    # cells at both ends of the axis included
    grids = [np.linspace(-1, 1, 5), np.linspace(0, 3, 7), np.linspace(-2, 0, 5)]
    prob, V = _cubic_exact_on_quadratics(grids, 5, 300)
    # node values are returned exactly, and the multilinear rule is kept where the cubic cannot apply
    P = prob.grid_points()
    np.testing.assert_array_equal(interpolate(prob, V, P, interp="cubic_last"), V.ravel())
    V2 = V.copy()
    V2[:, :, 0] = np.inf  # the first cabin node infeasible: the cubic's stencil reads it, multilinear not
    q = np.array([[0.1, 1.2, -2.0 + 0.5 * 1.5]])  # in cell 1 of the last axis
    np.testing.assert_allclose(interpolate(prob, V2, q, interp="cubic_last"), interpolate(prob, V2, q))
    with pytest.raises(ValueError, match="interp"):
        interpolate(prob, V, prob.grid_points(), interp="cubic")


def test_cubic_last_interpolation_of_a_convex_function_has_no_kink_at_nodes():
    # a convex function along the axis: multilinear overestimates it between nodes (kinks at the nodes),
    # the cubic follows it; the derivative is continuous across a node
    g = [np.linspace(0.0, 4.0, 5)]
    prob = DPProblem(grids=g, controls=np.zeros((1, 1)), N=1, transition=twostatesys)
    V = np.exp(g[0])
    z = np.linspace(0.0, 4.0, 401)[:, None]
    lin = interpolate(prob, V, z)
    cub = interpolate(prob, V, z, interp="cubic_last")
    assert np.max(np.abs(cub - np.exp(z[:, 0]))) < 0.5 * np.max(np.abs(lin - np.exp(z[:, 0])))
    e = 1e-6
    for node in (1.0, 2.0, 3.0):
        left, mid, right = interpolate(prob, V, [[node - e], [node], [node + e]], interp="cubic_last")
        assert (right - mid) / e == pytest.approx((mid - left) / e, rel=1e-3)


def test_reach_first_interpolates_a_boundary_cell_from_the_boundary():
    # levels in grid steps: node 0 outside the reach (0.5), node 1 inside (-0.5): the boundary is at the
    # cell's middle; the unreachable node's value (its least-level control's cost) is placed there
    from optimize.dp.kernels import _interp_reach

    V = np.array([10.0, 4.0, 1.0, 0.0], dtype=np.float32)
    L = np.array([0.5, -0.5, -1.5, -2.5], dtype=np.float32)
    strides = np.ones(1, np.int64)

    def at(c, t, lev=L, vals=V):
        return _interp_reach(vals, lev, 0.0, 1, strides, np.array([c], np.int64), np.array([t]))

    assert at(0, 0.75) == pytest.approx(10.0 + 0.5 * (4.0 - 10.0))  # the plain chord gives 5.5
    assert at(0, 0.5) == pytest.approx(10.0)
    assert at(0, 0.25) == pytest.approx(8.5)  # unreachable side: the plain chord
    assert at(1, 0.5) == pytest.approx(2.5)  # both nodes reachable: the plain chord
    assert at(0, 0.75, lev=V[:0]) == pytest.approx(5.5)  # no level function: multilinear
    # an upper bound: node 1 outside the reach
    Lu = np.array([-1.0, 1.0, 3.0, 5.0], dtype=np.float32)
    Vu = np.array([2.0, 8.0, 9.0, 9.0], dtype=np.float32)
    assert at(0, 0.25, lev=Lu, vals=Vu) == pytest.approx(2.0 + 0.5 * (8.0 - 2.0))
    # 2 states: per node of the second state, then linear along it
    V2 = np.array([[10.0, 20.0], [4.0, 4.0]], dtype=np.float32).ravel()
    L2 = np.array([[0.5, -0.5], [-0.5, -1.5]], dtype=np.float32).ravel()
    r = _interp_reach(V2, L2, 0.0, 2, np.array([2, 1], np.int64), np.array([0, 0], np.int64), np.array([0.75, 0.5]))
    assert r == pytest.approx(0.5 * 7.0 + 0.5 * (0.25 * 20.0 + 0.75 * 4.0))


def test_cubic_last_interpolation_with_three_nodes_on_the_last_axis_is_exact_on_quadratics():
    # three nodes are the fewest the cubic takes (one-sided second-order slopes at both ends, exact on a
    # quadratic): it reproduces a quadratic along the axis in both cells; multilinear misses it by
    # 2.1 * 0.5 * 0.5 = 0.525 times the bilinear factor at mid-cell
    _cubic_exact_on_quadratics([np.linspace(-1, 1, 3), np.linspace(0, 3, 4), np.linspace(-2, 0, 3)], 7, 200)


def test_reach_first_with_three_states_interpolates_the_last_state_first_then_the_boundary_cell():
    # 2 x 2 x 2 nodes; the last state is interpolated first (t2 = 0.5; its second node is the first plus
    # 2, same level), then along the first state per node of the second: at the second state's node 0
    # the boundary cuts the cell at its middle (levels 0.5, -0.5), at node 1 both nodes are reachable;
    # then linearly along the second state (t1 = 0.25)
    from optimize.dp.kernels import _interp_reach

    V0 = np.array([[10.0, 20.0], [4.0, 4.0]])  # [first, second] at the last state's node 0
    L0 = np.array([[0.5, -0.5], [-0.5, -1.5]])
    V = np.stack([V0, V0 + 2.0], axis=-1).astype(np.float32).ravel()
    L = np.stack([L0, L0], axis=-1).astype(np.float32).ravel()
    r = _interp_reach(V, L, 0.0, 3, np.array([4, 2, 1], np.int64), np.zeros(3, np.int64),
                      np.array([0.75, 0.25, 0.5]))
    at_node0 = 11.0 + (0.75 - 0.5) / 0.5 * (5.0 - 11.0)  # from the boundary (value 11 there) to node 1
    at_node1 = 0.25 * 21.0 + 0.75 * 5.0  # the plain chord
    assert r == pytest.approx(0.75 * at_node0 + 0.25 * at_node1)


def test_reach_first_with_the_boundary_on_a_node_gives_that_node_its_value():
    # levels 0.5 and 0.0 with tol 0: the reach boundary is node 1 itself (the cell's crossing fraction is
    # 1), so a query on node 1 is its value and one short of it, on the unreachable side, the plain chord;
    # mirrored, a boundary on node 0 gives node 0's value at fraction 0
    from optimize.dp.kernels import _lin_reach

    assert _lin_reach(10.0, 4.0, 0.5, 0.0, 0.0, 1.0) == 4.0
    assert _lin_reach(10.0, 4.0, 0.5, 0.0, 0.0, 0.25) == pytest.approx(0.75 * 10.0 + 0.25 * 4.0)
    assert _lin_reach(4.0, 10.0, 0.0, 0.5, 0.0, 0.0) == 4.0
    assert _lin_reach(4.0, 10.0, 0.0, 0.5, 0.0, 0.75) == pytest.approx(0.25 * 4.0 + 0.75 * 10.0)
    # the unreachable node's value +inf (no control reaches the set from it) leaves the boundary node's
    # value alone: no 0 * inf on the node itself
    assert _lin_reach(np.inf, 4.0, 0.5, 0.0, 0.0, 1.0) == 4.0
    assert _lin_reach(4.0, np.inf, 0.0, 0.5, 0.0, 0.0) == 4.0


def test_reach_first_is_offered_for_one_to_three_states_only():
    g = np.linspace(0.0, 1.0, 3)
    for n in (1, 2, 3):
        assert DPProblem(grids=[g] * n, controls=np.zeros((1, 1)), N=1, transition=twostatesys,
                         interp="reach_first").n_x == n
    with pytest.raises(ValueError, match="1 to 3 states"):
        DPProblem(grids=[g] * 4, controls=np.zeros((1, 1)), N=1, transition=twostatesys, interp="reach_first")


def test_dataframe_has_one_row_per_step_and_the_step_count():
    # N = 20 steps of a 2-state, 2-control-dimension problem: rows k = 0..20 and n_steps = 20 (neither the
    # number of control dimensions nor of states)
    prob = _twostate_problem(21, boundary="levelset")
    r = solve(prob, [0.05, 0.02])
    df = r.to_pandas()
    assert prob.N == 20 and df.attrs["n_steps"] == 20 and df["k"].tolist() == list(range(21))
    assert np.isnan(df["stage_cost"].iloc[-1]) and np.isnan(df["u0"].iloc[-1])
    assert df.attrs["cost"] == r.cost and df.attrs["feasible"] == r.feasible


def test_level_choice_rule_prefers_reaching_then_least_level_then_least_cost():
    """The level-set choice rule worked by hand (tol 0): a control reaching the terminal set replaces one
    that does not, and among reaching ones the cheaper wins; if none reaches, the least level wins, a tie in
    level goes to the cheaper, and an exact tie keeps the earlier control. A control's cost is needed while
    it could still be chosen."""
    from optimize.dp.kernels import level_better, level_needs_cost

    tol = 0.0
    assert level_better(-1.0, 9.0, tol, False, 0.5, 1.0)
    assert not level_better(-1.0, 9.0, tol, True, -2.0, 5.0) and level_better(-1.0, 4.0, tol, True, -2.0, 5.0)
    assert not level_better(1.0, 1.0, tol, True, -1.0, 5.0)
    assert level_better(0.5, 9.0, tol, False, 1.0, 1.0)
    assert not level_better(1.0, 5.0, tol, False, 1.0, 3.0) and level_better(1.0, 2.0, tol, False, 1.0, 3.0)
    assert not level_better(1.0, 3.0, tol, False, 1.0, 3.0)
    assert not level_better(-1.0, 5.0, tol, True, -2.0, 5.0)  # an exact tie among reaching controls too
    assert level_needs_cost(-1.0, tol, True, -2.0) and level_needs_cost(1.0, tol, False, 1.0)
    assert not level_needs_cost(1.0, tol, True, -1.0) and not level_needs_cost(1.5, tol, False, 1.0)


def test_level_choice_rule_applied_to_a_slot_reads_a_level_equal_to_tol_as_reaching():
    """The rule applied in place to one slot of the choice arrays (the fused kernels' form): a control at a
    level exactly tol reaches the set, so a later reaching control must be cheaper to replace it (6 is not,
    3 is); a control that does not reach replaces a non-reaching choice of higher level, and the other slot
    is left alone."""
    from optimize.dp.kernels import level_choose

    tol = 1e-3
    best, Lsel, feas = np.array([np.inf, 7.0]), np.array([np.inf, 5.0]), np.zeros(2, np.bool_)
    level_choose(tol, 4.0, tol, 0, best, Lsel, feas)
    assert feas[0] and best[0] == 4.0 and Lsel[0] == tol
    level_choose(-1.0, 6.0, tol, 0, best, Lsel, feas)
    assert best[0] == 4.0 and Lsel[0] == tol
    level_choose(-1.0, 3.0, tol, 0, best, Lsel, feas)
    assert feas[0] and best[0] == 3.0 and Lsel[0] == -1.0
    assert best[1] == 7.0 and Lsel[1] == 5.0 and not feas[1]
    level_choose(2.0, 9.0, tol, 1, best, Lsel, feas)
    assert best[1] == 9.0 and Lsel[1] == 2.0 and not feas[1]
    assert best[0] == 3.0 and Lsel[0] == -1.0 and feas[0]


def test_level_choice_rule_never_chooses_a_control_of_infinite_cost():
    """Terminal set x0 >= 2 with V_N = +inf on every node of the set (5 below it), stage cost 1, and a
    disturbance of +0.5 on x0, so next states fall inside cells: from x0 = 1 the step up (to 2.5, inside
    the set) and the hold (to 1.5, level 0.5, half on an infinite node) cost +inf, and neither is chosen (backward and forward pass),
    though both have a lower level than the step down (to 0.5, level 1.5, between two finite nodes). Worked
    by hand: V_0 = 1 + 5 = 6 there; from x0 = 2 every next state reads an infinite node: +inf."""
    controls = cartesian([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0])
    n0, n1 = 5, 4
    C = np.ones((1, controls.shape[0], n0, n1))
    term = np.where(np.arange(n0)[:, None] >= 2, np.inf, 5.0) * np.ones((1, n1))
    prob = DPProblem(grids=[np.arange(n0, dtype=float), np.arange(n1, dtype=float)], controls=controls, N=1,
                     w=np.array([[0.5, 0.0]]), params=C, transition=integer_table, terminal_cost=term,
                     terminal_bounds=[(2.0, None), (None, None)], boundary="levelset",
                     table_shape=(controls.shape[0], 1))
    vf = backward_pass(prob)
    assert vf.V[0][1, 1] == 6.0 and vf.V[0][0, 1] == 6.0
    assert np.isinf(vf.V[0][2, 1])
    # the forward pass makes the same choice: the step down, at cost 6, outside the set
    res = forward_pass(prob, vf, np.array([1.0, 1.0]))
    assert res.u[0, 0] == -1.0 and res.cost == 6.0 and not res.feasible


def test_reach_first_rule_reads_a_node_at_level_tol_as_reachable():
    """A node whose level equals the tolerance reaches the terminal set (level <= tol), so a cell between it
    and a reachable node is not cut by the reach boundary: the plain chord (1 - t) v0 + t v1, bit for bit
    (0.34 here, where v0 + t (v1 - v0) rounds to 0.33999999999999997), and +inf from an infinite node."""
    from optimize.dp.kernels import _lin_reach

    tol = 1e-3
    assert _lin_reach(0.1, 0.9, tol, -0.5, tol, 0.3) == (1.0 - 0.3) * 0.1 + 0.3 * 0.9 == 0.34
    assert _lin_reach(np.inf, 0.9, tol, -0.5, tol, 0.3) == np.inf
    assert _lin_reach(0.1, 0.9, tol, tol, tol, 0.3) == 0.34


def test_backward_pass_reports_its_own_duration():
    """``t_backward`` is the backward pass's wall time: positive and within the time measured around the
    call."""
    import time

    prob, _ = _integer_problem(np.random.default_rng(0), 4)
    t0 = time.perf_counter()
    vf = backward_pass(prob)
    elapsed = time.perf_counter() - t0
    assert 0.0 < vf.t_backward <= elapsed


def test_interpolation_rules_snap_a_query_within_1e_9_of_a_cell_onto_the_node():
    """A query closer than 1e-9 of its cell's width to a node is read on the node (rounding of a state
    computed to land there); farther outside the grid it is off-grid (+inf without clipping). The width is
    that of the cell the query is in or next to: on a non-uniform grid below its first node, the first
    cell's (0.5 here, where the second cell is 1.5 wide)."""
    g0 = np.array([0.0, 0.5, 2.0, 3.0])
    g1 = np.linspace(-1, 1, 5)
    prob = DPProblem(grids=[g0, g1], controls=np.zeros((1, 1)), N=1, transition=twostatesys)
    X = prob.grid_points()
    lin = (2 * X[:, 0] - 3 * X[:, 1] + 1).reshape(prob.grid_shape)
    w = 0.5
    out = interpolate(prob, lin, [[-0.5e-9 * w, 0.0], [-1.5e-9 * w, 0.0], [3.0 + 0.5e-9, 0.0], [3.0 + 1.5e-9, 0.0]])
    assert out[0] == pytest.approx(1.0, abs=1e-12) and out[2] == pytest.approx(7.0, abs=1e-12)
    assert np.isinf(out[1]) and np.isinf(out[3])


def _lin_reach_reference(v0, v1, l0, l1, tol, t):
    """The reach-boundary rule as the engine documents it, written independently of optimize.dp.kernels:
    in a cell whose linear level crosses tol between an unreachable node (level > tol) and a reachable one,
    a query on the reachable side of the crossing interpolates from the unreachable node's value placed at
    the crossing; elsewhere the plain chord."""
    if (l0 > tol) != (l1 > tol):
        cross = (l0 - tol) / (l0 - l1)  # where (1 - s) l0 + s l1 = tol
        if l1 <= tol and t >= cross:
            return v1 if cross >= 1.0 else v0 + (t - cross) / (1.0 - cross) * (v1 - v0)
        if l0 <= tol and t <= cross:
            return v0 if cross <= 0.0 else v0 + t / cross * (v1 - v0)
    return (1.0 - t) * v0 + t * v1


def test_reach_first_matches_an_independent_implementation_on_random_cells_of_two_and_three_states():
    """Random values and levels (varying along every state, so each node's level matters), random cells and
    fractions: the 2-state rule (reach rule along the first state per node of the second, then linear along
    the second) and the 3-state rule (linear along the last state first, then the reach rule along the
    first, then linear along the second) against :func:`_lin_reach_reference`."""
    from optimize.dp.kernels import _interp_reach

    rng = np.random.default_rng(5)
    for shape in ((4, 5), (4, 3, 5)):
        nx = len(shape)
        strides = np.array([int(np.prod(shape[d + 1:])) for d in range(nx)], np.int64)
        n_cut = 0
        for _ in range(200):
            V = rng.uniform(0.0, 10.0, shape)
            L = rng.uniform(-1.0, 1.0, shape)
            ib = np.array([rng.integers(0, s - 1) for s in shape], np.int64)
            tb = rng.uniform(0.0, 1.0, nx)
            got = _interp_reach(V.astype(np.float32).ravel(), L.astype(np.float32).ravel(), 0.0, nx, strides,
                                ib, tb)
            V32, L32 = V.astype(np.float32).astype(np.float64), L.astype(np.float32).astype(np.float64)
            rows = []
            for j in (0, 1):  # the second state's two nodes
                # the two nodes along the first state: values (3 states: linear along the last one first)
                if nx == 2:
                    Vc, Lc = V32[ib[0]:ib[0] + 2, ib[1] + j], L32[ib[0]:ib[0] + 2, ib[1] + j]
                else:
                    a = ib[2]
                    Vc = (1.0 - tb[2]) * V32[ib[0]:ib[0] + 2, ib[1] + j, a] + tb[2] * V32[ib[0]:ib[0] + 2, ib[1] + j, a + 1]
                    Lc = (1.0 - tb[2]) * L32[ib[0]:ib[0] + 2, ib[1] + j, a] + tb[2] * L32[ib[0]:ib[0] + 2, ib[1] + j, a + 1]
                n_cut += (Lc[0] > 0.0) != (Lc[1] > 0.0)
                rows.append(_lin_reach_reference(Vc[0], Vc[1], Lc[0], Lc[1], 0.0, tb[0]))
            want = (1.0 - tb[1]) * rows[0] + tb[1] * rows[1]
            assert got == pytest.approx(want, rel=1e-9, abs=1e-9), (shape, ib, tb)
        assert n_cut > 100  # the boundary cuts many of the cells tried


def test_forward_pass_reports_the_first_control_when_it_is_optimal():
    """x+ = x + u, cost u^2, controls (0, 1, 2), no terminal cost: u = 0 at every step is optimal, and the
    trajectory reports that control (index 0), not a missing one."""
    one = np.array([[1.0]])
    prob = DPProblem(grids=[np.linspace(-1.0, 5.0, 7)], controls=np.array([[0.0], [1.0], [2.0]]), N=3,
                     transition=linear_quadratic, params=(one, one, np.array([[0.0]]), one))
    r = solve(prob, [0.0])
    np.testing.assert_array_equal(r.u, np.zeros((3, 1)))
    assert r.cost == 0.0 and r.feasible


def test_a_grid_counts_as_uniform_when_its_steps_vary_by_at_most_1e_10_of_its_span():
    """Nodes 0, 1 and 2 + 2e: the steps 1 and 1 + 2e deviate from their mean by e, against 1e-10 of the whole
    span (about 2e-10). e = 1.5e-10 is uniform (an index by division), e = 3e-10 is not (binary search);
    the span of the first steps alone (1e-10) would call neither uniform."""
    for e, uniform in ((1.5e-10, True), (3e-10, False)):
        g = np.array([0.0, 1.0, 2.0 + 2 * e])
        prob = DPProblem(grids=[g, np.linspace(0.0, 1.0, 4)], controls=np.zeros((1, 2)), N=1, transition=counting,
                         params=np.zeros(4))
        _, _, _, flags, _, _ = prob._grid_arrays()
        assert flags.tolist() == [uniform, True], e


def test_interpolation_rules_locate_a_grid_node_exactly_and_the_last_node_in_the_last_cell():
    """A point on the last node lies in the last cell at fraction 1 (a cell starting there would reach past
    the grid); a point within 1e-9 cells of an interior node is snapped onto it (fraction 0), so an
    infinite neighbour is not read with a weight of 1e-10; one 1e-8 cells away is not snapped."""
    from optimize.dp.kernels import _locate

    lo, inv_dx, n = np.array([0.0]), np.array([2.0]), np.array([5])  # nodes 0, 0.5, ..., 2
    uniform, pts = np.array([True]), np.linspace(0.0, 2.0, 5)[None, :]
    for x, cell, frac in ((2.0, 3, 1.0), (1.5 - 2e-10, 3, 0.0), (1.5 + 2e-10, 3, 0.0), (0.0, 0, 0.0)):
        ib, tb = np.zeros(1, np.int64), np.zeros(1)
        assert _locate(x, 0, lo, inv_dx, n, uniform, pts, False, ib, tb), x
        assert (ib[0], tb[0]) == (cell, frac), x
    ib, tb = np.zeros(1, np.int64), np.zeros(1)
    assert _locate(1.5 - 5e-9, 0, lo, inv_dx, n, uniform, pts, False, ib, tb)
    assert ib[0] == 2 and tb[0] == pytest.approx(1.0 - 1e-8, abs=1e-12)


def test_reach_weights_are_the_reach_rule_as_weights_of_the_node_values():
    """The separable kernel applies the reach rule as weights of values interpolated along other dimensions
    first: a v0 + b v1 equals _lin_reach in every case of the rule (plain chord, chord from the boundary on
    either side, boundary on a node), with weights summing to 1."""
    from optimize.dp.kernels import _lin_reach, reach_weights

    rng = np.random.default_rng(3)
    for l0, l1 in [(0.5, -0.3), (-0.3, 0.5), (0.5, 0.0), (0.0, 0.5), (-1.0, -0.5), (2.0, 1.0), (0.7, -2.0)]:
        for t in np.concatenate([[0.0, 1.0], rng.random(20)]):
            v0, v1 = rng.normal(100.0, 30.0, 2)
            a, b = reach_weights(l0, l1, 0.0, t)
            assert a + b == pytest.approx(1.0, abs=1e-12)
            assert a * v0 + b * v1 == pytest.approx(_lin_reach(v0, v1, l0, l1, 0.0, t), rel=1e-12, abs=1e-9)
    assert reach_weights(0.5, 0.0, 0.0, 1.0) == (0.0, 1.0)
    assert reach_weights(0.0, 0.5, 0.0, 0.0) == (1.0, 0.0)
