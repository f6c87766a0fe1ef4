"""Fused backward-pass kernels for Thermal-DP and Thermal-Cabin-DP (private; see optimize.formulations).

Why: the generic engine (:mod:`optimize.dp`) evaluates every (state, control) pair through the user
transition and interpolates the cost-to-go and the level function independently; on 2 cores it runs at
about 25-65 M evaluations/s, i.e. ~10 s for Thermal-DP and several minutes for Thermal-Cabin-DP on the
paper's grids. These kernels compute *the same* value and level functions (same equations, same
interpolation formulas and the same lexicographic level-set rule and tie-breaking, so the results agree
with the engine to rounding; cross-checked in tests/test_formulations.py) by exploiting the structure:

* the next SOC depends only on (SOC node, power control): located once per pair, and infeasible power
  controls are skipped for a whole SOC row;
* the loop over the coolant nodes is innermost (contiguous, branch-light);
* Thermal-Cabin: when the heater is not limited by the coolant, the next cabin temperature depends only on
  (T_cab node, Q_heat): V and L are interpolated along T_cab once per (T_cab node, Q_heat) into 2-D slices
  (the engine's own trilinear formula, first stage), so the inner loop is bilinear; where the heater core
  limits the heat (cold coolant) the full trilinear interpolation is used. The "hold the bound" heater
  control's heat depends on the cabin node only: it is one more (T_cab node, heat) slice per node.
* levels are signed (negative inside the terminal set) and the true minimum is stored, with the engine's
  choice rule (:func:`optimize.dp.kernels.level_choose`).

The forward pass is the engine's (:func:`optimize.dp.engine.forward_pass`) on the value functions produced here.
"""
from __future__ import annotations


import numpy as np
from numba import njit, prange

from optimize.formulations.layout import (_C_CH, _C_CHI, _C_CREL, _C_PEN, _C_SH, _C_SHI, _C_SLO, _C_TH, _C_THI, _C_TLO, _C_TS,
                                          _C_TAMB, _C_WBL, _CCAB, _CENG, _CP, _EPS, _GAMMA, _LHV, _MS0, _QSUN,
                                          _RECIRC, _T_OK, _T_PE, _T_SOC0, _T_WF, _UACAB, _A_FCLG, _A_LOSSG)
from optimize.dp.kernels import _interp_slow as _slow  # the engine's exact multilinear interpolation
from optimize.dp.kernels import _hermite, _interp_cubic_last  # the engine's cubic along the cabin axis
from optimize.dp.kernels import _interp, _interp_reach, _lin_reach  # the engine's reach-boundary interpolation
from optimize.dp.kernels import level_better, level_choose, level_needs_cost, reach_weights  # the level-set choice rule
from optimize.dp.kernels import _interp_v, _locate  # the engine's locate and cost-to-go interpolation (Baseline-DP)
from optimize.dp.kernels import _locate_all  # the engine's forward loop (forward_hev)
from optimize.dp.engine import ValueFunctions
from calib.model.equations import cabin_heat_rate, coolant_heat_rate, heater_core_limit
from optimize.formulations.transition import _delivered_heat, hev_precompute, hev_transition, hold_heat

_SNAP = 1e-9


@njit(inline="always", cache=True)
def _loc(x, lo, inv, n):
    """Engine's locate with clip=True: (cell, fraction)."""
    r = (x - lo) * inv
    ri = np.floor(r + 0.5)
    if abs(r - ri) < _SNAP:
        r = ri
    if not (r >= 0.0):
        r = 0.0
    if r > n - 1:
        r = float(n - 1)
    i = int(r)
    if i > n - 2:
        i = n - 2
    return i, r - i


@njit(inline="always", cache=True)
def _bilin(S, o, s0, t0, t1):
    return (1.0 - t0) * ((1.0 - t1) * S[o] + t1 * S[o + 1]) + t0 * ((1.0 - t1) * S[o + s0] + t1 * S[o + s0 + 1])


@njit(inline="always", cache=True)
def _active(P, off, s_lo, s_inv, ns, skip):
    """SOC nodes [i_lo, i_hi) computed at a step of grid offset ``off``: the nodes of the cells holding
    [soc_min, soc_max] and two more on each side; all nodes unless ``skip``.

    The others (the drifting grid spans the range at every step, so about 40 % of its nodes lie outside
    it) take the nearest computed node's values (:func:`_extend`). An in-range next charge interpolates
    between computed nodes, with one exception: the engine-off step carries a node to a node of the
    next step only up to ~1e-3 of a cell, so a node at the edge reads its outer neighbour with that
    weight. Computing every node, that neighbour holds the penalty of a charge outside the range; skipped,
    it holds its neighbour's value. The value functions differ there, and attenuated by ~1e-3 a node
    inwards; the tests check the decisions and the cost at the initial state."""
    if not skip:
        return 0, ns
    lo = int(np.floor((P[_C_SLO] - off - s_lo) * s_inv + 1e-9)) - 2
    hi = int(np.ceil((P[_C_SHI] - off - s_lo) * s_inv - 1e-9)) + 3
    return max(lo, 0), min(hi, ns)


@njit(inline="always", cache=True)
def _extend(V, L, i_lo, i_hi, ns, row):
    """Skipped SOC nodes take the values of the nearest computed one (rows of ``row`` values)."""
    for i in range(ns):
        src = i_lo if i < i_lo else (i_hi - 1 if i >= i_hi else i)
        if src != i:
            for e in range(row):
                V[i * row + e] = V[src * row + e]
                L[i * row + e] = L[src * row + e]


@njit(inline="always", cache=True)
def _at2(ib, tb, a, b, ta, tt):
    """Cell indices and fractions of a 2-state query for the general interpolators (the fallbacks): every
    fallback sets all of them here, none reads what an earlier query left."""
    ib[0] = a
    ib[1] = b
    tb[0] = ta
    tb[1] = tt


@njit(inline="always", cache=True)
def _at3(ib, tb, a, b, c, ta, tt, t2):
    """The same for a 3-state query."""
    ib[0] = a
    ib[1] = b
    ib[2] = c
    tb[0] = ta
    tb[1] = tt
    tb[2] = t2


@njit(inline="always", cache=True)
def _excess(x, lo, hi, step):
    """How far x lies outside [lo, hi], in grid steps (0 inside): what the state-constraint penalty charges."""
    if x < lo:
        return (lo - x) / step
    if x > hi:
        return (x - hi) / step
    return 0.0


@njit(inline="always", cache=True)
def _soc_cell(P, tab, ip, i, s_off, s_lo, s_inv, ns):
    """Power control ``ip`` from SOC node ``i``: (allowed, SOC penalty in grid steps, next SOC's cell and
    fraction); not allowed where the control is off at this step or the battery cannot deliver it."""
    if tab[ip, _T_OK] == 0.0:
        return False, 0.0, 0, 0.0
    sn = tab[ip, _T_SOC0 + i]
    if not (sn == sn):
        return False, 0.0, 0, 0.0
    a, ta = _loc(sn - s_off, s_lo, s_inv, ns)
    return True, _excess(sn, P[_C_SLO], P[_C_SHI], P[_C_SH]), a, ta


@njit(cache=True)
def _heater_demand(P, tclg, T_cab, q0, qv):
    """Thermal-DP's heat per coolant node: the demand ``q0`` within the heater core's limit (and >= 0)."""
    for j in range(tclg.size):
        qv[j] = _delivered_heat(P, tclg[j], T_cab, q0, 0.0)  # a grid command: the target is not read


@njit(inline="always", cache=True)
def _next_coolant_cells(TB, TT, PT, n, tlo, thi, th, t_lo, t_inv, nt):
    """The next coolant temperatures in TT[0..n-1] to their penalty (grid steps outside the coolant box, in
    PT), cell (TB) and fraction (back into TT): a loop of its own on an unsigned ``n``, which LLVM
    vectorises."""
    for c in range(n):
        tn = TT[c]
        PT[c] = _excess(tn, tlo, thi, th)
        bb, tt = _loc(tn, t_lo, t_inv, nt)
        TB[c] = bb
        TT[c] = tt


@njit(cache=True)  # a call, not inlined: once per power control and step
def _coolant_columns2(ip, P, tab, tclg, fclg, lossg, qv, TB, TT, PT, C0):
    """Thermal-DP, power control ``ip``: per coolant node the next coolant's cell and fraction, its penalty
    (grid steps outside the coolant box) and the step's fuel (g); independent of SOC.

    Three short loops on unsigned indices, the next coolant passed through ``TT``: in one loop, the runtime
    checks that its eight arrays do not overlap were too many for LLVM to vectorise it (2.5 times slower)."""
    if tab[ip, _T_OK] == 0.0:
        return
    nt = tclg.size
    t_lo, t_inv = tclg[0], (nt - 1) / (tclg[-1] - tclg[0])
    Ts = P[_C_TS]
    wf = tab[ip, _T_WF]
    P_e = tab[ip, _T_PE]
    lhv, gam, ceng = P[_MS0 + _LHV], P[_MS0 + _GAMMA], P[_MS0 + _CENG]
    tlo, thi, th = P[_C_TLO], P[_C_THI], P[_C_TH]
    TBr, TTr, PTr, C0r = TB[ip], TT[ip], PT[ip], C0[ip]
    un = np.uint64(nt)
    for j in range(un):
        C0r[j] = wf * fclg[j] * Ts
    for j in range(un):
        TTr[j] = tclg[j] + Ts * coolant_heat_rate(gam, lhv * (wf * fclg[j]), P_e, lossg[j], qv[j])[0] / ceng
    _next_coolant_cells(TBr, TTr, PTr, un, tlo, thi, th, t_lo, t_inv, nt)


@njit(cache=True)  # a call, not inlined: once per power control and step
def _coolant_columns(ip, P, tab, tclg, fclg, lossg, Q, qh, nh, TB, TT, PT, QFUEL, C0):
    """Thermal-Cabin-DP, power control ``ip``: per coolant node the fuel heat and fuel (g), and per heat
    column (the heater grid's, then the hold heat of each cabin node) the next coolant's cell, fraction
    and penalty.

    Short loops along the columns on unsigned indices, the next coolant passed through ``TT``, as in
    :func:`_coolant_columns2`, so that LLVM vectorises them."""
    if tab[ip, _T_OK] == 0.0:
        return
    nt = tclg.size
    t_lo, t_inv = tclg[0], (nt - 1) / (tclg[-1] - tclg[0])
    Ts = P[_C_TS]
    wf = tab[ip, _T_WF]
    P_e = tab[ip, _T_PE]
    lhv, gam, ceng = P[_MS0 + _LHV], P[_MS0 + _GAMMA], P[_MS0 + _CENG]
    tlo, thi, th = P[_C_TLO], P[_C_THI], P[_C_TH]
    uq, uh = np.uint64(Q.size), np.uint64(nh)
    for j in range(nt):
        W_f = wf * fclg[j]
        Q_fuel = lhv * W_f
        QFUEL[ip, j] = Q_fuel
        C0[ip, j] = W_f * Ts
        TBr, TTr, PTr = TB[ip, j], TT[ip, j], PT[ip, j]
        t0, lj = tclg[j], lossg[j]
        for c in range(uq):
            TTr[c] = t0 + Ts * coolant_heat_rate(gam, Q_fuel, P_e, lj, Q[c])[0] / ceng
        for c in range(uh):
            TTr[uq + c] = t0 + Ts * coolant_heat_rate(gam, Q_fuel, P_e, lj, qh[c])[0] / ceng
        _next_coolant_cells(TBr, TTr, PTr, uq + uh, tlo, thi, th, t_lo, t_inv, nt)


@njit(cache=True)  # a call, not inlined: once per step
def _cabin_columns(P, cabg, tclg, Q, off, off_n, lb, hold, qlim, nunl, qh, hsk, pcu, cu, tu):
    """Thermal-Cabin-DP's cabin side of a step (cabin node m is the temperature cabg[m] + off, the next one is
    located at tc - off_n): per (coolant, cabin) node the heater core's limit and how many grid heats it
    delivers in full; per cabin node the hold heat and, per (coolant, cabin) node, whether it repeats a grid
    control; per (cabin node, heat column) the next cabin's cell, fraction and penalty."""
    nt, nc, nq = tclg.size, cabg.size, Q.size
    nq1 = nq + 1 if hold else nq
    c_lo, c_inv = cabg[0], (nc - 1) / (cabg[-1] - cabg[0])
    Ts = P[_C_TS]
    T_amb = P[_C_TAMB]
    for m in range(nc):
        T_m = cabg[m] + off
        for j in range(nt):
            ql = heater_core_limit(P[_MS0 + _EPS], P[_C_WBL], P[_MS0 + _CP], P[_MS0 + _RECIRC], tclg[j], T_m, T_amb)
            qlim[j, m] = ql
            cnt = 0
            for iq in range(nq):
                if not (Q[iq] > ql):
                    cnt += 1
            nunl[j, m] = cnt
        if hold:
            qh[m] = hold_heat(P, T_m, lb)
            for j in range(nt):
                ql = qlim[j, m]
                q = qh[m]
                sk = q > ql or q < 0.0  # delivers what the first limited (or zero) grid control does
                for iq in range(nq):
                    d = Q[iq]
                    if d > ql:
                        d = ql
                    if d < 0.0:
                        d = 0.0
                    if d == q:
                        sk = True
                hsk[j, m] = sk
        for iq in range(nq1):
            q = Q[iq] if iq < nq else qh[m]
            tc = T_m + Ts * cabin_heat_rate(P[_MS0 + _UACAB], P[_MS0 + _QSUN], T_m, T_amb, q)[0] / P[_MS0 + _CCAB]
            pcu[m, iq] = _excess(tc, lb, P[_C_CHI], P[_C_CH])
            c, tt = _loc(tc - off_n, c_lo, c_inv, nc)
            cu[m, iq] = c
            tu[m, iq] = tt


@njit(cache=True)
def _cabin_work(np_, nt, nc, nq, nq1, nh):
    """Thermal-Cabin-DP's per-step work arrays: heater-core limit and the number of grid heats it delivers in
    full per (coolant, cabin) node; the cabin penalty, cell and fraction per (cabin node, heat column); the
    hold heat per cabin node and whether it repeats a grid control; per (power control, coolant node,
    column: the heater grid's nq, then the hold heat of each cabin node) the next coolant's cell, fraction
    and penalty; the fuel heat and fuel per (power control, coolant node)."""
    return (np.empty((nt, nc)), np.empty((nt, nc), np.int64), np.empty((nc, nq1)), np.empty((nc, nq1), np.int64),
            np.empty((nc, nq1)), np.empty(nc), np.ones((nt, nc), np.bool_), np.empty((np_, nt, nq + nh), np.int64),
            np.empty((np_, nt, nq + nh)), np.empty((np_, nt, nq + nh)), np.empty((np_, nt)), np.empty((np_, nt)))


@njit(inline="always", cache=True)
def _cabin_offsets(P, wk):
    """Step k's comfort bound at k + 1, and the offsets of cabin node m's temperature (cabg[m] + off) and of
    the next one's (located at tc - off_n): the bounds themselves with the cabin relative to its bound."""
    lb = wk[2]
    if P[_C_CREL] != 0.0:
        return lb, wk[3], lb
    return lb, 0.0, 0.0


@njit(inline="always", cache=True)
def _limited_next(P, P_e, q, Q_fuel, T_cl, loss, T_m, lb):
    """Next coolant and cabin temperatures of a heat ``q`` limited by the core, and their penalties (steps)."""
    Ts = P[_C_TS]
    tn = T_cl + Ts * coolant_heat_rate(P[_MS0 + _GAMMA], Q_fuel, P_e, loss, q)[0] / P[_MS0 + _CENG]
    tc = T_m + Ts * cabin_heat_rate(P[_MS0 + _UACAB], P[_MS0 + _QSUN], T_m, P[_C_TAMB], q)[0] / P[_MS0 + _CCAB]
    return tn, tc, _excess(tn, P[_C_TLO], P[_C_THI], P[_C_TH]), _excess(tc, lb, P[_C_CHI], P[_C_CH])


@njit(parallel=True, cache=True)
def backward2(N, P, big, w, socg, tclg, Q, VT, LT, level_tol, reach, skip, k_lo=0):
    """Thermal-DP backward pass (states SOC x T_cl, one heater demand Q[0]); fills VT, LT[k_lo..N-1] from
    those at N (every kernel here runs a part of the pass, :func:`backward_pass_fused`).
    ``reach``: the cost-to-go is interpolated by the engine's ``interp="reach_first"``."""
    ns, nt = socg.size, tclg.size
    np_ = big.shape[1]
    s_lo, s_inv = socg[0], (ns - 1) / (socg[-1] - socg[0])
    PEN = P[_C_PEN]
    fclg = P[int(P[_A_FCLG]): int(P[_A_FCLG]) + nt]
    lossg = P[int(P[_A_LOSSG]): int(P[_A_LOSSG]) + nt]
    strides = np.array([nt, 1], np.int64)
    qv = np.empty(nt)
    TB = np.empty((np_, nt), np.int64)
    TT = np.empty((np_, nt))
    PT = np.empty((np_, nt))
    C0 = np.empty((np_, nt))
    for k in range(N - 1, k_lo - 1, -1):
        tab = big[k]
        Vn = VT[k + 1]
        Ln = LT[k + 1]
        s_off = w[k, 5]  # the SOC grid's offset at k + 1 (the tables hold the charge)
        T_cab = w[k, 1]
        _heater_demand(P, tclg, T_cab, Q[0], qv)
        # next coolant state per (power control, T_cl node): independent of SOC
        for ip in prange(np_):
            _coolant_columns2(ip, P, tab, tclg, fclg, lossg, qv, TB, TT, PT, C0)
        i_lo, i_hi = _active(P, w[k, 4], s_lo, s_inv, ns, skip)
        for ii in prange(i_hi - i_lo):
            i = i_lo + ii
            best = np.full(nt, np.inf)
            Lmin = np.full(nt, np.inf)
            Lsel = np.full(nt, np.inf)
            feas = np.zeros(nt, np.bool_)
            ib = np.empty(2, np.int64)
            tb = np.empty(2)
            for ip in range(np_):
                ok, pen0, a, ta = _soc_cell(P, tab, ip, i, s_off, s_lo, s_inv, ns)
                if not ok:
                    continue
                oa = a * nt
                for j in range(nt):
                    tt = TT[ip, j]
                    o = oa + TB[ip, j]
                    lv = _bilin(Ln, o, nt, ta, tt)
                    if not np.isfinite(lv):
                        _at2(ib, tb, a, TB[ip, j], ta, tt)
                        lv = _slow(Ln, 2, strides, ib, tb)
                        if not (lv < np.inf):
                            continue
                    if lv < Lmin[j]:
                        Lmin[j] = lv
                    if not level_needs_cost(lv, level_tol, feas[j], Lsel[j]):
                        continue
                    if reach:
                        # the engine's _interp_reach for 2 states, written out: a call per evaluation costs
                        # several times the arithmetic
                        vv = ((1.0 - tt) * _lin_reach(np.float64(Vn[o]), np.float64(Vn[o + nt]), np.float64(Ln[o]),
                                                      np.float64(Ln[o + nt]), level_tol, ta)
                              + tt * _lin_reach(np.float64(Vn[o + 1]), np.float64(Vn[o + nt + 1]),
                                                np.float64(Ln[o + 1]), np.float64(Ln[o + nt + 1]), level_tol, ta))
                        if not np.isfinite(vv):
                            _at2(ib, tb, a, TB[ip, j], ta, tt)
                            vv = _interp(Vn, 2, strides, ib, tb)
                    else:
                        vv = _bilin(Vn, o, nt, ta, tt)
                        if not np.isfinite(vv):
                            _at2(ib, tb, a, TB[ip, j], ta, tt)
                            vv = _slow(Vn, 2, strides, ib, tb)
                    v = C0[ip, j] + PEN * (pen0 + PT[ip, j]) + vv
                    if not (v < np.inf):
                        continue
                    level_choose(lv, v, level_tol, j, best, Lsel, feas)
            for j in range(nt):
                VT[k, i * nt + j] = best[j]
                LT[k, i * nt + j] = Lmin[j]
        _extend(VT[k], LT[k], i_lo, i_hi, ns, nt)


@njit(inline="always", cache=True)
def _tri(V, o, s0, s1, t0, t1, t2):
    a = (1.0 - t2) * V[o] + t2 * V[o + 1]
    b = (1.0 - t2) * V[o + s1] + t2 * V[o + s1 + 1]
    c = (1.0 - t2) * V[o + s0] + t2 * V[o + s0 + 1]
    e = (1.0 - t2) * V[o + s0 + s1] + t2 * V[o + s0 + s1 + 1]
    return (1.0 - t0) * ((1.0 - t1) * a + t1 * b) + t0 * ((1.0 - t1) * c + t1 * e)


@njit(cache=True)  # a call, not inlined: numba cannot inline this many arguments into a parfor; the path is rare
def _limited(P, tab, ip, a, ta, sidx, c0, pen0, q, Q_fuel, T_cl, loss, T_m, lb, off_n, t_lo, t_inv, nt, c_lo,
             c_inv, nc, s0, s1, strides, nn, unif, Vn, Ln, ib, tb, cubic, reach, level_tol, best, Lmin, Lsel, feas):
    """Evaluate the first heater-limited control (heat ``q``, the core limit) at state ``sidx`` by full
    trilinear interpolation and apply the engine's choice rule to best/Lmin/Lsel/feas."""
    tn, tc, pt, pc = _limited_next(P, tab[ip, _T_PE], q, Q_fuel, T_cl, loss, T_m, lb)
    pen = pen0
    pen += pt
    pen += pc
    bb, tt = _loc(tn, t_lo, t_inv, nt)
    c, t2 = _loc(tc - off_n, c_lo, c_inv, nc)
    _at3(ib, tb, a, bb, c, ta, tt, t2)
    o = a * s0 + bb * s1 + c
    lv = _tri(Ln, o, s0, s1, ta, tt, t2)
    if not np.isfinite(lv):
        lv = _slow(Ln, 3, strides, ib, tb)
    if not (lv < np.inf):
        return
    if lv < Lmin[sidx]:
        Lmin[sidx] = lv
    if not level_needs_cost(lv, level_tol, feas[sidx], Lsel[sidx]):
        return
    if cubic:
        vv = _interp_cubic_last(Vn, 3, nn, unif, strides, ib, tb)
    elif reach:
        vv = _interp_reach(Vn, Ln, level_tol, 3, strides, ib, tb)
    else:
        vv = _tri(Vn, o, s0, s1, ta, tt, t2)
        if not np.isfinite(vv):
            vv = _slow(Vn, 3, strides, ib, tb)
    v = c0 + P[_C_PEN] * pen + vv
    if not (v < np.inf):
        return
    level_choose(lv, v, level_tol, sidx, best, Lsel, feas)


@njit(parallel=True, cache=True)
def backward3(N, P, big, w, socg, tclg, cabg, Q, VT, LT, level_tol, cubic, hold, reach, skip, k_lo=0):
    """Thermal-Cabin-DP backward pass (states SOC x T_cl x T_cab, controls power x (Q grid[, hold])).

    Controls whose requested heat exceeds the heater-core limit all deliver the same heat (the limit):
    they are identical transitions, so only the first of them (lowest control index, the one the engine's
    tie rule would keep) is evaluated. ``cubic``: the cost-to-go is interpolated along T_cab by the
    engine's cubic Hermite (``interp="cubic_last"``, needs >= 3 cabin nodes); the level stays linear.
    ``hold``: each power control is also paired with "hold the bound" (last in its row of controls), whose
    heat depends on the cabin node only (:func:`optimize.formulations.transition.hold_heat`): its cabin
    slices are one more column per cabin node. Where it delivers what a grid control delivers (clipped to
    the grid's ends or to the core limit) it repeats an earlier control and is skipped, as the engine's tie
    rule would. ``reach``: the engine's ``interp="reach_first"`` (on the slices: cabin first, then SOC,
    then T_cl)."""
    ns, nt, nc, nq = socg.size, tclg.size, cabg.size, Q.size
    nq1 = nq + 1 if hold else nq
    np_ = big.shape[1]
    s_lo, s_inv = socg[0], (ns - 1) / (socg[-1] - socg[0])
    t_lo, t_inv = tclg[0], (nt - 1) / (tclg[-1] - tclg[0])
    c_lo, c_inv = cabg[0], (nc - 1) / (cabg[-1] - cabg[0])
    PEN = P[_C_PEN]
    fclg = P[int(P[_A_FCLG]): int(P[_A_FCLG]) + nt]
    lossg = P[int(P[_A_LOSSG]): int(P[_A_LOSSG]) + nt]
    s1 = nc
    s0 = nt * nc
    strides = np.array([s0, s1, 1], np.int64)
    nn = np.array([ns, nt, nc], np.int64)
    unif = np.ones(3, np.bool_)
    nplane = ns * nt
    SV = np.empty((nc * nq1, nplane))
    SL = np.empty((nc * nq1, nplane))
    nh = nc if hold else 0
    qlim, nunl, pcu, cu, tu, qh, hsk, TB, TT, PT, QFUEL, C0 = _cabin_work(np_, nt, nc, nq, nq1, nh)
    for k in range(N - 1, k_lo - 1, -1):
        tab = big[k]
        Vn = VT[k + 1]
        Ln = LT[k + 1]
        s_off = w[k, 5]  # the SOC grid's offset at k + 1 (the tables hold the charge)
        lb, off, off_n = _cabin_offsets(P, w[k])
        _cabin_columns(P, cabg, tclg, Q, off, off_n, lb, hold, qlim, nunl, qh, hsk, pcu, cu, tu)
        for r in prange(nc * nq1):
            m = r // nq1
            iq = r - m * nq1
            c = cu[m, iq]
            t2 = tu[m, iq]
            for e in range(nplane):
                o = e * nc + c
                if cubic:
                    SV[r, e] = _hermite(Vn, e * nc, c, nc, t2)
                else:
                    SV[r, e] = (1.0 - t2) * Vn[o] + t2 * Vn[o + 1]
                SL[r, e] = (1.0 - t2) * Ln[o] + t2 * Ln[o + 1]
        for ip in prange(np_):
            _coolant_columns(ip, P, tab, tclg, fclg, lossg, Q, qh, nh, TB, TT, PT, QFUEL, C0)
        i_lo, i_hi = _active(P, w[k, 4], s_lo, s_inv, ns, skip)
        for ii in prange(i_hi - i_lo):
            i = i_lo + ii
            best = np.full(nt * nc, np.inf)
            Lmin = np.full(nt * nc, np.inf)
            Lsel = np.full(nt * nc, np.inf)
            feas = np.zeros(nt * nc, np.bool_)
            ib = np.empty(3, np.int64)
            tb = np.empty(3)
            for ip in range(np_):
                ok, pen0, a, ta = _soc_cell(P, tab, ip, i, s_off, s_lo, s_inv, ns)
                if not ok:
                    continue
                oa = a * nt
                for j in range(nt):
                    c0 = C0[ip, j]
                    for m in range(nc):
                        sidx = j * nc + m
                        nu_ = nunl[j, m]
                        # controls whose heat is delivered in full: 2-D slices
                        for iq in range(nu_):
                            rr = m * nq1 + iq
                            tt = TT[ip, j, iq]
                            o = oa + TB[ip, j, iq]
                            lv = _bilin(SL[rr], o, nt, ta, tt)
                            if not np.isfinite(lv):
                                _at3(ib, tb, a, TB[ip, j, iq], cu[m, iq], ta, tt, tu[m, iq])
                                lv = _slow(Ln, 3, strides, ib, tb)
                                if not (lv < np.inf):
                                    continue
                            if lv < Lmin[sidx]:
                                Lmin[sidx] = lv
                            if not level_needs_cost(lv, level_tol, feas[sidx], Lsel[sidx]):
                                continue
                            if reach:
                                S = SV[rr]
                                SLr = SL[rr]
                                vv = ((1.0 - tt) * _lin_reach(S[o], S[o + nt], SLr[o], SLr[o + nt], level_tol, ta)
                                      + tt * _lin_reach(S[o + 1], S[o + nt + 1], SLr[o + 1], SLr[o + nt + 1],
                                                        level_tol, ta))
                            else:
                                vv = _bilin(SV[rr], o, nt, ta, tt)
                            if not np.isfinite(vv):
                                _at3(ib, tb, a, TB[ip, j, iq], cu[m, iq], ta, tt, tu[m, iq])
                                if cubic:
                                    vv = _interp_cubic_last(Vn, 3, nn, unif, strides, ib, tb)
                                elif reach:
                                    vv = _interp(Vn, 3, strides, ib, tb)
                                else:
                                    vv = _slow(Vn, 3, strides, ib, tb)
                            v = c0 + PEN * ((pen0 + PT[ip, j, iq]) + pcu[m, iq]) + vv
                            if not (v < np.inf):
                                continue
                            level_choose(lv, v, level_tol, sidx, best, Lsel, feas)
                        if nu_ < nq:
                            # the first heater-limited control (the others repeat it)
                            _limited(P, tab, ip, a, ta, sidx, c0, pen0, qlim[j, m], QFUEL[ip, j], tclg[j],
                                     lossg[j], cabg[m] + off, lb, off_n, t_lo, t_inv, nt, c_lo, c_inv, nc, s0, s1,
                                     strides, nn, unif, Vn, Ln, ib, tb, cubic, reach, level_tol, best, Lmin, Lsel, feas)
                        if hsk[j, m]:
                            continue
                        # hold the bound: the slices of column nq, the coolant of the hold heat
                        rr = m * nq1 + nq
                        tt = TT[ip, j, nq + m]
                        o = oa + TB[ip, j, nq + m]
                        lv = _bilin(SL[rr], o, nt, ta, tt)
                        if not np.isfinite(lv):
                            _at3(ib, tb, a, TB[ip, j, nq + m], cu[m, nq], ta, tt, tu[m, nq])
                            lv = _slow(Ln, 3, strides, ib, tb)
                            if not (lv < np.inf):
                                continue
                        if lv < Lmin[sidx]:
                            Lmin[sidx] = lv
                        if not level_needs_cost(lv, level_tol, feas[sidx], Lsel[sidx]):
                            continue
                        if reach:
                            S = SV[rr]
                            SLr = SL[rr]
                            vv = ((1.0 - tt) * _lin_reach(S[o], S[o + nt], SLr[o], SLr[o + nt], level_tol, ta)
                                  + tt * _lin_reach(S[o + 1], S[o + nt + 1], SLr[o + 1], SLr[o + nt + 1],
                                                    level_tol, ta))
                        else:
                            vv = _bilin(SV[rr], o, nt, ta, tt)
                        if not np.isfinite(vv):
                            _at3(ib, tb, a, TB[ip, j, nq + m], cu[m, nq], ta, tt, tu[m, nq])
                            if cubic:
                                vv = _interp_cubic_last(Vn, 3, nn, unif, strides, ib, tb)
                            elif reach:
                                vv = _interp(Vn, 3, strides, ib, tb)
                            else:
                                vv = _slow(Vn, 3, strides, ib, tb)
                        v = c0 + PEN * ((pen0 + PT[ip, j, nq + m]) + pcu[m, nq]) + vv
                        if not (v < np.inf):
                            continue
                        level_choose(lv, v, level_tol, sidx, best, Lsel, feas)
            for e in range(nt * nc):
                VT[k, i * nt * nc + e] = best[e]
                LT[k, i * nt * nc + e] = Lmin[e]
        _extend(VT[k], LT[k], i_lo, i_hi, ns, nt * nc)


@njit(cache=True)  # serial: once per step, a copy
def _soc_innermost(Vrow, ns, out):
    """The next cost-to-go ``Vrow`` (SOC outermost, as stored) into ``out`` with SOC innermost (in out's dtype);
    False if a value is not finite (the separable kernels then hand the pass to the exact ones)."""
    ng = Vrow.size // ns
    ok = True
    for i in range(ns):
        for g in range(ng):
            x = np.float64(Vrow[i * ng + g])
            if not np.isfinite(x):
                ok = False
            out[g * ns + i] = x
    return ok


@njit(inline="always", cache=True)
def _extend_rows(X, i_lo, i_hi, ns, row):
    """Skipped SOC nodes take the values of the nearest computed one (``X``: rows of ``row`` values)."""
    for i in range(ns):
        src = i_lo if i < i_lo else (i_hi - 1 if i >= i_hi else i)
        if src != i:
            for e in range(row):
                X[i * row + e] = X[src * row + e]


@njit(cache=True)  # a call, not inlined (too many arguments to inline into a parfor); once per power control
def _soc_col(ip, P, tab, L1n, s_off, s_lo, s_inv, ns, i_lo, i_hi, level_tol, reach, LV, AC, WA, WB, PP):
    """The separable kernels' SOC side of power control ``ip`` (levels on SOC alone) on the SOC rows
    [i_lo, i_hi), at ``ip * ns + row`` (control-major, so this loop runs along contiguous memory): its level
    (+inf where the control is not allowed), the next SOC's cell (-1 where not allowed), the weights along
    SOC (the reach rule's where ``reach``) and the SOC penalty's stage cost.

    :func:`_soc_cell` written out: a disallowed row is marked by selects, not skipped by a branch out of the
    loop, and the indices are unsigned, so that LLVM vectorises the loop (3.6 times faster alone); the weights
    and penalty of a row whose cell is -1 are written too and never read."""
    o = np.uint64(ip * ns)
    u_lo, u_hi = np.uint64(i_lo), np.uint64(i_hi)
    if tab[ip, _T_OK] == 0.0:
        for i in range(u_lo, u_hi):
            LV[o + i] = np.inf
            AC[o + i] = -1
        return
    PEN, lo, hi, sh = P[_C_PEN], P[_C_SLO], P[_C_SHI], P[_C_SH]
    # two loops: the cells first (AC, and the fractions in WB), then the levels they read (in one loop, the
    # levels' loads at cells computed in it took 40 ms against 31 ms over a pass of the default drive)
    for i in range(u_lo, u_hi):
        sn = tab[ip, np.uint64(_T_SOC0) + i]
        a, ta = _loc(sn - s_off, s_lo, s_inv, ns)  # a NaN charge gives cell 0; it is not allowed below
        AC[o + i] = a
        WB[o + i] = ta
        PP[o + i] = PEN * _excess(sn, lo, hi, sh)
    for i in range(u_lo, u_hi):
        a = np.uint64(AC[o + i])
        ta = WB[o + i]
        la = np.float64(L1n[a])
        lb = np.float64(L1n[a + np.uint64(1)])
        # the engine's exact interpolation: a corner of weight 0 is not read
        lv = la if ta == 0.0 else (lb if ta == 1.0 else (1.0 - ta) * la + ta * lb)
        sn = tab[ip, np.uint64(_T_SOC0) + i]
        ok = (sn == sn) and lv < np.inf  # a NaN charge: the battery cannot deliver the control
        LV[o + i] = lv if ok else np.inf
        AC[o + i] = AC[o + i] if ok else -1
        if reach:
            wa, wb = reach_weights(la, lb, level_tol, ta)
        else:
            wa, wb = 1.0 - ta, ta
        WA[o + i] = wa
        WB[o + i] = wb


@njit(inline="always", cache=True)
def _choose_rows(LV, AC, ns, np_, i_lo, i_hi, level_tol, LMIN, L1k):
    """The choice rule (:func:`optimize.dp.kernels.level_better`) on each SOC row [i_lo, i_hi): the row's
    level is the least over its power controls (into ``L1k``); the candidates are the controls reaching the
    terminal set or, if none does, those of least level. The others get cell -1 in ``AC``. Unsigned
    indices (:func:`_min_runs`): both passes vectorise."""
    u_lo, u_hi = np.uint64(i_lo), np.uint64(i_hi)
    for i in range(u_lo, u_hi):
        LMIN[i] = np.inf
    for ip in range(np_):
        o = np.uint64(ip * ns)
        for i in range(u_lo, u_hi):
            lv = LV[o + i]
            lm = LMIN[i]
            LMIN[i] = lv if lv < lm else lm
    for i in range(u_lo, u_hi):
        L1k[i] = LMIN[i]
        if LMIN[i] <= level_tol:  # some control reaches the set: its bound is the tolerance
            LMIN[i] = level_tol
    for ip in range(np_):
        o = np.uint64(ip * ns)
        for i in range(u_lo, u_hi):
            a = AC[o + i]
            AC[o + i] = a if LV[o + i] <= LMIN[i] else -1  # an infinite level keeps its cell -1 (it has no other)


@njit(inline="always", cache=True)
def _runs(AC, ip, ns, i_lo, i_hi, r0, r1, rd):
    """Runs [r0, r1) of the SOC rows where control ``ip`` is a candidate (cell >= 0 in the control-major
    ``AC``) and its SOC cell is the row plus rd (reads of a row-indexed array contiguous over a run);
    returns (runs, least cell, greatest cell)."""
    nrun = 0
    amin = ns
    amax = -1
    o = ip * ns
    i = i_lo
    while i < i_hi:
        a = AC[o + i]
        if a < 0:
            i += 1
            continue
        d = a - i
        i1 = i + 1
        while i1 < i_hi and AC[o + i1] == i1 + d:
            i1 += 1
        amin = min(amin, a)
        amax = max(amax, AC[o + i1 - 1])
        r0[nrun] = i
        r1[nrun] = i1
        rd[nrun] = d
        nrun += 1
        i = i1
    return nrun, amin, amax


@njit(cache=True)  # serial: once per step
def _all_runs(AC, np_, ns, i_lo, i_hi, R0, R1, RD, RN):
    """:func:`_runs` of every power control, once per step (the chunks of a step all read them): control
    ``ip``'s runs in ``R0[ip]``, ``R1[ip]``, ``RD[ip]``; ``RN[ip]`` holds (runs, least cell, greatest cell)."""
    for ip in range(np_):
        nrun, amin, amax = _runs(AC, ip, ns, i_lo, i_hi, R0[ip], R1[ip], RD[ip])
        RN[ip, 0] = nrun
        RN[ip, 1] = amin
        RN[ip, 2] = amax


@njit(inline="always", cache=True)
def _lerp_into(W, ow, X, o0, o1, s0, s1, t):
    """W[ow + s] = (1 - t) X[o0 + s] + t X[o1 + s] for s0 <= s < s1: the separable kernels' interpolation of
    the cost-to-go along coolant or cabin, one SOC node per s. Unsigned indices, as in :func:`_min_runs`:
    with signed ones this loop ran 1.5 times slower (Thermal-Cabin-DP's backward pass, same values)."""
    uw = np.uint64(ow)
    u0 = np.uint64(o0)
    u1 = np.uint64(o1)
    for s in range(np.uint64(s0), np.uint64(s1)):
        W[uw + s] = (1.0 - t) * X[u0 + s] + t * X[u1 + s]


@njit(inline="always", cache=True)
def _min_runs(best, ob, W, ow, add, ip, ns, PP, WA, WB, r0, r1, rd, nrun):
    """The separable kernels' inner loop: for the SOC rows of control ``ip``'s runs, the pair's cost (``add``
    plus the row's SOC penalty plus the weighted reads of W, the cost-to-go interpolated along the other
    states, at offset ``ow``) into the running minimum ``best[ob + row]``. Unsigned indices: a signed one
    makes numba add a negative-index check that keeps LLVM from vectorising the loop."""
    for ru in range(nrun):
        d = rd[ru]
        for i in range(r0[ru], r1[ru]):
            u = np.uint64(ip * ns + i)
            v = add + PP[u] + (WA[u] * W[np.uint64(ow + i + d)] + WB[u] * W[np.uint64(ow + i + d + 1)])
            ub = np.uint64(ob + i)
            bo = best[ub]
            best[ub] = v if v < bo else bo


@njit(inline="always", cache=True)
def _min_runs_pair(best, ob0, ob1, W, ow0, ow1, a0, a1, ip, ns, PP, WA, WB, r0, r1, rd, nrun):
    """:func:`_min_runs` for two columns of W at once (offsets ``ow0``, ``ow1``, stage costs ``a0``, ``a1``) into
    the running minima at ``ob0`` and ``ob1``: two coolant states of Thermal-DP, or two heater columns of the
    same state (``ob0 == ob1``: taken in that order, so the result is that of two calls). A row's weights and
    SOC penalty are read once for both (the loop is bound by its reads)."""
    for ru in range(nrun):
        d = rd[ru]
        for i in range(r0[ru], r1[ru]):
            u = np.uint64(ip * ns + i)
            x = np.uint64(i + d)
            wa = WA[u]
            wb = WB[u]
            pp = PP[u]
            v0 = a0 + pp + (wa * W[np.uint64(ow0) + x] + wb * W[np.uint64(ow0) + x + np.uint64(1)])
            v1 = a1 + pp + (wa * W[np.uint64(ow1) + x] + wb * W[np.uint64(ow1) + x + np.uint64(1)])
            u0 = np.uint64(ob0 + i)
            u1 = np.uint64(ob1 + i)
            b0 = best[u0]
            best[u0] = v0 if v0 < b0 else b0
            b1 = best[u1]
            best[u1] = v1 if v1 < b1 else b1


@njit(inline="always", cache=True)
def _column(K, CB, CC, col, cb, cc, tt, t2, add):
    """Heat column ``col`` of Thermal-Cabin-DP's separable kernel: its next coolant's and cabin's cells, the
    bilinear weights of the cell's corners (00, 01: next cabin node, 10: next coolant node, 11), its stage
    cost (fuel and penalties) and the two fractions."""
    CB[col] = cb
    CC[col] = cc
    K[col, 0] = (1.0 - tt) * (1.0 - t2)
    K[col, 1] = (1.0 - tt) * t2
    K[col, 2] = tt * (1.0 - t2)
    K[col, 3] = tt * t2
    K[col, 4] = add
    K[col, 5] = tt
    K[col, 6] = t2


@njit(inline="always", cache=True)
def _soc_row(U, stamp, r, V, ip, ns, WA, WB, r0, r1, rd, nrun):
    """Thermal-Cabin-DP's separable kernel: row ``r`` (a (coolant, cabin) node) of the cost-to-go interpolated
    along SOC for control ``ip``'s SOC rows (its runs), U[r * ns + row], from V ([coolant, cabin, SOC]); once
    per control: ``stamp[r]`` holds the control it was computed for."""
    if stamp[r] == ip:
        return
    stamp[r] = ip
    o = np.uint64(r * ns)
    for ru in range(nrun):
        d = rd[ru]
        for i in range(r0[ru], r1[ru]):
            u = np.uint64(ip * ns + i)
            x = o + np.uint64(i + d)
            U[o + np.uint64(i)] = WA[u] * V[x] + WB[u] * V[x + np.uint64(1)]
        if ru + 1 < nrun:  # rows between runs are not candidates: +inf, so the passes over [r0[0], r1[-1]) skip them
            for i in range(r1[ru], r0[ru + 1]):
                U[o + np.uint64(i)] = np.inf


@njit(inline="always", cache=True)
def _corners_at(U, u00, u01, u10, u11, ui):
    """SOC row ``ui`` of a (coolant, cabin) cell's four corner rows of U."""
    return U[u00 + ui], U[u01 + ui], U[u10 + ui], U[u11 + ui]


@njit(inline="always", cache=True)
def _lower(best, ub, v):
    """best[ub] = min(best[ub], v), as a select (a NaN or +inf v changes nothing)."""
    bo = best[ub]
    best[ub] = v if v < bo else bo


@njit(inline="always", cache=True)
def _interior_possible(vs, ve, g):
    """Whether a quadratic of curvature g / (2 L^2) over a stretch of length L, with ends vs and ve, may have
    its minimum inside (:func:`_min_stretches`: g carries a margin of two times, 1e-9 of the value more)."""
    return _interior_flag(vs, ve, g) != 0


@njit(inline="always", cache=True)
def _interior_flag(vs, ve, g):
    """:func:`_interior_possible` as 1 or 0, without a branch (the passes over the rows vectorise)."""
    return np.int64((g > 0.0) & (abs(ve - vs) < g + 1e-9 * abs(vs)))


@njit(inline="always", cache=True)
def _weights(K, q):
    """Heat column ``q``'s four corner weights and stage cost, read once for a pass over the rows."""
    return K[q, 0], K[q, 1], K[q, 2], K[q, 3], K[q, 4]


@njit(inline="always", cache=True)
def _cost(w, x0, x1, x2, x3):
    """A column's cost (weights and stage cost ``w``, :func:`_weights`) at a SOC row whose cell corners hold
    x0..x3: the stage cost plus the bilinear combination."""
    return w[4] + (w[0] * x0 + w[1] * x1 + w[2] * x2 + w[3] * x3)


@njit(inline="always", cache=True)
def _costs4(wa, wb, wc, wd, x0, x1, x2, x3):
    """:func:`_cost` of four columns at one SOC row, and the least of them."""
    va = _cost(wa, x0, x1, x2, x3)
    vb = _cost(wb, x0, x1, x2, x3)
    vc = _cost(wc, x0, x1, x2, x3)
    vd = _cost(wd, x0, x1, x2, x3)
    v = va if va < vb else vb
    v = v if v < vc else vc
    return va, vb, vc, vd, (v if v < vd else vd)


@njit(inline="always", cache=True)
def _min_corners4(best, ob, U, o00, o01, o10, o11, K, q, ip, ns, PP, i0, i1):
    """Four heat columns of one (coolant, cabin) cell (rows q..q+3 of K: corner weights, stage cost) into the
    running minimum ``best[ob + row]`` for the SOC rows i0..i1-1 (rows that are not candidates hold +inf in U,
    :func:`_soc_row`): the bilinear combination of the cell's corners (rows of U at offsets
    ``o00``, ``o01`` next cabin node, ``o10`` next coolant node, ``o11``), plus the stage cost and the row's SOC
    penalty. The corners are read once for the four."""
    wa = _weights(K, q)
    wb = _weights(K, q + 1)
    wc = _weights(K, q + 2)
    wd = _weights(K, q + 3)
    u00, u01, u10, u11 = np.uint64(o00), np.uint64(o01), np.uint64(o10), np.uint64(o11)
    for i in range(i0, i1):
        x0, x1, x2, x3 = _corners_at(U, u00, u01, u10, u11, np.uint64(i))
        v = _costs4(wa, wb, wc, wd, x0, x1, x2, x3)[4]
        _lower(best, np.uint64(ob + i), v + PP[np.uint64(ip * ns + i)])


@njit(inline="always", cache=True)
def _min_corners1(best, ob, U, o00, o01, o10, o11, K, q, ip, ns, PP, i0, i1):
    """:func:`_min_corners4` for one column."""
    wa = _weights(K, q)
    u00, u01, u10, u11 = np.uint64(o00), np.uint64(o01), np.uint64(o10), np.uint64(o11)
    for i in range(i0, i1):
        x0, x1, x2, x3 = _corners_at(U, u00, u01, u10, u11, np.uint64(i))
        _lower(best, np.uint64(ob + i), _cost(wa, x0, x1, x2, x3) + PP[np.uint64(ip * ns + i)])


@njit(inline="always", cache=True)
def _bends(K, q):
    """Whether heat column ``q``'s stage cost, next coolant's fraction or next cabin's fraction departs from the
    line through its neighbours' (second difference): where a penalty starts or stops, or a next temperature
    leaves the grid (its fraction is clipped). Rounding and the locate's snap to a node (1e-9 of a cell) are
    not bends."""
    return (abs(K[q + 1, 4] - 2.0 * K[q, 4] + K[q - 1, 4]) > 1e-12 * abs(K[q, 4])
            or abs(K[q + 1, 5] - 2.0 * K[q, 5] + K[q - 1, 5]) > 1e-8
            or abs(K[q + 1, 6] - 2.0 * K[q, 6] + K[q - 1, 6]) > 1e-8)


@njit(inline="always", cache=True)
def _gain(K, qs, qe):
    """2 tau sigma L^2 of the stretch qs..qe (its fractions' changes): times the corners' mixed difference, the
    margin-doubled curvature term of :func:`_interior_possible`."""
    return 2.0 * (K[qe, 5] - K[qs, 5]) * (K[qe, 6] - K[qs, 6])


@njit(inline="always", cache=True)
def _inner_columns(best, ob, U, u00, u01, u10, u11, K, qs, qe, ip, ns, PP, i0, i1):
    """The inner columns of the stretch qs..qe for the rows where its ends and curvature allow an interior
    minimum (:func:`_interior_possible`)."""
    gl = _gain(K, qs, qe)
    ws = _weights(K, qs)
    we = _weights(K, qe)
    for i in range(i0, i1):
        x0, x1, x2, x3 = _corners_at(U, u00, u01, u10, u11, np.uint64(i))
        if not _interior_possible(_cost(ws, x0, x1, x2, x3), _cost(we, x0, x1, x2, x3), gl * (x3 - x2 - x1 + x0)):
            continue
        pp = PP[ip * ns + i]
        for q in range(qs + 1, qe):
            _lower(best, np.uint64(ob + i), _cost(_weights(K, q), x0, x1, x2, x3) + pp)


@njit(inline="always", cache=True)
def _ends1(best, ob, U, u00, u01, u10, u11, K, qs, qe, ip, ns, PP, i0, i1):
    """One stretch's ends (columns qs, qe) into the running minimum for the SOC rows i0..i1-1; returns how many
    rows may have an interior minimum."""
    gl = _gain(K, qs, qe)
    ws = _weights(K, qs)
    we = _weights(K, qe)
    flagged = 0
    for i in range(i0, i1):
        x0, x1, x2, x3 = _corners_at(U, u00, u01, u10, u11, np.uint64(i))
        vs = _cost(ws, x0, x1, x2, x3)
        ve = _cost(we, x0, x1, x2, x3)
        v = vs if vs < ve else ve
        _lower(best, np.uint64(ob + i), v + PP[np.uint64(ip * ns + i)])
        flagged += _interior_flag(vs, ve, gl * (x3 - x2 - x1 + x0))
    return flagged


@njit(inline="always", cache=True)
def _ends4(best, ob, U, u00, u01, u10, u11, K, qa, qb, qc, qd, qf, ip, ns, PP, i0, i1):
    """:func:`_ends1` for four consecutive stretches (columns qa, qb, qc, qd, qf; a stretch of length 0 repeats
    a column and flags nothing) in one pass: each column is evaluated once."""
    ga = _gain(K, qa, qb)
    gb = _gain(K, qb, qc)
    gc = _gain(K, qc, qd)
    gd = _gain(K, qd, qf)
    wa = _weights(K, qa)
    wb = _weights(K, qb)
    wc = _weights(K, qc)
    wd = _weights(K, qd)
    wf = _weights(K, qf)
    flagged = 0
    for i in range(i0, i1):
        x0, x1, x2, x3 = _corners_at(U, u00, u01, u10, u11, np.uint64(i))
        va, vb, vc, vd, v = _costs4(wa, wb, wc, wd, x0, x1, x2, x3)
        vf = _cost(wf, x0, x1, x2, x3)
        v = v if v < vf else vf
        _lower(best, np.uint64(ob + i), v + PP[np.uint64(ip * ns + i)])
        xm = x3 - x2 - x1 + x0
        flagged += (_interior_flag(va, vb, ga * xm) | _interior_flag(vb, vc, gb * xm) | _interior_flag(vc, vd, gc * xm)
                    | _interior_flag(vd, vf, gd * xm))
    return flagged


@njit(inline="always", cache=True)
def _min_stretches(best, ob, U, o00, o01, o10, o11, K, CAND, a, e, ip, ns, PP, i0, i1):
    """The least cost over heat columns a..e-1 of one cell (the grid's heats, in order), into the running
    minimum ``best[ob + row]``, the same as evaluating every column (:func:`_min_corners1`).

    Between two columns where the stage cost or a fraction bends (:func:`_bends`; a stretch of length L),
    the fractions and the stage cost are affine in the column index, so the interpolated cost-to-go is a
    quadratic in it, of curvature tau * sigma * (x11 - x10 - x01 + x00) (tau, sigma: the fractions' steps
    along the stretch). A quadratic has an interior minimum only if its curvature g is positive and its ends
    differ by less than g L^2. So the ends of the stretches are evaluated for all rows (vectorised; up to
    four stretches in one pass), and the inner columns only for the rows where that test, with a margin of
    two times and 1e-9 of the value, does not rule an interior minimum out."""
    n = 0
    CAND[n] = a
    n += 1
    for q in range(a + 1, e - 1):
        if _bends(K, q):
            CAND[n] = q
            n += 1
    CAND[n] = e - 1
    n += 1
    u00, u01, u10, u11 = np.uint64(o00), np.uint64(o01), np.uint64(o10), np.uint64(o11)
    c = 0
    while c < n - 1:
        m = min(n - 1 - c, 4)  # stretches in this pass
        if m == 1:
            flagged = _ends1(best, ob, U, u00, u01, u10, u11, K, CAND[c], CAND[c + 1], ip, ns, PP, i0, i1)
        else:
            q = CAND[c + m]  # columns past the pass's last repeat it
            flagged = _ends4(best, ob, U, u00, u01, u10, u11, K, CAND[c], CAND[c + 1], CAND[c + 2],
                             CAND[c + 3] if m >= 3 else q, q, ip, ns, PP, i0, i1)
        if flagged:
            for cc in range(c, c + m):
                if CAND[cc + 1] - CAND[cc] >= 2:
                    _inner_columns(best, ob, U, u00, u01, u10, u11, K, CAND[cc], CAND[cc + 1], ip, ns, PP, i0, i1)
        c += m


@njit(parallel=True, cache=True)
def backward2_sep(N, P, big, w, socg, tclg, Q, VT, L1T, level_tol, reach, skip, nchunk, k_lo=0):
    """Thermal-DP backward pass when the level depends on SOC alone (a terminal set on SOC only, the default):
    fills VT[k_lo..N-1] and the levels per SOC node L1T[k_lo..N-1]; returns -1, or the step k whose next
    cost-to-go holds a non-finite value (then nothing below k is filled and the caller uses :func:`backward2`).

    The next SOC depends on (SOC node, power control), the next coolant on (coolant node, power control),
    and the level on SOC alone, so:

    * a control's level, feasibility and cell weights along SOC are computed once per (SOC node, power
      control), not per coolant node; the choice rule (:func:`optimize.dp.kernels.level_better`) then picks,
      for a whole SOC row, the candidates: the controls reaching the terminal set, or if none does, those
      of least level. What is left per state is the least cost over the candidates;
    * per power control, the cost-to-go is interpolated along the coolant once for every SOC node it reads,
      W[s, j] (the coolant cell and weight depend on the control and the coolant node only), so a
      state-control pair costs two contiguous reads of W and the weights along SOC
      (:func:`optimize.dp.kernels.reach_weights`, the reach rule's weights, since the levels of both
      coolant corners are equal).

    The values are those of :func:`backward2` up to rounding (the interpolation runs coolant first); the
    levels are the same. Where the least level is tied the rule's cost order is applied exactly, while
    :func:`backward2` compares levels that carry rounding from the coolant weights: a state from which the
    terminal set cannot be reached may then take another least-level control (tests/test_formulations.py).

    Indices into the flat work arrays are unsigned (:func:`_min_runs`).

    A step has one parallel region (a region costs a wake-up of the threads): while the threads take the
    least costs of step k, they also prepare step k - 1 (its coolant columns and SOC side, which do not
    depend on the cost-to-go; the SOC side reads the levels of step k, chosen before the region) into the
    other of two buffers."""
    ns, nt = socg.size, tclg.size
    np_ = big.shape[1]
    s_lo, s_inv = socg[0], (ns - 1) / (socg[-1] - socg[0])
    PEN = P[_C_PEN]
    fclg = P[int(P[_A_FCLG]): int(P[_A_FCLG]) + nt]
    lossg = P[int(P[_A_LOSSG]): int(P[_A_LOSSG]) + nt]
    qv = np.empty(nt)
    # two buffers (step k's, step k - 1's) of the coolant columns per (power control, coolant node) ...
    TB = np.empty((2, np_, nt), np.int64)
    TT = np.empty((2, np_, nt))
    PT = np.empty((2, np_, nt))
    C0 = np.empty((2, np_, nt))
    # ... and of the SOC side per (power control, SOC node), control-major: level, SOC cell (-1: not a
    # candidate), weights along SOC, stage cost of the SOC penalty
    LV = np.empty((2, np_ * ns))
    AC = np.empty((2, np_ * ns), np.int64)
    WA = np.empty((2, np_ * ns))
    WB = np.empty((2, np_ * ns))
    PP = np.empty((2, np_ * ns))
    LMIN = np.empty(ns)
    # the cost-to-go, [coolant, SOC]: SOC innermost for contiguous reads; float32 as stored (the same values,
    # half the cache: 6 % faster, alternated in one process)
    V32 = np.empty(ns * nt, np.float32)
    R0 = np.empty((np_, ns), np.int64)  # per control, runs of rows whose SOC cell is the row plus a constant
    R1 = np.empty((np_, ns), np.int64)
    RD = np.empty((np_, ns), np.int64)
    RN = np.empty((np_, 3), np.int64)
    csz = (nt + nchunk - 1) // nchunk
    BEST = np.empty((nchunk, csz * ns))  # per task: [coolant node, SOC row]
    WK = np.empty((nchunk, csz * ns))  # per task: [coolant node, SOC node], the cost-to-go interpolated along the coolant
    # step N - 1's preparation
    _heater_demand(P, tclg, w[N - 1, 1], Q[0], qv)
    p_lo, p_hi = _active(P, w[N - 1, 4], s_lo, s_inv, ns, skip)
    cur = (N - 1) % 2
    for ip in prange(np_):
        _coolant_columns2(ip, P, big[N - 1], tclg, fclg, lossg, qv, TB[cur], TT[cur], PT[cur], C0[cur])
        _soc_col(ip, P, big[N - 1], L1T[N], w[N - 1, 5], s_lo, s_inv, ns, p_lo, p_hi, level_tol, reach, LV[cur],
                 AC[cur], WA[cur], WB[cur], PP[cur])
    for k in range(N - 1, k_lo - 1, -1):
        cur = k % 2
        nxt = 1 - cur
        if not _soc_innermost(VT[k + 1], ns, V32):
            return k
        i_lo, i_hi = p_lo, p_hi
        _choose_rows(LV[cur], AC[cur], ns, np_, i_lo, i_hi, level_tol, LMIN, L1T[k])
        _extend_rows(L1T[k], i_lo, i_hi, ns, 1)  # step k - 1's SOC side reads these levels
        _all_runs(AC[cur], np_, ns, i_lo, i_hi, R0, R1, RD, RN)
        nr = i_hi - i_lo
        if k > k_lo:  # the next part prepares its first step itself
            _heater_demand(P, tclg, w[k - 1, 1], Q[0], qv)
            p_lo, p_hi = _active(P, w[k - 1, 4], s_lo, s_inv, ns, skip)
        TBc, TTc, PTc, C0c = TB[cur], TT[cur], PT[cur], C0[cur]
        WAc, WBc, PPc = WA[cur], WB[cur], PP[cur]
        # least cost over the candidates; tasks own disjoint blocks of coolant nodes
        for c in prange(nchunk):
            j0 = c * csz
            m = min(nt, j0 + csz) - j0
            if m > 0:
                best = BEST[c]
                best[:m * nr] = np.inf
                W = WK[c]
                for ip in range(np_):
                    nrun, amin, amax = RN[ip, 0], RN[ip, 1], RN[ip, 2]
                    if nrun == 0:
                        continue
                    r0, r1, rd = R0[ip], R1[ip], RD[ip]
                    for jj in range(m):
                        o = TBc[ip, j0 + jj] * ns
                        _lerp_into(W, jj * ns, V32, o, o + ns, amin, amax + 2, TTc[ip, j0 + jj])
                    m2 = m - m % 2
                    for jj in range(0, m2, 2):
                        _min_runs_pair(best, jj * nr - i_lo, (jj + 1) * nr - i_lo, W, jj * ns, (jj + 1) * ns,
                                       C0c[ip, j0 + jj] + PEN * PTc[ip, j0 + jj],
                                       C0c[ip, j0 + jj + 1] + PEN * PTc[ip, j0 + jj + 1], ip, ns, PPc, WAc, WBc, r0,
                                       r1, rd, nrun)
                    for jj in range(m2, m):
                        _min_runs(best, jj * nr - i_lo, W, jj * ns, C0c[ip, j0 + jj] + PEN * PTc[ip, j0 + jj], ip, ns,
                                  PPc, WAc, WBc, r0, r1, rd, nrun)
                for ii in range(nr):
                    for jj in range(m):
                        VT[k, (i_lo + ii) * nt + j0 + jj] = best[jj * nr + ii]
            if k > k_lo:  # step k - 1's preparation: the power controls dealt to the tasks in turn (at most steps
                # only the first half of them is allowed, so runs of consecutive ones left one thread most of it)
                for ip in range(c, np_, nchunk):
                    _coolant_columns2(ip, P, big[k - 1], tclg, fclg, lossg, qv, TB[nxt], TT[nxt], PT[nxt], C0[nxt])
                    _soc_col(ip, P, big[k - 1], L1T[k], w[k - 1, 5], s_lo, s_inv, ns, p_lo, p_hi, level_tol, reach,
                             LV[nxt], AC[nxt], WA[nxt], WB[nxt], PP[nxt])
        _extend_rows(VT[k], i_lo, i_hi, ns, nt)
    return -1


@njit(inline="always", cache=True)
def _dealt(cp, n, nth):
    """The block that iteration ``cp`` of a prange over ``n`` blocks takes on ``nth`` threads: numba splits a
    prange into one run of consecutive iterations per thread, and the blocks are dealt out in turn instead
    (thread t takes blocks t, t + T, t + 2T, ...). Thermal-Cabin-DP's blocks of states along the coolant
    grid differ in work (on the default drive the coldest eighth costs a third of the others: the heater
    core delivers fewer heats), so consecutive blocks would leave one thread idle. The identity where n is
    not a multiple of the threads (the thread count is an argument: a kernel that asks numba for it cannot
    be cached)."""
    per = n // nth
    if per * nth != n:
        return np.int64(cp)
    return np.int64((cp % per) * nth + cp // per)


# fused multiply-adds: 1.11 times on the paper grid, the stored values one float32 unit apart at most
@njit(parallel=True, cache=True, fastmath={"contract"})
def backward3_sep(N, P, big, w, socg, tclg, cabg, Q, VT, L1T, level_tol, hold, reach, skip, nchunk, nth, k_lo=0):
    """Thermal-Cabin-DP backward pass when the level depends on SOC alone, the counterpart of
    :func:`backward2_sep` for :func:`backward3` (multilinear or reach interpolation; not the cubic):
    returns -1, or the step whose next cost-to-go holds a non-finite value.

    The order of the interpolation is turned round: SOC first. Per power control, the cost-to-go is
    interpolated along SOC with the control's weights for each (coolant, cabin) node a heat column reads, once
    (:func:`_soc_row`). A heat column (the heats the core can deliver, the first limited one, hold the bound)
    then costs, per SOC row, the bilinear combination of its (coolant, cabin) cell's four corners. The heats
    change the next coolant and cabin temperatures by hundredths of a cell, so most columns of a state share
    one cell: its corners are read once for four columns (:func:`_min_corners4`). Over the grid's heats of a
    cell the least cost is taken from the ends of the stretches where the stage cost and the fractions are
    affine, and from the inner columns only where the curvature allows an interior minimum
    (:func:`_min_stretches`: the same minimum as every column's). The value is the same trilinear
    interpolation, rounded in another order (the stored float32 values are equal to those of the cabin-first
    order, or one unit of the last place apart). The cost-to-go is kept SOC-innermost ([coolant, cabin, SOC])
    so the reads along SOC are contiguous."""
    ns, nt, nc, nq = socg.size, tclg.size, cabg.size, Q.size
    nq1 = nq + 1 if hold else nq
    np_ = big.shape[1]
    s_lo, s_inv = socg[0], (ns - 1) / (socg[-1] - socg[0])
    t_lo, t_inv = tclg[0], (nt - 1) / (tclg[-1] - tclg[0])
    c_lo, c_inv = cabg[0], (nc - 1) / (cabg[-1] - cabg[0])
    PEN = P[_C_PEN]
    fclg = P[int(P[_A_FCLG]): int(P[_A_FCLG]) + nt]
    lossg = P[int(P[_A_LOSSG]): int(P[_A_LOSSG]) + nt]
    ng = nt * nc
    nh = nc if hold else 0
    qlim, nunl, pcu, cu, tu, qh, hsk, TB, TT, PT, QFUEL, C0 = _cabin_work(np_, nt, nc, nq, nq1, nh)
    VS = np.empty(ng * ns)  # the cost-to-go, [coolant, cabin, SOC]
    # per (power control, SOC node), control-major: level, SOC cell (-1: not a candidate)
    LV = np.empty(np_ * ns)
    AC = np.empty(np_ * ns, np.int64)
    LMIN = np.empty(ns)
    WA = np.empty(np_ * ns)
    WB = np.empty(np_ * ns)
    PP = np.empty(np_ * ns)
    R0 = np.empty((np_, ns), np.int64)  # per control, runs of rows whose SOC cell is the row plus a constant
    R1 = np.empty((np_, ns), np.int64)
    RD = np.empty((np_, ns), np.int64)
    RN = np.empty((np_, 3), np.int64)
    gsz = (ng + nchunk - 1) // nchunk
    for k in range(N - 1, k_lo - 1, -1):
        tab = big[k]
        L1n = L1T[k + 1]
        if not _soc_innermost(VT[k + 1], ns, VS):
            return k
        s_off = w[k, 5]
        lb, off, off_n = _cabin_offsets(P, w[k])
        _cabin_columns(P, cabg, tclg, Q, off, off_n, lb, hold, qlim, nunl, qh, hsk, pcu, cu, tu)
        i_lo, i_hi = _active(P, w[k, 4], s_lo, s_inv, ns, skip)
        for ip in prange(np_):  # one parallel region for both sides of a control
            _coolant_columns(ip, P, tab, tclg, fclg, lossg, Q, qh, nh, TB, TT, PT, QFUEL, C0)
            _soc_col(ip, P, tab, L1n, s_off, s_lo, s_inv, ns, i_lo, i_hi, level_tol, reach, LV, AC, WA, WB, PP)
        _choose_rows(LV, AC, ns, np_, i_lo, i_hi, level_tol, LMIN, L1T[k])
        _all_runs(AC, np_, ns, i_lo, i_hi, R0, R1, RD, RN)
        nr = i_hi - i_lo
        for cp in prange(nchunk):
            ch = _dealt(cp, nchunk, nth)
            g0 = ch * gsz
            g1 = min(ng, g0 + gsz)
            if g1 <= g0:
                continue
            best = np.full((g1 - g0) * nr, np.inf)  # [state (coolant, cabin), SOC row]
            U = np.empty(ng * ns)  # the cost-to-go interpolated along SOC for one control, [coolant, cabin, SOC row]
            stamp = np.full(ng, -1, np.int64)  # the control a row of U was computed for
            CB = np.empty(nq + 2, np.int64)  # per heat column: its next coolant's and cabin's cells, ...
            CC = np.empty(nq + 2, np.int64)
            K = np.empty((nq + 2, 7))  # ... the weights of the cell's four corners, the stage cost, the fractions
            CAND = np.empty(nq + 2, np.int64)  # a group's heat columns where the minimum can lie
            for ip in range(np_):
                nrun = RN[ip, 0]
                if nrun == 0:
                    continue
                r0, r1, rd = R0[ip], R1[ip], RD[ip]
                i0, i1 = r0[0], r1[nrun - 1]  # the passes run over the rows from the first run to the last
                for g in range(g0, g1):
                    j = g // nc
                    m = g - j * nc
                    ob = (g - g0) * nr - i_lo
                    nu_ = nunl[j, m]
                    c0 = C0[ip, j]
                    for iq in range(nu_):  # the heats the core delivers in full
                        _column(K, CB, CC, iq, TB[ip, j, iq], cu[m, iq], TT[ip, j, iq], tu[m, iq],
                                c0 + PEN * (PT[ip, j, iq] + pcu[m, iq]))
                    ncol = nu_
                    if nu_ < nq:
                        # the first heater-limited control: the core's limit heat, both next temperatures
                        # depend on the state
                        tn, tc, pt, pc = _limited_next(P, tab[ip, _T_PE], qlim[j, m], QFUEL[ip, j], tclg[j],
                                                       lossg[j], cabg[m] + off, lb)
                        bb, tt = _loc(tn, t_lo, t_inv, nt)
                        c, t2 = _loc(tc - off_n, c_lo, c_inv, nc)
                        _column(K, CB, CC, ncol, bb, c, tt, t2, c0 + PEN * (pt + pc))
                        ncol += 1
                    if not hsk[j, m]:  # hold the bound
                        _column(K, CB, CC, ncol, TB[ip, j, nq + m], cu[m, nq], TT[ip, j, nq + m], tu[m, nq],
                                c0 + PEN * (PT[ip, j, nq + m] + pcu[m, nq]))
                        ncol += 1
                    # groups: consecutive columns whose next (coolant, cabin) lies in the same cell (the grid's
                    # heats are in order, so their cells change at most once along each axis)
                    a = 0
                    while a < ncol:
                        e = a + 1
                        while e < ncol and CB[e] == CB[a] and CC[e] == CC[a]:
                            e += 1
                        r00 = CB[a] * nc + CC[a]
                        for r in (r00, r00 + 1, r00 + nc, r00 + nc + 1):
                            _soc_row(U, stamp, r, VS, ip, ns, WA, WB, r0, r1, rd, nrun)
                        o00 = r00 * ns
                        o10 = o00 + nc * ns
                        eg = min(e, nu_)  # the grid's heats of the group; then the limited one and the hold
                        if eg - a >= 3:
                            _min_stretches(best, ob, U, o00, o00 + ns, o10, o10 + ns, K, CAND, a, eg, ip, ns, PP, i0,
                                           i1)
                            a = eg
                        e4 = e - (e - a) % 4
                        for q in range(a, e4, 4):
                            _min_corners4(best, ob, U, o00, o00 + ns, o10, o10 + ns, K, q, ip, ns, PP, i0, i1)
                        for q in range(e4, e):
                            _min_corners1(best, ob, U, o00, o00 + ns, o10, o10 + ns, K, q, ip, ns, PP, i0, i1)
                        a = e
            for ii in range(nr):
                for g in range(g0, g1):
                    VT[k, (i_lo + ii) * ng + g] = best[(g - g0) * nr + ii]
        _extend_rows(VT[k], i_lo, i_hi, ns, ng)
        _extend_rows(L1T[k], i_lo, i_hi, ns, 1)
    return -1


@njit(cache=True)
def backward1(N, P, big, w, VT, LT, level_tol, mode, lo, inv_dx, n, uniform, pts, strides, k_lo=0):
    """Baseline-DP backward pass (SOC alone, the level-set boundary, next states clipped to the grid): fills
    VT and LT at steps k_lo..N-1 from those at N (a part of the pass: :func:`backward_pass_fused` runs it
    in pieces to report progress). ``mode``, ``lo`` .. ``strides``: the engine's interpolation code and grid
    arrays (:meth:`optimize.dp.engine.DPProblem._grid_arrays`).

    The generic engine's loop with :func:`optimize.formulations.transition.hev_transition` written in for
    one state: the same operations in the same order on the same values, so the value and level functions
    are the engine's bit for bit, without a function argument (which numba compiles afresh in every
    process instead of caching it) and without copying the step's table or slicing the control rows.
    Serial: about 150 states per step are too few to pay for a parallel region per step. The heater
    controls of a power control all give the same transition with one state, so only the first of them
    is evaluated (the engine's tie rule keeps it)."""
    ns = VT.shape[1]
    np_ = big.shape[1]
    Ts = P[_C_TS]
    PEN = P[_C_PEN]
    ib = np.empty(1, np.int64)
    tb = np.empty(1)
    for k in range(N - 1, k_lo - 1, -1):
        tab = big[k]
        Vn = VT[k + 1]
        Ln = LT[k + 1]
        s_off = w[k, 5]
        for i in range(ns):
            best = np.inf
            Lmin = np.inf
            Lsel = np.inf
            feas = False
            for ip in range(np_):
                if tab[ip, _T_OK] == 0.0:
                    continue
                sn = tab[ip, _T_SOC0 + i]
                if not (sn == sn):
                    continue
                pen = 0.0
                if sn < P[_C_SLO]:
                    pen += (P[_C_SLO] - sn) / P[_C_SH]
                elif sn > P[_C_SHI]:
                    pen += (sn - P[_C_SHI]) / P[_C_SH]
                cst = tab[ip, _T_WF] * Ts + PEN * pen
                if not (cst < np.inf):
                    continue
                if not _locate(sn - s_off, 0, lo, inv_dx, n, uniform, pts, True, ib, tb):
                    continue
                lv = _interp(Ln, 1, strides, ib, tb)
                if not (lv < np.inf):
                    continue
                if lv < Lmin:
                    Lmin = lv
                if not level_needs_cost(lv, level_tol, feas, Lsel):
                    continue
                v = cst + _interp_v(mode, Vn, Ln, level_tol, 1, n, uniform, strides, ib, tb)
                if not (v < np.inf):
                    continue
                if level_better(lv, v, level_tol, feas, Lsel, best):
                    best = v
                    Lsel = lv
                    feas = lv <= level_tol
            LT[k, i] = Lmin
            VT[k, i] = best


@njit(cache=True)
def forward_hev(N, x0, controls, w, p, tab, VT, LT, use_level, level_tol, lo, inv_dx, n, uniform, pts, strides,
                clip, X_out, U_idx, stage, pred, mode):  # pragma: no cover - compiled
    """The engine's forward kernel (:func:`optimize.dp.kernels.forward`, the same loop) with
    :func:`hev_transition` and :func:`hev_precompute` called directly, for
    :attr:`optimize.dp.engine.DPProblem.forward_kernel`: numba caches it on disk, whereas the engine's
    kernel, which takes the functions as arguments, is compiled afresh in every process (a wrapper that
    passes them on is not cached either: numba marks the transition's code as using dynamic globals).
    tests/test_dp_progress.py checks that both passes give the same trajectory."""
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
        hev_precompute(k, w[k], p, tab)
        wk = w[k]
        Vn = VT[k + 1]
        Ln = LT[k + 1]
        best = np.inf
        Lsel = np.inf
        feas = False
        bi = -1
        for iu in range(nu):
            cst = hev_transition(k, x, controls[iu], wk, p, tab, iu, ix, xn)
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
        cst = hev_transition(k, x, controls[bi], wk, p, tab, bi, ix, xn)
        U_idx[k] = bi
        stage[k] = cst
        pred[k] = best
        for d in range(nx):
            x[d] = xn[d]
            X_out[k + 1, d] = xn[d]
    return N



def backward_pass_fused(prob, skip: bool = True, separable: bool = True, progress=None) -> ValueFunctions:
    """Backward pass of a problem built by :func:`optimize.formulations.build_problem`: Baseline-DP (1 state,
    :func:`backward1`), Thermal-DP (2 states) or Thermal-Cabin-DP (3 states); returns the engine's
    :class:`ValueFunctions`.

    ``skip``: SOC nodes whose charge is more than two nodes outside [soc_min, soc_max] at a step are not
    computed (:func:`_active`); ``False`` computes every node, as the generic engine does (2 and 3 states;
    Baseline-DP computes every node, as the engine does).
    ``separable``: a terminal level that depends on SOC alone runs :func:`backward2_sep` or
    :func:`backward3_sep` (the same value function up to rounding where the terminal set is reachable);
    ``False``, or another terminal set, or the cubic cost-to-go, or a cost-to-go with a non-finite value,
    runs :func:`backward2` or :func:`backward3` (the generic engine's values and levels bit for bit).
    ``progress``: None, or ``progress(done, total)`` called with the steps done so far as the pass goes
    (:func:`optimize.dp.engine.backward_pass`). ``.kernel`` says which kernel ran."""
    import time

    import numba

    from optimize.dp.engine import _interp_mode, _step_parts
    from optimize.formulations.layout import _A_BIG, _C_HOLD, _C_NQ

    P = prob.params
    nx = prob.n_x
    phi, level = prob.terminal_arrays()
    ns = prob.n_states
    N = prob.N
    VT = np.empty((N + 1, ns), dtype=np.float32)
    LT = np.empty((N + 1, ns), dtype=np.float32)
    VT[N] = phi
    LT[N] = level
    o, n = int(P[_A_BIG]), int(P[_A_BIG + 1])
    shape = prob.table_shape
    big = P[o: o + n].reshape(N, shape[0], shape[1])
    nq = int(P[_C_NQ])
    hold = bool(P[_C_HOLD]) if nx == 3 else False
    Q = np.ascontiguousarray(prob.controls[:nq - 1 if hold else nq, 2])
    if prob.interp == "cubic_last" and nx != 3:
        raise ValueError(f"interp {prob.interp!r}: the fused kernels offer it for 3 states only")
    reach = prob.interp == "reach_first"
    if nx not in (1, 2, 3):
        raise ValueError("fused kernels cover 1, 2 and 3 states")
    if nx == 1 and not (prob.boundary == "levelset" and prob.clip):
        raise ValueError("the 1-state fused kernel covers the level-set boundary with clipped next states")
    parts = _step_parts(N, progress)
    t0 = time.perf_counter()
    if progress is not None:
        progress(0, N)
    if nx == 1:
        lo, inv_dx, nn, uniform, pts, strides = prob._grid_arrays()
        mode = _interp_mode(prob.interp, 1)
        for hi, lo_k in parts:
            backward1(hi, P, big, prob.w, VT, LT, float(prob.level_tol), mode, lo, inv_dx, nn, uniform, pts, strides,
                      lo_k)
            if progress is not None:
                progress(N - lo_k, N)
        shape1 = (N + 1,) + prob.grid_shape
        return ValueFunctions(V=VT.reshape(shape1), L=LT.reshape(shape1), policy=None,
                              t_backward=time.perf_counter() - t0, n_evaluations=N * ns * prob.n_controls,
                              kernel="fused-1")
    g = prob.grids
    cubic = nx == 3 and prob.interp == "cubic_last" and g[2].size >= 3
    rows = LT[N].reshape(g[0].size, -1)
    kernel = "fused"
    if separable and not cubic and (nx == 3 or nq == 1) and bool(np.all(rows == rows[:, :1])):
        L1T = np.empty((N + 1, g[0].size), dtype=np.float32)
        L1T[N] = rows[:, 0]
        tol = float(prob.level_tol)
        nth = numba.get_num_threads()
        k = -1
        for hi, lo_k in parts:
            if nx == 2:
                k = backward2_sep(hi, P, big, prob.w, g[0], g[1], Q, VT, L1T, tol, reach, skip,
                                  min(g[1].size, 2 * nth), lo_k)
            else:
                k = backward3_sep(hi, P, big, prob.w, g[0], g[1], g[2], Q, VT, L1T, tol, hold, reach, skip,
                                  min(rows.shape[1], 4 * nth), nth, lo_k)
            if k >= 0:
                break
            if progress is not None:
                progress(N - lo_k, N)
        if k < 0:  # else a non-finite cost-to-go at step k: the exact kernel redoes the pass (V_N is untouched)
            # the levels of every state from those per SOC node, broadcast in place (np.repeat's temporary copy
            # of the 30-MB array took 9-57 ms of Thermal-DP's pass)
            LT.reshape(N + 1, g[0].size, -1)[:] = L1T[:, :, None]
            kernel = "fused-separable"
    if kernel == "fused":
        for hi, lo_k in parts:
            if nx == 2:
                backward2(hi, P, big, prob.w, g[0], g[1], Q, VT, LT, float(prob.level_tol), reach, skip, lo_k)
            else:
                backward3(hi, P, big, prob.w, g[0], g[1], g[2], Q, VT, LT, float(prob.level_tol), cubic, hold,
                          reach, skip, lo_k)
            if progress is not None:
                progress(N - lo_k, N)
    t_b = time.perf_counter() - t0
    gs = (N + 1,) + prob.grid_shape
    socg = prob.grids[0]
    s_inv = (socg.size - 1) / (socg[-1] - socg[0])
    rows = sum(b - a for a, b in (_active(P, prob.w[k, 4], socg[0], s_inv, socg.size, skip) for k in range(N)))
    return ValueFunctions(V=VT.reshape(gs), L=LT.reshape(gs), policy=None, t_backward=t_b,
                          n_evaluations=rows * (ns // socg.size) * prob.n_controls, kernel=kernel)
