"""One model step from a wheel-power demand, for every candidate control (compiled).

:func:`calib.model.equations.step` takes speeds; a causal controller (and the stochastic DP) knows the
demand ``P_trac`` instead. :func:`step_demand` chains the same equation functions as ``step`` after the
traction power (power split, battery, fuel rate, heater limit, coolant and cabin rates, Euler update),
so no equation is written twice; ``tests/test_causal_sdp.py`` checks it against ``step``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from calib.model.equations import (ENGINE_POWER, IDLE, OFF, ON, battery, battery_ocv_r, cabin_rate, coolant_flows,
                                   fuel_rate, heater_limit, power_split, traction_power)


@njit(cache=True)
def step_demand(p, soc, T_cl, T_cab, e_mode, P_bat_mg, Q_heat_cmd, P_trac, T_amb, T_bat, W_bl, Ts):
    """Returns (soc_next, T_cl_next, T_cab_next, W_f, code) of one step with wheel power ``P_trac``."""
    P_e, Pbm, P_em, P_brake, ok_e = power_split(p, e_mode, P_bat_mg, P_trac)
    I, V, U, R, code = battery(p, soc, Pbm + p.P_aux, T_bat)
    if not ok_e:
        code = ENGINE_POWER
    W_f = fuel_rate(p, e_mode, P_e, T_cl)
    Q_max = heater_limit(p, T_cl, T_cab, T_amb, W_bl)
    Q_heat = Q_heat_cmd if Q_heat_cmd < Q_max else Q_max
    if Q_heat < 0.0:
        Q_heat = 0.0
    dT_cl, Q_exh, Q_air, Q_rad, T_com = coolant_flows(p, T_cl, T_amb, p.LHV * W_f, P_e, Q_heat)
    dT_cab, Q_load = cabin_rate(p, T_cab, T_amb, Q_heat)
    if code != 0:
        return np.nan, np.nan, np.nan, np.nan, code
    return soc - I * Ts / p.C_bat_As, T_cl + Ts * dT_cl, T_cab + Ts * dT_cab, W_f, code


@njit(cache=True)
def eval_controls(p, soc, T_cl, T_cab, P_trac, controls, Q_heat_cmd, T_amb, T_bat, W_bl, Ts, out):
    """Every control row ``(e_mode, P_bat_mg)`` -> out[i] = (soc', T_cl', T_cab', W_f, feasible)."""
    for i in range(controls.shape[0]):
        r = step_demand(p, soc, T_cl, T_cab, int(controls[i, 0]), controls[i, 1], Q_heat_cmd, P_trac, T_amb,
                        T_bat, W_bl, Ts)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = r[0], r[1], r[2], r[3]
        out[i, 4] = 1.0 if r[4] == 0 else 0.0


def power_controls(mp, pbat_step: float = 500.0) -> np.ndarray:
    """Control rows (e_mode, P_bat_mg): off, idle, and on with the battery-terminal power on the grid
    ``P_bat_min : pbat_step : P_bat_max`` (the DP's power controls)."""
    n = int(np.floor((mp.P_bat_max - mp.P_bat_min) / pbat_step + 1e-9)) + 1
    P_bat = mp.P_bat_min + pbat_step * np.arange(n)
    rows = [(OFF, 0.0), (IDLE, 0.0)] + [(ON, pb - mp.P_aux) for pb in P_bat]
    return np.array(rows, dtype=np.float64)


def electric_g_per_soc(mp, soc: float) -> float:
    """Fuel (g) worth one unit of SOC: the valuation of :meth:`calib.model.simulate.SimResult.fuel_equivalents`."""
    U, _ = battery_ocv_r(mp, soc, mp.T_bat_ref)
    return float(mp.C_bat_As * U / (mp.LHV * float(np.max(mp.eta_ool)) * mp.eta_mech * mp.eta_em))


def coolant_g_per_K(mp) -> float:
    """Fuel (g) worth one kelvin of coolant (the same valuation as the corrected fuel)."""
    return float(mp.C_eng / (mp.LHV * (1.0 - mp.gamma_exh)))


@njit(cache=True)
def speed_after(p, v, P_trac, Ts):
    """Speed (m/s) at the end of a step that starts at ``v`` and asks wheel power ``P_trac`` on a flat road:
    :func:`calib.model.equations.traction_power` inverted by bisection (it increases with the end speed).

    The controllers' interface carries the wheel power, not the speed; chaining this from standstill
    recovers the speed a car reads from its wheel sensors (exactly on a flat road; a grade makes it drift
    until the next stop, where it clamps to 0)."""
    if P_trac <= traction_power(p, v, 0.0, 0.0, Ts):
        return 0.0
    lo, hi = 0.0, v + 10.0 * Ts
    while traction_power(p, v, hi, 0.0, Ts) < P_trac:
        hi = 2.0 * hi + 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if traction_power(p, v, mid, 0.0, Ts) < P_trac:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-9:
            break
    return 0.5 * (lo + hi)


def kinetic_soc_per_v2(mp, soc: float, regen_fraction: float) -> float:
    """SOC (per (m/s)^2) that braking to a stop returns to the battery: ``regen_fraction`` of the kinetic
    energy ``m_eq v^2 / 2`` (road load and friction brakes take the rest), over ``C_bat U_oc(soc)``."""
    U, _ = battery_ocv_r(mp, soc, mp.T_bat_ref)
    return float(regen_fraction * 0.5 * mp.m_eq / (mp.C_bat_As * U))


def stop_regen(mp, cycle, soc: float = 0.6, T_amb: float = 0.0) -> np.ndarray:
    """Every braking to a stop of ``cycle`` (speed falling from above 3 m/s to below 0.5 m/s): rows
    ``(v0 m/s, share)``, the SOC the model's battery gains from the first slower sample to the stop with the
    engine off, as a share of the kinetic energy at ``v0`` (:func:`kinetic_soc_per_v2` with share 1).

    The share falls with speed: from highway speed the way down is longer, and road load takes more."""
    from calib.model.cycles import load_cycle

    c = load_cycle(cycle) if isinstance(cycle, str) else cycle
    v, n, k1 = np.asarray(c.v, float), len(c.v), kinetic_soc_per_v2(mp, soc, 1.0)
    rows, i = [], 0
    while i < n - 1:
        if v[i] > 3.0 and v[i + 1] < v[i]:
            j = i
            while j < n - 1 and v[j + 1] <= v[j] + 0.05 and v[j] > 0.3:  # tolerate sensor wiggle
                j += 1
            if v[j] <= 0.5:
                s = soc
                for k in range(i, j):
                    P = traction_power(mp, v[k], v[k + 1], 0.0, c.Ts)
                    s = step_demand(mp, s, 70.0, 20.0, OFF, 0.0, 0.0, P, T_amb, mp.T_bat_ref, mp.W_bl, c.Ts)[0]
                rows.append((v[i], (s - soc) / (k1 * v[i] ** 2)))
            i = j + 1
        else:
            i += 1
    return np.array(rows, float).reshape(-1, 2)


def fit_stop_regen(mp, cycles, soc: float = 0.6) -> tuple[float, float]:
    """``(share at standstill, change per m/s)``: the line through the stops of ``cycles``
    (:func:`stop_regen`) by least squares weighted by each stop's kinetic energy."""
    from calib.errors import IptmError

    r = np.vstack([stop_regen(mp, c, soc) for c in cycles])
    if r.shape[0] < 2 or np.ptp(r[:, 0]) < 1.0:
        raise IptmError(f"fit_stop_regen: {r.shape[0]} stops in {list(cycles)} span too few speeds to fit a line; "
                        "give drives that brake to a stop from different speeds")
    w = r[:, 0]  # residuals times speed: squared, weighted by kinetic energy
    A = np.column_stack([np.ones(r.shape[0]), r[:, 0]]) * w[:, None]
    f0, f1 = np.linalg.lstsq(A, r[:, 1] * w, rcond=None)[0]
    return float(f0), float(f1)
