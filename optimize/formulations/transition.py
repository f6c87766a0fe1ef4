"""The compiled HEV transition shared by the three formulations, and its per-step tables."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from calib.model.equations import (IDLE, OFF, battery_current, battery_ocv_r, cabin_heat_rate, cabin_heat_to_reach,
                                   coolant_heat_rate, engine_bay_loss, fuel_map, heater_core_limit, power_split, radiator_heat)

from optimize.formulations.layout import (_A_BIG, _A_FCL, _A_FCLG, _A_LOSSG, _A_RINT, _A_SOCBP, _A_SOCBPR, _A_TFCL, _A_UOC, _CBAT,
                     _CCAB, _CENG, _CP, _C_CH, _C_CHI, _C_CREL, _C_NQ, _C_QHI, _C_QLO, _C_NX, _C_PEN, _C_SH, _C_SHI, _C_SLO, _C_TAMB,
                     _C_TBAT, _C_TH, _C_THI, _C_TLO, _C_TS, _C_WBL, _EPS, _GAMMA, _HA, _KAPPA, _KRAD, _LHV,
                     _MS0, _QRADMAX, _QSUN, _RECIRC, _R_TC, _TBREF, _TOPEN, _T_OK, _T_PBAT, _T_PE, _T_SOC0, _UHYST,
                     _T_WF, _UACAB, _arr)

@njit(cache=True)
def build_tables(mp, pc, socg, P_trac, Ts, T_bat, off):  # pragma: no cover - compiled
    """(N, n_p, 4 + n_soc): per step and power control: feasible, P_e, warm fuel (g/s), P_bat and the
    next SOC at every SOC node (NaN: infeasible); the node i of step k is the charge ``socg[i] + off[k]``
    (:func:`drift_offsets`; zeros: a fixed grid). Uses the model functions of :mod:`calib.model`."""
    out = np.empty((P_trac.shape[0], pc.shape[0], _T_SOC0 + socg.shape[0]))
    fill_tables(out, mp, pc, socg, P_trac, Ts, T_bat, off)
    return out


@njit(cache=True)
def fill_tables(out, mp, pc, socg, P_trac, Ts, T_bat, off):  # pragma: no cover - compiled
    """:func:`build_tables` into ``out`` (a view of the packed parameter vector: the tables, the largest
    array of a problem, are then held once)."""
    N = P_trac.shape[0]
    nsoc = socg.shape[0]
    Us = np.empty(nsoc)
    Rs = np.empty(nsoc)
    for k in range(N):
        for i in range(nsoc):
            Us[i], Rs[i] = battery_ocv_r(mp, socg[i] + off[k], T_bat)
        for ip in range(pc.shape[0]):
            e = int(pc[ip, 0])
            P_e, Pbm, P_em, P_brake, ok = power_split(mp, e, pc[ip, 1], P_trac[k])
            P_bat = Pbm + mp.P_aux
            if P_bat < mp.P_bat_min or P_bat > mp.P_bat_max:
                ok = False
            out[k, ip, _T_OK] = 1.0 if ok else 0.0
            out[k, ip, _T_PE] = P_e
            if e == OFF:
                wf = 0.0
            elif e == IDLE:
                wf = mp.W_idle
            else:
                wf = fuel_map(mp, P_e)
            out[k, ip, _T_WF] = wf
            out[k, ip, _T_PBAT] = P_bat
            for i in range(nsoc):
                sn = np.nan
                if ok:
                    # U_oc and R_int of the node precomputed
                    I = battery_current(Us[i], Rs[i], P_bat, mp.U_hyst)
                    if I == I:
                        sn = (socg[i] + off[k]) - I * Ts / mp.C_bat_As
                out[k, ip, _T_SOC0 + i] = sn


@njit(cache=True)
def drift_offsets(mp, P_trac, Ts, T_bat, soc_end):  # pragma: no cover - compiled
    """(N+1,) charge the engine-off drive carries to ``soc_end`` at step N, minus ``soc_end``: the engine
    stays off (where it may; elsewhere the charge is held) and the step is inverted by three fixed-point
    iterations. A SOC grid shifted by these offsets at every step carries an engine-off step from node to
    node (up to the battery's dependence on the charge, below 0.1 % of a 0.01 cell a step)."""
    N = P_trac.shape[0]
    off = np.zeros(N + 1)
    r = soc_end
    for k in range(N - 1, -1, -1):
        P_e, Pbm, P_em, P_brake, ok = power_split(mp, OFF, 0.0, P_trac[k])
        P_bat = Pbm + mp.P_aux
        if ok and mp.P_bat_min <= P_bat <= mp.P_bat_max:
            x = r
            for _ in range(3):
                U, R = battery_ocv_r(mp, x, T_bat)
                I = battery_current(U, R, P_bat, mp.U_hyst)
                if not (I == I):
                    x = r
                    break
                x = r + I * Ts / mp.C_bat_As
            r = x
        off[k] = r - soc_end
    return off


@njit(cache=True)
def hev_precompute(k, w_k, p, tab):  # pragma: no cover - compiled
    """Per step: copy step k's slice of the per-step per-control table."""
    o = int(p[_A_BIG])
    n0 = tab.shape[0]
    n1 = tab.shape[1]
    o += k * n0 * n1
    for i in range(n0):
        for j in range(n1):
            tab[i, j] = p[o + i * n1 + j]


@njit(inline="always", cache=True)
def _soc_next(p, soc, P_bat, Ts):
    """Off-grid SOC step (forward pass): calib.model.equations.battery with the tables of p; NaN if no real root."""
    U = np.interp(soc, _arr(p, _A_SOCBP), _arr(p, _A_UOC))
    R = np.interp(soc, _arr(p, _A_SOCBPR), _arr(p, _A_RINT)) * math.exp(-p[_MS0 + _R_TC] * (p[_C_TBAT] - p[_MS0 + _TBREF]))
    return soc - battery_current(U, R, P_bat, p[_MS0 + _UHYST]) * Ts / p[_MS0 + _CBAT]


@njit(inline="always", cache=True)
def hold_heat(p, T_cab, T_target):
    """Heat of the "hold the bound" control: what takes the cabin from T_cab to T_target in one step
    (:func:`calib.model.equations.cabin_heat_to_reach`), clipped to the heater grid's ends (Q_heat_min and
    the grid's top value); the heater-core limit is applied after, as to any command."""
    q = cabin_heat_to_reach(p[_MS0 + _UACAB], p[_MS0 + _QSUN], p[_MS0 + _CCAB], T_cab, p[_C_TAMB], T_target,
                            p[_C_TS])
    if q < p[_C_QLO]:
        q = p[_C_QLO]
    if q > p[_C_QHI]:
        q = p[_C_QHI]
    return q


@njit(inline="always", cache=True)
def _delivered_heat(p, T_cl, T_cab, q_cmd, T_target):
    """The heat a command delivers at (T_cl, T_cab): the hold heat for a NaN command, then the core limit."""
    q_lim = heater_core_limit(p[_MS0 + _EPS], p[_C_WBL], p[_MS0 + _CP], p[_MS0 + _RECIRC], T_cl, T_cab, p[_C_TAMB])
    q = q_cmd
    if not (q == q):
        q = hold_heat(p, T_cab, T_target)
    if q > q_lim:
        q = q_lim
    if q < 0.0:
        q = 0.0
    return q


@njit(cache=True)
def delivered_heat(p, x, u, w):  # pragma: no cover - compiled
    """(N,) heat delivered by the controls u (N, 3) along the trajectory x (N+1, 3) of a Thermal-Cabin
    problem (the forward pass's states): what :func:`hev_transition` used at each step."""
    N = u.shape[0]
    out = np.empty(N)
    for k in range(N):
        T_cab = x[k, 2]
        if p[_C_CREL] != 0.0:
            T_cab += w[k, 3]
        out[k] = _delivered_heat(p, x[k, 1], T_cab, u[k, 2], w[k, 2])
    return out


@njit(cache=True)
def hev_transition(k, x, u, w_k, p, tab, iu, ix, x_next):  # pragma: no cover - compiled
    """x = (soc[, T_cl[, T_cab]]), u = (e_mode, P_bat_mg, Q_heat_cmd; NaN: hold the bound, :func:`hold_heat`);
    w_k = (P_trac, T_cab_ref_k, T_cab_LB_k+1, T_cab_LB_k, SOC offset_k, SOC offset_k+1). The SOC state is the
    charge minus the step's offset (:func:`drift_offsets`; zeros: the charge itself). With the cabin relative
    to its bound (``p[_C_CREL]``) the cabin state is T_cab - T_cab_LB_k.

    Returns the fuel (g) of the step, inf if infeasible. Same equations as :func:`calib.model.equations.step`."""
    nq = int(p[_C_NQ])
    ip = iu // nq
    if tab[ip, _T_OK] == 0.0:
        return np.inf
    Ts = p[_C_TS]
    if ix[0] >= 0:
        sn = tab[ip, _T_SOC0 + ix[0]]
    else:
        sn = _soc_next(p, x[0] + w_k[4], tab[ip, _T_PBAT], Ts)
    if not (sn == sn):
        return np.inf
    x_next[0] = sn - w_k[5]
    pen = 0.0
    if sn < p[_C_SLO]:
        pen += (p[_C_SLO] - sn) / p[_C_SH]
    elif sn > p[_C_SHI]:
        pen += (sn - p[_C_SHI]) / p[_C_SH]
    nx = int(p[_C_NX])
    wf = tab[ip, _T_WF]
    if nx == 1:
        return wf * Ts + p[_C_PEN] * pen
    T_cl = x[1]
    T_amb = p[_C_TAMB]
    if ix[1] >= 0:
        fcl = p[int(p[_A_FCLG]) + ix[1]]
        loss = p[int(p[_A_LOSSG]) + ix[1]]
    else:
        fcl = np.interp(T_cl, _arr(p, _A_TFCL), _arr(p, _A_FCL))
        q_air, _ = engine_bay_loss(p[_MS0 + _HA], p[_MS0 + _KAPPA], T_cl, T_amb)
        loss = q_air + radiator_heat(p[_MS0 + _KRAD], p[_MS0 + _TOPEN], p[_MS0 + _QRADMAX], T_cl)
    W_f = wf * fcl
    if nx == 3:
        T_cab = x[2]
        if p[_C_CREL] != 0.0:
            T_cab += w_k[3]
    else:
        T_cab = w_k[1]
    q = _delivered_heat(p, T_cl, T_cab, u[2], w_k[2])
    Q_fuel = p[_MS0 + _LHV] * W_f
    P_e = tab[ip, _T_PE]
    tn = T_cl + Ts * coolant_heat_rate(p[_MS0 + _GAMMA], Q_fuel, P_e, loss, q)[0] / p[_MS0 + _CENG]
    x_next[1] = tn
    if tn < p[_C_TLO]:
        pen += (p[_C_TLO] - tn) / p[_C_TH]
    elif tn > p[_C_THI]:
        pen += (tn - p[_C_THI]) / p[_C_TH]
    if nx == 3:
        tc = T_cab + Ts * cabin_heat_rate(p[_MS0 + _UACAB], p[_MS0 + _QSUN], T_cab, T_amb, q)[0] / p[_MS0 + _CCAB]
        x_next[2] = tc - w_k[2] if p[_C_CREL] != 0.0 else tc
        if tc < w_k[2]:
            pen += (w_k[2] - tc) / p[_C_CH]
        elif tc > p[_C_CHI]:
            pen += (tc - p[_C_CHI]) / p[_C_CH]
    return W_f * Ts + p[_C_PEN] * pen


# ---------------------------------------------------------------------------------------------------
# outcome
# ---------------------------------------------------------------------------------------------------
