r"""Generic deterministic finite-horizon dynamic programming engine.

Solves

.. math::  \min_{u_0..u_{N-1}} \sum_{k=0}^{N-1} g_k(x_k, u_k, w_k) + \Phi(x_N),
           \quad x_{k+1} = f_k(x_k, u_k, w_k),\; x_k \in \text{grid box},\; u_k \in \mathcal U

for any number of states (rectangular grids, one increasing 1-D array per state; uniform grids get O(1)
index lookup, non-uniform ones a binary search) and any number of controls (a finite control set, given as
the rows of an array ``controls`` of shape ``(n_controls, n_u)``; :func:`cartesian` builds the product
of per-control grids). It follows DPM (Sundström & Guzzella 2009) and DynaProg (Miretti 2021):

* **Backward pass.** For k = N-1..0 and every grid state, every control is evaluated with the user's
  compiled transition, the cost-to-go :math:`V_{k+1}` is interpolated multilinearly at the (off-grid) next
  state, and the minimum and (optionally) the argmin are stored. Model evaluation, interpolation and the
  minimum are fused in one numba kernel (``parallel=True``; ``prange`` over chunks of states, so it uses
  ``numba.get_num_threads()`` threads and respects ``numba.set_num_threads``). Memory is O(N x n_states)
  for the stored value functions (float32) and O(threads x n_x) scratch: the states x controls
  tensor is never built.
* **Forward pass.** From the true initial state ``x0`` (off-grid allowed), at each k every control is
  evaluated at the *actual* state with the same transition and the one minimising stage cost plus
  interpolated :math:`V_{k+1}` is applied (ties: lowest control index). The reported cost is the forward
  simulation's: ``sum(stage_cost) + terminal_cost(x_N)`` (terminal cost interpolated at x_N).

Infeasibility
    * the transition returns ``np.inf`` (or NaN) for an infeasible (state, control) pair: a mask;
    * a next state outside the grid box is infeasible, unless ``clip=True``, in which case the
      cost-to-go is looked up at the nearest point of the box (the state itself is not changed: a model
      that saturates must do so in its transition);
    * interpolation treats +inf corners as follows: a corner with zero weight is ignored (so on-grid next
      states are exact), a corner with positive weight that is +inf makes the interpolated value +inf.
      Queries within 1e-9 grid spacings of a grid point are snapped onto it.

Terminal costs and sets
    ``terminal_cost``: an array of the grid's shape (``inf`` outside the terminal set) or a callable
    ``phi(X) -> (n_states,)`` evaluated on the grid points ``X`` (n_states, n_x); default 0.
    ``terminal_bounds``: a list with one ``(lo, hi)`` per state (``None`` = unbounded) describing a box
    terminal set, e.g. charge sustaining ``SOC_N >= SOC_0`` is ``[(soc0, None), (None, None)]``.

Boundary method: level sets (Elbert, Ebbesen & Guzzella, IEEE TCST 2013)
    With ``boundary="levelset"`` (and a terminal set) the engine carries a second function, the level
    :math:`L_k(x) = \min_u L_{k+1}(f(x,u))` with the signed terminal level
    :math:`L_N(x) = \max_d \max(lo_d - x_d,\, x_d - hi_d) / h_d` (in units of each bounded dimension's
    grid spacing ``h_d``): negative inside the terminal box, zero on its boundary, positive outside, so
    ``L_k(x) <= 0`` means "the terminal set is reachable from x". The true minimum is stored (negative
    values included): a signed distance is (piecewise) linear in the state, so multilinear interpolation
    carries it back exactly even where every control moves the state by less than one cell per step (a
    level clipped to 0 inside the set would be mixed with positive neighbours there and drift above any
    tolerance). At each state (backward) and at the true state (forward) the control is chosen
    lexicographically: among controls whose interpolated level is <= ``level_tol`` (default 0) the one of
    least cost; if none, the one of least level (its cost is stored, so :math:`V` stays finite and smooth
    near the constraint boundary instead of being polluted by +inf corners). This makes hard terminal
    constraints work on coarse grids, where the naive +inf terminal cost propagates through interpolation
    and makes reachable states look infeasible. ``boundary="none"`` (default) uses the plain +inf terminal
    cost. With "levelset" the terminal set must be given by ``terminal_bounds``; +inf entries of
    ``terminal_cost`` then act as hard exclusions (level +inf) without the level-set benefit. Feasibility
    of the result is judged on the forward trajectory's true final state (``DPResult.feasible``,
    ``terminal_level``). The value of a state outside the reach is its least-level control's cost (the
    most it can do towards the set), about the cost on the reach boundary itself; with
    ``interp="reach_first"`` a cell along the first state that the boundary cuts is interpolated from the
    boundary (located where the cell's linear level crosses ``level_tol``) to the reachable node, in the
    spirit of the boundary-line method of Sundstrom et al. 2010, instead of by the chord from the
    unreachable node, which puts too low a cost near the boundary.

User functions (compile them with ``numba.njit(cache=True)`` at module level). Each distinct user function
compiles its own specialisation of the two kernels (static dispatch, the user code is inlined into the
inner loop): about 4 s (backward, parallel) + 2 s (forward) on first use in a process. The kernels are
not cached on disk: numba's cache never hits for functions specialised on a function argument. A problem
solved often can carry a cached forward kernel written for its functions (``DPProblem.forward_kernel``);
the formulations of :mod:`optimize.formulations` also have cached backward kernels of their own.

``transition(k, x, u, w_k, p, tab, iu, ix, x_next) -> float``
    ``k`` step index; ``x`` (n_x,) current state; ``u`` (n_u,) control row; ``w_k`` (n_w,) exogenous
    inputs of step k; ``p`` the user's parameters (any numba-typeable object: a float64 array, a tuple of
    arrays, ...); ``tab`` the 2-D float64 per-step table filled by ``precompute`` (an empty (0, 0) array
    if none); ``iu`` the control index (row of ``controls``); ``ix`` (n_x,) int64 grid indices of ``x``
    in the backward pass, **all -1 in the forward pass** (off-grid state) so a lookup-table shortcut
    must fall back to computing from ``x`` then; writes the next state into ``x_next`` and returns the
    stage cost (``np.inf`` = infeasible). Must not allocate if speed matters.
``precompute(k, w_k, p, tab) -> None`` (optional)
    called once per step (backward and forward) before the controls are evaluated; fills ``tab``
    (shape ``table_shape``), e.g. a per-control table of the step's power demand and fuel, so the
    transition only does lookups.

Worked example (scalar LQ: x_{k+1} = x_k + u_k, cost u^2, terminal 10 x_N^2)::

    import numpy as np
    from numba import njit
    from optimize.dp.engine import DPProblem, solve

    @njit(cache=True)
    def lq(k, x, u, w_k, p, tab, iu, ix, x_next):
        x_next[0] = x[0] + u[0]
        return u[0] * u[0]

    prob = DPProblem(grids=[np.linspace(-2, 2, 81)], controls=np.linspace(-1, 1, 101)[:, None],
                     N=10, transition=lq, terminal_cost=lambda X: 10 * X[:, 0] ** 2)
    res = solve(prob, x0=[1.3])
    res.cost, res.x[:, 0], res.u[:, 0]      # forward-pass cost, trajectory and controls
    res.to_pandas()                          # one row per step
    res.V[0]                                 # cost-to-go at k = 0 on the grid (float32)
    res.evals_per_second                     # state-control evaluations per second (backward pass)

Parameters, exogenous inputs and the hook for, say, a charge-sustaining hybrid problem::

    prob = DPProblem(grids=[soc_grid, tcl_grid], controls=cartesian(modes, p_bat), N=len(v),
                     w=np.column_stack([v, a]), params=model_params, transition=prius_step,
                     terminal_bounds=[(soc0, None), (None, None)], boundary="levelset",
                     precompute=per_step_tables, table_shape=(n_controls, 4))

Memory: value functions are stored as float32, ``(N+1) x n_states`` (e.g. 993 x 41 x 101 -> 16 MB);
the level function, when used, as much again; the policy (int32, optional, ``store_policy=True``)
``N x n_states``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from optimize.dp import kernels as _k

__all__ = ["DPProblem", "DPResult", "ValueFunctions", "cartesian", "solve", "backward_pass",
           "forward_pass", "interpolate"]


#: Interpolations of the cost-to-go (``DPProblem.interp``; see :func:`forward_pass`).
FORWARD_INTERP = ("multilinear", "cubic_last", "reach_first")


def _interp_mode(interp: str, n_x: int) -> int:
    """Kernel code of an interpolation name (:func:`optimize.dp.kernels._interp_v`)."""
    if interp not in FORWARD_INTERP:
        raise ValueError(f"interp {interp!r}: choose one of {', '.join(FORWARD_INTERP)}")
    if interp == "reach_first" and n_x > 3:
        raise ValueError("interp 'reach_first' is offered for 1 to 3 states")
    return FORWARD_INTERP.index(interp)


def cartesian(*grids: Sequence[float]) -> np.ndarray:
    """Cartesian product of per-control grids as an (n_controls, n_u) float64 array (last varies fastest)."""
    arrs = [np.asarray(g, dtype=np.float64).ravel() for g in grids]
    mesh = np.meshgrid(*arrs, indexing="ij")
    return np.column_stack([m.ravel() for m in mesh])


@dataclass
class DPProblem:
    """A deterministic finite-horizon DP problem; see the module docstring.

    grids: one increasing 1-D array (>= 2 points) per state dimension.
    controls: (n_controls, n_u) array of admissible control vectors (a 1-D array means n_u = 1).
    N: number of steps.
    transition: ``@njit`` function ``(k, x, u, w_k, p, tab, iu, ix, x_next) -> stage cost``.
    w: (N, n_w) exogenous inputs per step (default: an (N, 0) array).
    params: anything numba can type (default: an empty float64 array).
    terminal_cost: grid-shaped array, or callable ``phi(X)`` on the (n_states, n_x) grid points, or None (0).
    terminal_bounds: optional per-state ``(lo, hi)`` box terminal set (None = unbounded).
    boundary: "none" (+inf outside the terminal set) or "levelset" (Elbert 2013).
    clip: look up the cost-to-go at the nearest box point for next states outside the grid.
    precompute: optional ``@njit`` hook ``(k, w_k, p, tab)``; table_shape: shape of ``tab`` (2-D).
    level_tol: level values <= level_tol count as feasible (levelset only).
    interp: how the cost-to-go is interpolated at off-grid next states, in both passes: "multilinear"
    (default), "cubic_last" (multilinear in the other states, cubic Hermite along the last one; see
    :func:`forward_pass`) or "reach_first" (multilinear, except along the first state in a cell the reach
    boundary of the terminal set cuts; levelset only, up to 3 states; see the module docstring). The level
    function is always multilinear.
    forward_kernel: optional ``@njit(cache=True)`` function ``f(*args)`` equal to
    ``optimize.dp.kernels.forward(transition, precompute, *args)``: the same loop with this problem's two
    functions called directly (e.g. :func:`optimize.formulations.fused.forward_hev`). The forward pass then
    runs it, and numba caches its compiled code on disk; the engine's kernel, which takes the functions as
    arguments, is compiled afresh in every process (about 2 s).
    """

    grids: Sequence[np.ndarray]
    controls: np.ndarray
    N: int
    transition: Callable
    w: np.ndarray | None = None
    params: Any = None
    terminal_cost: Any = None
    terminal_bounds: Sequence[tuple] | None = None
    boundary: str = "none"
    clip: bool = False
    precompute: Callable | None = None
    table_shape: tuple = (0, 0)
    level_tol: float = 0.0
    interp: str = "multilinear"
    forward_kernel: Callable | None = None

    def __post_init__(self):
        self.grids = [np.ascontiguousarray(g, dtype=np.float64).ravel() for g in self.grids]
        for d, g in enumerate(self.grids):
            if g.size < 2 or not np.all(np.diff(g) > 0):
                raise ValueError(f"grid {d} must be strictly increasing with at least 2 points")
        c = np.asarray(self.controls, dtype=np.float64)
        if c.ndim == 1:
            c = c[:, None]
        if c.ndim != 2 or c.shape[0] == 0:
            raise ValueError("controls must be a non-empty (n_controls, n_u) array")
        self.controls = np.ascontiguousarray(c)
        self.N = int(self.N)
        if self.N < 1:
            raise ValueError("N must be >= 1")
        if self.w is None:
            self.w = np.zeros((self.N, 0))
        w = np.asarray(self.w, dtype=np.float64)
        if w.ndim == 1:
            w = w[:, None]
        if w.shape[0] != self.N:
            raise ValueError(f"w must have N={self.N} rows, got {w.shape[0]}")
        self.w = np.ascontiguousarray(w)
        if self.params is None:
            self.params = np.zeros(0)
        if self.boundary not in ("none", "levelset"):
            raise ValueError("boundary must be 'none' or 'levelset'")
        if len(self.table_shape) != 2:
            raise ValueError("table_shape must be 2-D")
        _interp_mode(self.interp, len(self.grids))

    # ---- derived grid data -------------------------------------------------------------------
    @property
    def n_x(self) -> int:
        """Number of state variables."""
        return len(self.grids)

    @property
    def grid_shape(self) -> tuple:
        """Nodes per state variable."""
        return tuple(g.size for g in self.grids)

    @property
    def n_states(self) -> int:
        """Number of grid nodes (product of the grid sizes)."""
        return int(np.prod(self.grid_shape))

    @property
    def n_controls(self) -> int:
        """Number of candidate controls."""
        return self.controls.shape[0]

    def grid_points(self) -> np.ndarray:
        """All grid states, (n_states, n_x), C order (last state dimension varies fastest)."""
        return cartesian(*self.grids)

    def _grid_arrays(self):
        nx = self.n_x
        n = np.array([g.size for g in self.grids], dtype=np.int64)
        lo = np.array([g[0] for g in self.grids])
        inv_dx = np.empty(nx)
        uniform = np.zeros(nx, dtype=np.bool_)
        pts = np.zeros((nx, int(n.max())))
        for d, g in enumerate(self.grids):
            dx = np.diff(g)
            uniform[d] = np.max(np.abs(dx - dx.mean())) <= 1e-10 * max(abs(g[-1] - g[0]), 1e-300)
            inv_dx[d] = (g.size - 1) / (g[-1] - g[0])
            pts[d, : g.size] = g
        strides = np.ones(nx, dtype=np.int64)
        for d in range(nx - 2, -1, -1):
            strides[d] = strides[d + 1] * n[d + 1]
        return lo, inv_dx, n, uniform, pts, strides

    def terminal_arrays(self):
        """(V_N, L_N) on the flattened grid: terminal cost (+inf outside the terminal set) and level."""
        X = self.grid_points()
        if self.terminal_cost is None:
            phi = np.zeros(X.shape[0])
        elif callable(self.terminal_cost):
            phi = np.asarray(self.terminal_cost(X), dtype=np.float64).reshape(-1)
        else:
            phi = np.asarray(self.terminal_cost, dtype=np.float64).reshape(-1)
        if phi.size != X.shape[0]:
            raise ValueError("terminal cost must have one value per grid state")
        level = self.terminal_level(X)
        level[~(phi < np.inf)] = np.inf
        if self.boundary == "none":
            phi = np.where(level > 0, np.inf, phi)
        return phi, level

    def terminal_level(self, X) -> np.ndarray:
        """Signed terminal level of the states X (m, n_x): ``max_d max(lo_d - x_d, x_d - hi_d) / h_d`` in
        grid steps (h_d: dimension d's mean spacing), negative inside the terminal box, 0 on its boundary,
        positive outside; -1 everywhere without bounds."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        level = np.full(X.shape[0], -np.inf)
        if self.terminal_bounds is not None:
            if len(self.terminal_bounds) != self.n_x:
                raise ValueError("terminal_bounds needs one (lo, hi) per state")
            for d, (blo, bhi) in enumerate(self.terminal_bounds):
                g = self.grids[d]
                h = (g[-1] - g[0]) / (g.size - 1)
                if blo is not None:
                    level = np.maximum(level, (blo - X[:, d]) / h)
                if bhi is not None:
                    level = np.maximum(level, (X[:, d] - bhi) / h)
        return np.where(np.isfinite(level), level, -1.0)


@dataclass
class ValueFunctions:
    """Output of the backward pass: ``V`` of shape ``(N+1, *grid_shape)``, float32, optional level ``L`` and policy; ``kernel``
    names the backward kernel that produced them."""

    V: np.ndarray
    L: np.ndarray | None
    policy: np.ndarray | None
    t_backward: float
    n_evaluations: int
    kernel: str = "generic"


@dataclass
class DPResult:
    """Optimal trajectory from the forward pass (style of python-control's TimeResponseData).

    x (N+1, n_x) states, u (N, n_u) controls, u_index (N,) control rows, stage_cost (N,),
    terminal_cost (float), cost = sum(stage_cost) + terminal_cost, predicted_cost (N,) the minimised
    stage + interpolated cost-to-go at each step, feasible (bool: all steps done, finite cost and, with a
    terminal set, the final state inside it within ``level_tol``), terminal_level, V / L / policy (from
    the backward pass), t_backward, t_forward, solve_time, n_evaluations (state-control evaluations of the
    backward pass) and evals_per_second.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    u_index: np.ndarray
    stage_cost: np.ndarray
    terminal_cost: float
    cost: float
    predicted_cost: np.ndarray
    feasible: bool
    terminal_level: float
    steps_completed: int
    V: np.ndarray = field(repr=False)
    L: np.ndarray | None = field(repr=False)
    policy: np.ndarray | None = field(repr=False)
    t_backward: float = 0.0
    t_forward: float = 0.0
    n_evaluations: int = 0
    kernel: str = "generic"

    @property
    def solve_time(self) -> float:
        """Backward plus forward pass time, in s."""
        return self.t_backward + self.t_forward

    @property
    def evals_per_second(self) -> float:
        """State-control evaluations per second of the backward pass."""
        return self.n_evaluations / self.t_backward if self.t_backward > 0 else float("nan")

    def plot(self, path=None, title=None):
        """States, controls and cumulative stage cost over the steps (:func:`optimize.plotting.plot_dp_result`).
        Returns the Figure."""
        from optimize.plotting import plot_dp_result

        return plot_dp_result(self, path, title)

    def to_pandas(self):
        """One row per step k = 0..N: states x0.., controls u0.. and stage cost (NaN at k = N)."""
        import pandas as pd

        N = self.u.shape[0]
        data = {"k": self.t}
        for d in range(self.x.shape[1]):
            data[f"x{d}"] = self.x[:, d]
        for j in range(self.u.shape[1]):
            data[f"u{j}"] = np.append(self.u[:, j], np.nan)
        data["u_index"] = np.append(self.u_index.astype(float), np.nan)
        data["stage_cost"] = np.append(self.stage_cost, np.nan)
        df = pd.DataFrame(data)
        df.attrs.update(cost=self.cost, terminal_cost=self.terminal_cost, feasible=self.feasible,
                        solve_time=self.solve_time, n_steps=N)
        return df


def _tab(prob: DPProblem) -> np.ndarray:
    return np.zeros(tuple(int(s) for s in prob.table_shape))


#: Parts of the backward pass between two progress reports, as a fraction of the steps.
PROGRESS_PART = 0.01


def _step_parts(N: int, progress) -> list:
    """Step ranges ``(k_hi, k_lo)`` of a backward pass from N down to 0: one without ``progress``, else
    parts of about :data:`PROGRESS_PART` of the steps (each a kernel call: tens of microseconds)."""
    if progress is None:
        return [(N, 0)]
    size = max(1, int(round(N * PROGRESS_PART)))
    return [(hi, max(0, hi - size)) for hi in range(N, 0, -size)]


def backward_pass(prob: DPProblem, store_policy: bool = False, progress=None) -> ValueFunctions:
    """Run the backward pass; returns the stored value functions (float32). ``progress``: as in
    :func:`solve`."""
    grid = prob._grid_arrays()
    X = prob.grid_points()
    ns = X.shape[0]
    phi, level = prob.terminal_arrays()
    use_level = prob.boundary == "levelset"
    VT = np.empty((prob.N + 1, ns), dtype=np.float32)
    VT[prob.N] = phi
    LT = np.zeros((prob.N + 1 if use_level else 1, ns), dtype=np.float32)
    if use_level:
        LT[prob.N] = level
    else:
        LT = np.zeros((prob.N + 1, 0), dtype=np.float32)  # unused
    policy = np.full((prob.N, ns) if store_policy else (1, 1), -1, dtype=np.int32)
    pre = prob.precompute if prob.precompute is not None else _k.no_precompute
    t0 = time.perf_counter()
    tab = _tab(prob)
    mode = _interp_mode(prob.interp, prob.n_x)
    if progress is not None:
        progress(0, prob.N)
    for hi, lo in _step_parts(prob.N, progress):
        _k.backward(prob.transition, pre, hi, lo, X, prob.controls, prob.w, prob.params, tab, VT, LT, use_level,
                    float(prob.level_tol), *grid, bool(prob.clip), policy, bool(store_policy), mode)
        if progress is not None:
            progress(prob.N - lo, prob.N)
    t_b = time.perf_counter() - t0
    shape = (prob.N + 1,) + prob.grid_shape
    return ValueFunctions(V=VT.reshape(shape), L=LT.reshape(shape) if use_level else None,
                          policy=policy.reshape((prob.N,) + prob.grid_shape) if store_policy else None,
                          t_backward=t_b, n_evaluations=prob.N * ns * prob.n_controls)


def interpolate(prob: DPProblem, values: np.ndarray, points, interp: str = "multilinear") -> np.ndarray:
    """Interpolation of a grid-shaped array at points (m, n_x) with the engine's rules; ``interp`` as in
    :func:`forward_pass` (default multilinear; "reach_first" needs the level function, so here it is
    multilinear)."""
    mode = _interp_mode(interp, prob.n_x)
    grid = prob._grid_arrays()
    Q = np.atleast_2d(np.asarray(points, dtype=np.float64))
    V = np.ascontiguousarray(np.asarray(values).reshape(-1))
    return _k.interp_points(V, Q, *grid, bool(prob.clip), mode)


def forward_pass(prob: DPProblem, vf: ValueFunctions, x0, interp: str | None = None) -> DPResult:
    """Simulate the optimal policy from the true initial state x0 (may be off-grid).

    ``interp`` is how the one-step decision interpolates the cost-to-go at the next state (default
    ``prob.interp``, the backward pass's rule): ``"multilinear"``, ``"reach_first"`` (see the module
    docstring) or ``"cubic_last"``: multilinear in the other states,
    cubic Hermite along the last one (central-difference slopes: exact on quadratics, equal to the node
    values at nodes, C1 across them). A cost-to-go convex along an axis is overestimated between nodes by
    linear interpolation, whose kinks then hold the state on a node; the cubic has no kinks. It needs a
    uniform last grid of at least 3 nodes and finite values around the query (elsewhere it falls back to
    multilinear). The level function is always multilinear (it is piecewise linear)."""
    interp = prob.interp if interp is None else interp
    mode = _interp_mode(interp, prob.n_x)
    x0 = np.ascontiguousarray(np.asarray(x0, dtype=np.float64).ravel())
    if x0.size != prob.n_x:
        raise ValueError(f"x0 must have {prob.n_x} entries")
    grid = prob._grid_arrays()
    N, ns = prob.N, prob.n_states
    use_level = vf.L is not None
    VT = vf.V.reshape(N + 1, ns)
    LT = vf.L.reshape(N + 1, ns) if use_level else np.zeros((N + 1, 0), dtype=np.float32)
    X_out = np.full((N + 1, prob.n_x), np.nan)
    U_idx = np.full(N, -1, dtype=np.int64)
    stage = np.full(N, np.nan)
    pred = np.full(N, np.nan)
    pre = prob.precompute if prob.precompute is not None else _k.no_precompute
    t0 = time.perf_counter()
    args = (N, x0, prob.controls, prob.w, prob.params, _tab(prob), VT, LT, use_level, float(prob.level_tol),
            *grid, bool(prob.clip), X_out, U_idx, stage, pred, mode)
    if prob.forward_kernel is not None:
        done = prob.forward_kernel(*args)
    else:
        done = _k.forward(prob.transition, pre, *args)
    t_f = time.perf_counter() - t0
    u = np.full((N, prob.controls.shape[1]), np.nan)
    ok = U_idx >= 0
    u[ok] = prob.controls[U_idx[ok]]
    phi, level = prob.terminal_arrays()
    if done == N:
        xN = X_out[N][None, :]
        term = float(interpolate(prob, phi, xN)[0])
        lvl = float(prob.terminal_level(xN)[0])
        cost = float(np.sum(stage) + term)
        feasible = bool(np.isfinite(cost) and lvl <= prob.level_tol + 1e-9)
    else:
        term, lvl, cost, feasible = np.inf, np.inf, np.inf, False
    return DPResult(t=np.arange(N + 1), x=X_out, u=u, u_index=U_idx, stage_cost=stage,
                    terminal_cost=term, cost=cost, predicted_cost=pred, feasible=feasible,
                    terminal_level=float(lvl), steps_completed=int(done), V=vf.V, L=vf.L,
                    policy=vf.policy, t_backward=vf.t_backward, t_forward=t_f,
                    n_evaluations=vf.n_evaluations, kernel=vf.kernel)


def solve(prob: DPProblem, x0, store_policy: bool = False, progress=None) -> DPResult:
    """Backward pass then forward pass from x0; returns a :class:`DPResult`.

    ``progress``: None, or a callable ``progress(done, total)`` called during the backward pass with the
    number of steps done and the number of steps N (integers): ``(0, N)`` first, then after every part of
    about 1 % of the steps, ending with ``(N, N)``. The pass then runs in about 100 parts, one kernel call
    each (a call costs tens of microseconds); it returns the same values as in one piece. The forward pass
    (a few percent of the solve) reports nothing."""
    vf = backward_pass(prob, store_policy=store_policy, progress=progress)
    return forward_pass(prob, vf, x0)
