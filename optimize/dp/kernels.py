"""Compiled (numba) kernels of the generic DP engine; see :mod:`optimize.dp` for the public API.

Everything here is private. The kernels take the user's ``@njit`` transition and precompute functions
as first-class arguments: numba compiles one specialisation of each kernel per distinct user function
(static dispatch, so LLVM can inline the user's code into the inner loop).

Grid description (per state dimension ``d``; states are flattened in C order, last dimension fastest):

* ``lo[d]``, ``inv_dx[d]``: first point and 1/spacing (used when ``uniform[d]``: O(1) lookup);
* ``n[d]``: number of points (>= 2);
* ``pts[d, :n[d]]``: the points (used for non-uniform grids: binary search);
* ``strides[d]``: flat-index stride.
"""
from __future__ import annotations

import numpy as np
import numba
from numba import njit, prange

# Snap tolerance in grid-index units: a query within 1e-9 of a grid point is treated as exactly on it,
# so that zero-weight corners (which may be +inf) never contaminate an on-grid lookup.
_SNAP = 1e-9


@njit(cache=True)
def no_precompute(k, w_k, p, tab):  # pragma: no cover - compiled
    """Default per-step hook: does nothing."""
    return


@njit(inline="always", cache=True)
def _locate(x, d, lo, inv_dx, n, uniform, pts, clip, ib, tb):
    """Cell index and fraction of ``x`` along dimension ``d`` into ib[d], tb[d]; False if off-grid."""
    nd = n[d]
    if uniform[d]:
        r = (x - lo[d]) * inv_dx[d]
    else:
        if x <= pts[d, 0]:
            r = (x - pts[d, 0]) / (pts[d, 1] - pts[d, 0])
        elif x >= pts[d, nd - 1]:
            r = nd - 1 + (x - pts[d, nd - 1]) / (pts[d, nd - 1] - pts[d, nd - 2])
        else:
            a = 0
            b = nd - 1
            while b - a > 1:
                m = (a + b) >> 1
                if pts[d, m] <= x:
                    a = m
                else:
                    b = m
            r = a + (x - pts[d, a]) / (pts[d, a + 1] - pts[d, a])
    ri = np.floor(r + 0.5)
    if abs(r - ri) < _SNAP:
        r = ri
    if not (r >= 0.0):  # also catches NaN
        if clip and r == r:
            r = 0.0
        else:
            return False
    if r > nd - 1:
        if clip:
            r = float(nd - 1)
        else:
            return False
    i = int(r)
    if i > nd - 2:
        i = nd - 2
    ib[d] = i
    tb[d] = r - i
    return True


@njit(inline="always", cache=True)
def _locate_all(xq, nx, lo, inv_dx, n, uniform, pts, clip, ib, tb):
    for d in range(nx):
        if not _locate(xq[d], d, lo, inv_dx, n, uniform, pts, clip, ib, tb):
            return False
    return True


@njit(inline="always", cache=True)
def _corner(c, nd, strides, ib, tb):
    """(multilinear weight, flat offset) of corner ``c`` (bit d set: upper node in dimension d) of the cell
    located at (ib, tb), over the first ``nd`` dimensions."""
    wgt = 1.0
    off = 0
    for d in range(nd):
        if (c >> d) & 1:
            wgt *= tb[d]
            off += (ib[d] + 1) * strides[d]
        else:
            wgt *= 1.0 - tb[d]
            off += ib[d] * strides[d]
    return wgt, off


@njit(cache=True)
def _interp_slow(V, nx, strides, ib, tb):
    """Exact multilinear interpolation that ignores zero-weight corners; +inf if any
    positive-weight corner is +inf."""
    acc = 0.0
    for c in range(1 << nx):
        wgt, off = _corner(c, nx, strides, ib, tb)
        if wgt == 0.0:
            continue
        v = np.float64(V[off])
        if not (v < np.inf):
            return np.inf
        acc += wgt * v
    return acc


@njit(inline="always", cache=True)
def _interp(V, nx, strides, ib, tb):
    """Multilinear interpolation of the flat array V at the located point (ib, tb).

    Fast path specialised for 1, 2 and 3 dimensions; falls back to :func:`_interp_slow` whenever the
    fast result is not finite (an +inf corner, possibly with zero weight)."""
    if nx == 1:
        i0 = ib[0]
        t0 = tb[0]
        r = (1.0 - t0) * V[i0] + t0 * V[i0 + 1]
    elif nx == 2:
        s0 = strides[0]
        t0 = tb[0]
        t1 = tb[1]
        o = ib[0] * s0 + ib[1]
        r = (1.0 - t0) * ((1.0 - t1) * V[o] + t1 * V[o + 1]) + t0 * (
            (1.0 - t1) * V[o + s0] + t1 * V[o + s0 + 1])
    elif nx == 3:
        s0 = strides[0]
        s1 = strides[1]
        t0 = tb[0]
        t1 = tb[1]
        t2 = tb[2]
        o = ib[0] * s0 + ib[1] * s1 + ib[2]
        a = (1.0 - t2) * V[o] + t2 * V[o + 1]
        b = (1.0 - t2) * V[o + s1] + t2 * V[o + s1 + 1]
        c = (1.0 - t2) * V[o + s0] + t2 * V[o + s0 + 1]
        e = (1.0 - t2) * V[o + s0 + s1] + t2 * V[o + s0 + s1 + 1]
        r = (1.0 - t0) * ((1.0 - t1) * a + t1 * b) + t0 * ((1.0 - t1) * c + t1 * e)
    else:
        return _interp_slow(V, nx, strides, ib, tb)
    if np.isfinite(r):
        return r
    return _interp_slow(V, nx, strides, ib, tb)


@njit(inline="always", cache=True)
def _hermite(V, o, c, nl, t):
    """Cubic Hermite along a uniform axis of ``nl >= 3`` nodes (values V[o], V[o+1], ...) in cell c at
    fraction t: slopes are central differences (one-sided second-order ones at the two end nodes), so
    the interpolant is exact on quadratics, C1 across nodes, and equals the node values at t = 0, 1."""
    f0 = np.float64(V[o + c])
    f1 = np.float64(V[o + c + 1])
    if t == 0.0:
        return f0
    if t == 1.0:
        return f1
    if c > 0:
        m0 = 0.5 * (f1 - np.float64(V[o + c - 1]))
    else:
        m0 = 0.5 * (-3.0 * f0 + 4.0 * f1 - np.float64(V[o + 2]))
    if c + 2 < nl:
        m1 = 0.5 * (np.float64(V[o + c + 2]) - f0)
    else:
        m1 = 0.5 * (3.0 * f1 - 4.0 * f0 + np.float64(V[o + c - 1]))
    t2 = t * t
    t3 = t2 * t
    return ((2.0 * t3 - 3.0 * t2 + 1.0) * f0 + (t3 - 2.0 * t2 + t) * m0 + (3.0 * t2 - 2.0 * t3) * f1
            + (t3 - t2) * m1)


@njit(cache=True)
def _interp_cubic_last(V, nx, n, uniform, strides, ib, tb):
    """Multilinear in the first nx-1 dimensions, cubic Hermite (:func:`_hermite`) along the last one.

    Why: a cost-to-go convex along that axis is overestimated between nodes by linear interpolation, and
    the kinks at the nodes draw a one-step minimisation onto them. Falls back to :func:`_interp` (and its
    +inf rules) where the last axis is non-uniform or has fewer than 3 nodes, or the result is not
    finite (a value the cubic reads is +inf). For 2 and 3 dimensions the corners are combined in the
    order of the fused Thermal kernels (same rounding)."""
    nl = n[nx - 1]
    if nl < 3 or not uniform[nx - 1]:
        return _interp(V, nx, strides, ib, tb)
    c = ib[nx - 1]
    t = tb[nx - 1]
    if nx == 1:
        r = _hermite(V, 0, c, nl, t)
    elif nx == 2:
        s0 = strides[0]
        t0 = tb[0]
        o = ib[0] * s0
        r = (1.0 - t0) * _hermite(V, o, c, nl, t) + t0 * _hermite(V, o + s0, c, nl, t)
    elif nx == 3:
        s0 = strides[0]
        s1 = strides[1]
        t0 = tb[0]
        t1 = tb[1]
        o = ib[0] * s0 + ib[1] * s1
        a = _hermite(V, o, c, nl, t)
        b = _hermite(V, o + s1, c, nl, t)
        cc = _hermite(V, o + s0, c, nl, t)
        e = _hermite(V, o + s0 + s1, c, nl, t)
        r = (1.0 - t0) * ((1.0 - t1) * a + t1 * b) + t0 * ((1.0 - t1) * cc + t1 * e)
    else:
        r = 0.0
        for corner in range(1 << (nx - 1)):
            wgt, off = _corner(corner, nx - 1, strides, ib, tb)
            if wgt != 0.0:
                r += wgt * _hermite(V, off, c, nl, t)
    if np.isfinite(r):
        return r
    return _interp(V, nx, strides, ib, tb)


@njit(inline="always", cache=True)
def _lin_reach(v0, v1, l0, l1, tol, t):
    """Linear interpolation between node values v0, v1 (levels l0, l1) at fraction t, except in a cell the
    reach boundary cuts (one level above tol, one at or below): there the unreachable node's value is
    placed where the cell's linear level crosses tol, and a query on the reachable side interpolates
    between that point and the reachable node.

    Why: the value of a node outside the reach is the cost of its least-level control (the most charging),
    which is about the cost on the boundary itself; the plain chord from that node puts a lower value on
    the boundary than the boundary costs, and a policy then lets the charge fall towards the boundary and
    pays the most charging to recover (the boundary-line idea of Sundstrom et al. 2010, with the boundary
    located from the signed level)."""
    kind, s = _reach_rule(l0, l1, tol, t)
    if kind == 1:
        return v0 + s * (v1 - v0)
    if kind == 2:
        return v1
    if kind == 3:
        return v0
    return (1.0 - t) * v0 + t * v1


@njit(cache=True)
def _interp_reach(V, L, tol, nx, strides, ib, tb):
    """Multilinear interpolation of V, except along the first dimension in a cell the reach boundary of
    the level L cuts (:func:`_lin_reach`, per node of the other dimensions; with 3 dimensions the last one
    is interpolated first, as in the fused Thermal-Cabin slices, then the first, then the second). Without
    levels (L empty), or where the result is not finite, :func:`_interp` (and its +inf rules)."""
    if L.shape[0] == 0 or nx > 3:
        return _interp(V, nx, strides, ib, tb)
    c = ib[0]
    t = tb[0]
    s0 = strides[0]
    if nx == 1:
        r = _lin_reach(np.float64(V[c]), np.float64(V[c + 1]), np.float64(L[c]), np.float64(L[c + 1]), tol, t)
    elif nx == 2:
        t1 = tb[1]
        o = c * s0 + ib[1]
        a = _lin_reach(np.float64(V[o]), np.float64(V[o + s0]), np.float64(L[o]), np.float64(L[o + s0]), tol, t)
        b = _lin_reach(np.float64(V[o + 1]), np.float64(V[o + s0 + 1]), np.float64(L[o + 1]),
                       np.float64(L[o + s0 + 1]), tol, t)
        r = (1.0 - t1) * a + t1 * b
    else:
        s1 = strides[1]
        t1 = tb[1]
        t2 = tb[2]
        o = c * s0 + ib[1] * s1 + ib[2]
        r0 = 0.0
        r1 = 0.0
        for j in range(2):
            oj = o + j * s1
            va = (1.0 - t2) * V[oj] + t2 * V[oj + 1]
            vb = (1.0 - t2) * V[oj + s0] + t2 * V[oj + s0 + 1]
            la = (1.0 - t2) * L[oj] + t2 * L[oj + 1]
            lb = (1.0 - t2) * L[oj + s0] + t2 * L[oj + s0 + 1]
            if j == 0:
                r0 = _lin_reach(va, vb, la, lb, tol, t)
            else:
                r1 = _lin_reach(va, vb, la, lb, tol, t)
        r = (1.0 - t1) * r0 + t1 * r1
    if np.isfinite(r):
        return r
    return _interp(V, nx, strides, ib, tb)


@njit(inline="always", cache=True)
def _interp_v(mode, V, L, tol, nx, n, uniform, strides, ib, tb):
    """The cost-to-go interpolation of ``mode`` (the engine's ``FORWARD_INTERP`` index): 0 multilinear,
    1 cubic along the last dimension (:func:`_interp_cubic_last`), 2 multilinear with the reach boundary
    along the first (:func:`_interp_reach`; L is the level function, empty without one)."""
    if mode == 1:
        return _interp_cubic_last(V, nx, n, uniform, strides, ib, tb)
    if mode == 2:
        return _interp_reach(V, L, tol, nx, strides, ib, tb)
    return _interp(V, nx, strides, ib, tb)


@njit(inline="always", cache=True)
def level_needs_cost(lv, tol, feas, Lsel):
    """Whether a control of interpolated level ``lv`` can still be chosen (so its cost is needed), given
    the current choice (``feas``: it reaches the terminal set; ``Lsel``: its level)."""
    if lv <= tol:
        return True
    return (not feas) and lv <= Lsel


@njit(inline="always", cache=True)
def level_better(lv, v, tol, feas, Lsel, best):
    """The level-set choice rule: among controls reaching the terminal set (level <= tol) the one of least
    cost; if none does, the one of least level (then least cost). Ties keep the earlier control."""
    if lv <= tol:
        return (not feas) or v < best
    if feas:
        return False
    return lv < Lsel or (lv == Lsel and v < best)


@njit(inline="always", cache=True)
def level_choose(lv, v, tol, j, best, Lsel, feas):
    """:func:`level_better` applied to slot ``j`` of the arrays ``best``, ``Lsel``, ``feas``: a control the
    rule prefers becomes the choice there, reaching the set when its level is at most ``tol``."""
    if level_better(lv, v, tol, feas[j], Lsel[j], best[j]):
        best[j] = v
        Lsel[j] = lv
        feas[j] = lv <= tol


@njit(parallel=True, cache=False)  # no disk cache: kernels specialised on a user function never hit it
def backward(transition, precompute, N, k_lo, X, controls, w, p, tab, VT, LT, use_level, level_tol,
             lo, inv_dx, n, uniform, pts, strides, clip, policy, store_policy, mode):
    """Backward pass, or the part of it from step N - 1 down to k_lo (the engine runs it in parts to report
    progress). VT[N] (and LT[N] when use_level) must hold the data of step N (the terminal data for the
    whole pass); fills VT[k_lo..N-1], LT[k_lo..N-1] and, when store_policy, policy[k_lo..N-1] (argmin
    control index, -1 if none).
    ``mode``: the cost-to-go interpolation (:func:`_interp_v`)."""
    n_states = X.shape[0]
    nx = X.shape[1]
    nu = controls.shape[0]
    nthreads = numba.get_num_threads()
    nchunks = nthreads * 8
    if nchunks > n_states:
        nchunks = n_states
    csize = (n_states + nchunks - 1) // nchunks
    nchunks = (n_states + csize - 1) // csize
    # dynamic scheduling of the chunks (one chunk per grab): robust against a thread being descheduled
    # by other load on the machine, where numba's default static split would stall every step
    old_chunk = numba.set_parallel_chunksize(1)
    for k in range(N - 1, k_lo - 1, -1):
        precompute(k, w[k], p, tab)
        Vn = VT[k + 1]
        Ln = LT[k + 1]
        Vk = VT[k]
        Lk = LT[k]
        wk = w[k]
        for c in prange(nchunks):
            x = np.empty(nx)
            xn = np.empty(nx)
            ix = np.empty(nx, np.int64)
            ib = np.empty(nx, np.int64)
            tb = np.empty(nx)
            s_end = min(n_states, (c + 1) * csize)
            for s in range(c * csize, s_end):
                rem = s
                for d in range(nx):
                    x[d] = X[s, d]
                    q = rem // strides[d]
                    ix[d] = q
                    rem -= q * strides[d]
                best = np.inf
                Lmin = np.inf
                Lsel = np.inf
                feas = False
                bi = -1
                for iu in range(nu):
                    cst = transition(k, x, controls[iu], wk, p, tab, iu, ix, xn)
                    if not (cst < np.inf):
                        continue
                    if not _locate_all(xn, nx, lo, inv_dx, n, uniform, pts, clip, ib, tb):
                        continue
                    lv = 0.0
                    if use_level:
                        lv = _interp(Ln, nx, strides, ib, tb)
                        if not (lv < np.inf):
                            continue
                        if lv < Lmin:
                            Lmin = lv
                        if not level_needs_cost(lv, level_tol, feas, Lsel):
                            continue
                    v = cst + _interp_v(mode, Vn, Ln, level_tol, nx, n, uniform, strides, ib, tb)
                    if not (v < np.inf):
                        continue
                    if use_level:
                        if level_better(lv, v, level_tol, feas, Lsel, best):
                            best = v
                            Lsel = lv
                            feas = lv <= level_tol
                            bi = iu
                    elif v < best:
                        best = v
                        bi = iu
                if use_level:
                    Lk[s] = Lmin
                Vk[s] = best
                if store_policy:
                    policy[k, s] = bi
    numba.set_parallel_chunksize(old_chunk)


@njit(cache=False)
def forward(transition, precompute, N, x0, controls, w, p, tab, VT, LT, use_level, level_tol,
            lo, inv_dx, n, uniform, pts, strides, clip, X_out, U_idx, stage, pred, mode):
    """Forward pass from the true (off-grid) state x0. Returns the number of steps completed
    (N unless no admissible control was found at some step). ``mode``: the cost-to-go interpolation
    (:func:`_interp_v`; the level stays multilinear)."""
    nx = x0.shape[0]
    nu = controls.shape[0]
    x = x0.copy()
    xn = np.empty(nx)
    ix = np.full(nx, -1, np.int64)
    ib = np.empty(nx, np.int64)
    tb = np.empty(nx)
    for d in range(nx):
        X_out[0, d] = x[d]
    for k in range(N):
        precompute(k, w[k], p, tab)
        wk = w[k]
        Vn = VT[k + 1]
        Ln = LT[k + 1]
        best = np.inf
        Lsel = np.inf
        feas = False
        bi = -1
        for iu in range(nu):
            cst = transition(k, x, controls[iu], wk, p, tab, iu, ix, xn)
            if not (cst < np.inf):
                continue
            if not _locate_all(xn, nx, lo, inv_dx, n, uniform, pts, clip, ib, tb):
                continue
            if use_level:
                lv = _interp(Ln, nx, strides, ib, tb)
                if not (lv < np.inf):
                    continue
                if not level_needs_cost(lv, level_tol, feas, Lsel):
                    continue
                v = cst + _interp_v(mode, Vn, Ln, level_tol, nx, n, uniform, strides, ib, tb)
                if not (v < np.inf):
                    continue
                if level_better(lv, v, level_tol, feas, Lsel, best):
                    best = v
                    Lsel = lv
                    feas = lv <= level_tol
                    bi = iu
            else:
                v = cst + _interp_v(mode, Vn, Ln, level_tol, nx, n, uniform, strides, ib, tb)
                if v < best:
                    best = v
                    bi = iu
        if bi < 0:
            return k
        cst = transition(k, x, controls[bi], wk, p, tab, bi, ix, xn)
        U_idx[k] = bi
        stage[k] = cst
        pred[k] = best
        for d in range(nx):
            x[d] = xn[d]
            X_out[k + 1, d] = xn[d]
    return N


@njit(cache=True)
def interp_points(V, Q, lo, inv_dx, n, uniform, pts, strides, clip, mode):
    """Interpolate flat V at each row of Q (m, nx); +inf off-grid. ``mode``: as in :func:`_interp_v`."""
    m, nx = Q.shape
    out = np.empty(m)
    ib = np.empty(nx, np.int64)
    tb = np.empty(nx)
    for j in range(m):
        if _locate_all(Q[j], nx, lo, inv_dx, n, uniform, pts, clip, ib, tb):
            out[j] = _interp_v(mode, V, V[:0], 0.0, nx, n, uniform, strides, ib, tb)
        else:
            out[j] = np.inf
    return out


@njit(inline="always", cache=True)
def _reach_rule(l0, l1, tol, t):
    """Where :func:`_lin_reach` reads a cell of levels l0, l1 at fraction t, as (kind, s): kind 0, the plain
    chord at t; 1, the chord from the reach boundary, ``v0 + s (v1 - v0)``; 2, the node v1; 3, the node v0."""
    if l0 > tol and l1 <= tol:
        tb = (l0 - tol) / (l0 - l1)
        if t >= tb:
            if tb >= 1.0:
                return 2, 1.0
            return 1, (t - tb) / (1.0 - tb)
    elif l1 > tol and l0 <= tol:
        tb = (tol - l0) / (l1 - l0)
        if t <= tb:
            if tb <= 0.0:
                return 3, 0.0
            return 1, t / tb
    return 0, t


@njit(inline="always", cache=True)
def reach_weights(l0, l1, tol, t):
    """:func:`_lin_reach` as weights (a, b) of the node values, ``a v0 + b v1`` (equal in exact arithmetic):
    a kernel whose cell levels are shared by many queries applies them to values interpolated along the
    other dimensions first."""
    kind, s = _reach_rule(l0, l1, tol, t)
    if kind == 1:
        return 1.0 - s, s
    if kind == 2:
        return 0.0, 1.0
    if kind == 3:
        return 1.0, 0.0
    return 1.0 - t, t
