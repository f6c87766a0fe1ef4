"""The vehicle model of docs/model.md: one implementation for simulation, fitting and DP.

Every equation is a small ``numba`` function on scalars taking the compiled parameter tuple
(:meth:`calib.model.params.ParameterSet.model_params`). Compiled kernels (the simulator's step, the fitters'
output-error loops, the DP kernels in :mod:`optimize`) call these same functions inline;
:func:`evaluate` broadcasts them over numpy arrays of any shape (whole DP grids, whole logs).

Conventions (SI; temperatures in degC): states ``soc`` (fraction), ``T_cl`` (coolant), ``T_cab`` (cabin);
controls ``e_mode`` (1 off, 2 idle, 3 on, 4 catalyst heating), ``P_bat_mg`` (W, + = discharge; only used when on),
``Q_heat_cmd`` (W, heat requested from the heater core); exogenous ``v, v_next`` (m/s at steps k, k+1),
``grade`` (rad), ``T_amb``, ``T_bat`` (degC), ``W_bl`` (kg/s blower flow).

Refinements of the spec's choices (allowed by docs/model.md, stated here):

- Traction power uses the step's mean speed ``(v_k + v_{k+1})/2`` with ``a_k = (v_{k+1} - v_k)/Ts``, so
  the kinetic-energy change over a step is exact and pulling away from standstill costs power.
- An engine that is on never burns less than at idle: ``W_f = max(map(P_e), W_idle) f_cl``.
- The heater core delivers ``min(Q_heat_cmd, eps_hc W_bl c_p (T_cl - T_in))``; the shortfall is reported.
- Battery current uses the cancellation-free form ``I = 2 P / (U + sqrt(U^2 - 4 R P))`` of eq. 1.
- Integration: explicit Euler with step ``Ts`` (default 1 s) for SOC, coolant and cabin.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

G = 9.81
OFF, IDLE, ON = 1, 2, 3
# Catalyst heating after a cold start: the engine turns at a set speed with its ignition retarded, gives no
# power to the drive and burns a fixed fuel rate; the motor drives the car (docs/cold_start.md).
CAT = 4

# Feasibility codes returned by :func:`step` (0 = feasible).
FEASIBLE, ENGINE_POWER, BATTERY_LIMIT, BATTERY_ROOT = 0, 1, 2, 3
INFEASIBLE_REASONS = {
    ENGINE_POWER: "engine power outside (0, P_e_max]",
    BATTERY_LIMIT: "battery power outside [P_bat_min, P_bat_max]",
    BATTERY_ROOT: "battery power above U_oc^2/(4 R_int): no real current",
}

# Names of the outputs of :func:`step`, in order.
OUTPUTS = (
    "soc_next", "T_cl_next", "T_cab_next", "code", "P_trac", "P_e", "P_bat_mg", "P_em", "P_brake",
    "P_bat", "I_bat", "V_bat", "U_oc", "R_int", "omega_e", "tau_e", "W_f", "f_cl", "Q_fuel", "Q_exh",
    "Q_air", "Q_rad", "Q_heat", "Q_heat_max", "Q_cab_load", "T_com",
)
N_OUT = len(OUTPUTS)


@njit(cache=True)
def traction_power(p, v, v_next, grade, Ts):
    """Eq. in s.1: power at the wheels (W), mean speed over the step."""
    vm = 0.5 * (v + v_next)
    a = (v_next - v) / Ts
    F = p.m_eq * a + p.m * G * math.sin(grade)
    if vm > 0.0:
        F += p.A + p.B * vm + p.C * vm * vm
    return F * vm


@njit(cache=True)
def power_split(p, e_mode, P_bat_mg, P_trac):
    """s.2: returns (P_e, P_bat_mg, P_em, P_brake, ok).

    Off/idle: the motor alone meets the demand (regeneration limited to ``P_regen_max`` at the wheels,
    friction brakes take the rest) and ``P_bat_mg`` is set by the demand. On: ``P_bat_mg`` is the control
    and the engine supplies the rest; feasible when ``0 < P_e <= P_e_max``.
    """
    if e_mode != ON:
        if P_trac >= 0.0:
            return 0.0, P_trac / p.eta_em, P_trac, 0.0, True
        P_em = max(P_trac, -p.P_regen_max)
        return 0.0, P_em * p.eta_em, P_em, P_trac - P_em, True
    if P_bat_mg >= 0.0:
        P_em = p.eta_em * P_bat_mg
    else:
        P_em = P_bat_mg / p.eta_em
    P_e = (P_trac - P_em) / p.eta_mech
    return P_e, P_bat_mg, P_em, 0.0, (P_e > 0.0) and (P_e <= p.P_e_max)


@njit(cache=True)
def battery_ocv_r(p, soc, T_bat):
    """U_oc(SOC) and R_int(SOC, T_bat) from the tables."""
    U = np.interp(soc, p.soc_bp, p.U_oc)
    R = np.interp(soc, p.soc_bp_R, p.R_int) * math.exp(-p.R_tc * (T_bat - p.T_bat_ref))
    return U, R


@njit(cache=True)
def battery_current(U, R, P_bat, U_h):
    """Eq. 1's current for terminal power P_bat at open-circuit voltage U, resistance R and hysteresis U_h
    (``V = U - U_h sgn(I) - R I``; I has the sign of P_bat, so the effective source voltage is ``U - U_h``
    discharging and ``U + U_h`` charging). Cancellation-free root; NaN where ``U_e^2 < 4 R P_bat``."""
    if P_bat > 0.0:
        U = U - U_h
    elif P_bat < 0.0:
        U = U + U_h
    disc = U * U - 4.0 * R * P_bat
    if disc < 0.0:
        return np.nan
    return 2.0 * P_bat / (U + math.sqrt(disc))


@njit(cache=True)
def battery(p, soc, P_bat, T_bat):
    """Eq. 1: returns (I, V, U_oc, R_int, code); code 0 feasible, else an infeasibility code."""
    U, R = battery_ocv_r(p, soc, T_bat)
    I = battery_current(U, R, P_bat, p.U_hyst)
    if not (I == I):
        return np.nan, np.nan, U, R, BATTERY_ROOT
    code = FEASIBLE
    if P_bat < p.P_bat_min or P_bat > p.P_bat_max:
        code = BATTERY_LIMIT
    return I, U - p.U_hyst * np.sign(I) - R * I, U, R, code


@njit(cache=True)
def f_cold(p, T_cl):
    """Cold-coolant fuel factor f_cl(T_cl) (flat beyond the table's ends)."""
    return np.interp(T_cl, p.T_fcl, p.f_cl)


@njit(cache=True)
def engine_speed(p, e_mode, P_e):
    """Engine speed (rad/s): 0 off, idle speed, catalyst-heating speed, or the optimal operating line at P_e."""
    if e_mode == OFF:
        return 0.0
    if e_mode == IDLE:
        return p.w_idle
    if e_mode == CAT:
        return p.w_cat
    return np.interp(P_e, p.P_ool, p.w_ool)


@njit(cache=True)
def fuel_map(p, P_e):
    """Warm fuel rate on the optimal operating line (g/s), never below idle."""
    eta = np.interp(P_e, p.P_ool, p.eta_ool)
    w = p.fuel_scale * P_e / (eta * p.LHV)
    return w if w > p.W_idle else p.W_idle


@njit(cache=True)
def fuel_rate(p, e_mode, P_e, T_cl):
    """Eqs. 4-5: fuel mass flow (g/s) with the cold correction; catalyst heating burns its set rate."""
    if e_mode == OFF:
        return 0.0
    if e_mode == IDLE:
        return p.W_idle * f_cold(p, T_cl)
    if e_mode == CAT:
        return p.W_cat
    return fuel_map(p, P_e) * f_cold(p, T_cl)


# Scalar forms (parameters as plain numbers): the DP kernels, which receive the parameters as a flat
# vector, call these; the ``p`` forms below call them too, so each equation is written once.
@njit(cache=True)
def heater_core_limit(eps_hc, W_bl, cp_air, recirc, T_cl, T_cab, T_amb):
    """Most heat the core can pass to the air: eps W_bl c_p (T_cl - T_in), >= 0."""
    T_in = recirc * T_cab + (1.0 - recirc) * T_amb
    q = eps_hc * W_bl * cp_air * (T_cl - T_in)
    return q if q > 0.0 else 0.0


@njit(cache=True)
def radiator_heat(k_rad, T_open, Q_rad_max, T_cl):
    """Eq. 9: radiator heat rejection (W)."""
    if T_cl <= T_open:
        return 0.0
    q = k_rad * (T_cl - T_open)
    return q if q < Q_rad_max else Q_rad_max


@njit(cache=True)
def engine_bay_loss(hA_eng, kappa, T_cl, T_amb):
    """Eqs. 7-8: (heat lost to the engine-bay air Q_air, engine-compartment temperature T_com)."""
    T_com = T_amb + kappa * (T_cl - T_amb)
    return hA_eng * (T_cl - T_com), T_com


@njit(cache=True)
def coolant_heat_rate(gamma_exh, Q_fuel, P_e, Q_loss, Q_heat):
    """Eqs. 3, 6: net heat into the coolant (W) and Q_exh, with Q_loss = engine-bay loss + radiator."""
    Q_exh = gamma_exh * (Q_fuel - P_e)
    return Q_fuel - P_e - Q_exh - Q_loss - Q_heat, Q_exh


@njit(cache=True)
def cabin_heat_rate(UA_cab, Q_sun, T_cab, T_amb, Q_heat):
    """Eq. 10: net heat into the cabin (W) and the load Q_load."""
    Q_load = UA_cab * (T_amb - T_cab)
    return Q_heat + Q_load + Q_sun, Q_load


@njit(cache=True)
def cabin_heat_to_reach(UA_cab, Q_sun, C_cab, T_cab, T_amb, T_target, Ts):
    """Eq. 10 solved for the heat: the Q_heat that takes the cabin from T_cab to T_target in one explicit-
    Euler step of Ts (unbounded; the caller clips it to what the heater can do)."""
    net0, _ = cabin_heat_rate(UA_cab, Q_sun, T_cab, T_amb, 0.0)
    return C_cab * (T_target - T_cab) / Ts - net0


@njit(cache=True)
def heater_limit(p, T_cl, T_cab, T_amb, W_bl):
    """Most heat the core can pass to the air: eps W_bl c_p (T_cl - T_in), >= 0."""
    return heater_core_limit(p.eps_hc, W_bl, p.cp_air, p.recirc, T_cl, T_cab, T_amb)


@njit(cache=True)
def radiator(p, T_cl):
    """Eq. 9: radiator heat rejection (W)."""
    return radiator_heat(p.k_rad, p.T_open, p.Q_rad_max, T_cl)


@njit(cache=True)
def coolant_flows(p, T_cl, T_amb, Q_fuel, P_e, Q_heat):
    """Eqs. 3, 6-8: returns (dT_cl/dt, Q_exh, Q_air, Q_rad, T_com)."""
    Q_air, T_com = engine_bay_loss(p.hA_eng, p.kappa, T_cl, T_amb)
    Q_rad = radiator(p, T_cl)
    net, Q_exh = coolant_heat_rate(p.gamma_exh, Q_fuel, P_e, Q_air + Q_rad, Q_heat)
    return net / p.C_eng, Q_exh, Q_air, Q_rad, T_com


@njit(cache=True)
def cabin_rate(p, T_cab, T_amb, Q_heat):
    """Eq. 10: returns (dT_cab/dt, Q_load)."""
    net, Q_load = cabin_heat_rate(p.UA_cab, p.Q_sun, T_cab, T_amb, Q_heat)
    return net / p.C_cab, Q_load


@njit(cache=True)
def step(p, soc, T_cl, T_cab, e_mode, P_bat_mg, Q_heat_cmd, v, v_next, grade, T_amb, T_bat, W_bl, Ts):
    """One explicit-Euler step of the whole model; returns a tuple in the order of :data:`OUTPUTS`."""
    P_trac = traction_power(p, v, v_next, grade, Ts)
    P_e, Pbm, P_em, P_brake, ok_e = power_split(p, e_mode, P_bat_mg, P_trac)
    P_bat = Pbm + p.P_aux
    I, V, U, R, code = battery(p, soc, P_bat, T_bat)
    if not ok_e:
        code = ENGINE_POWER
    omega = engine_speed(p, e_mode, P_e)
    tau = P_e / omega if omega > 0.0 else 0.0
    W_f = fuel_rate(p, e_mode, P_e, T_cl)
    fcl = f_cold(p, T_cl)
    Q_fuel = p.LHV * W_f
    Q_max = heater_limit(p, T_cl, T_cab, T_amb, W_bl)
    Q_heat = Q_heat_cmd if Q_heat_cmd < Q_max else Q_max
    if Q_heat < 0.0:
        Q_heat = 0.0
    dT_cl, Q_exh, Q_air, Q_rad, T_com = coolant_flows(p, T_cl, T_amb, Q_fuel, P_e, Q_heat)
    dT_cab, Q_load = cabin_rate(p, T_cab, T_amb, Q_heat)
    soc_next = soc - I * Ts / p.C_bat_As
    return (soc_next, T_cl + Ts * dT_cl, T_cab + Ts * dT_cab, float(code), P_trac, P_e, Pbm, P_em, P_brake,
            P_bat, I, V, U, R, omega, tau, W_f, fcl, Q_fuel, Q_exh, Q_air, Q_rad, Q_heat, Q_max, Q_load, T_com)


@njit(cache=True)
def _evaluate_flat(p, soc, T_cl, T_cab, e_mode, P_bat_mg, Q_heat_cmd, v, v_next, grade, T_amb, T_bat, W_bl,
                   Ts, out):
    for i in range(soc.shape[0]):
        r = step(p, soc[i], T_cl[i], T_cab[i], int(e_mode[i]), P_bat_mg[i], Q_heat_cmd[i], v[i], v_next[i],
                 grade[i], T_amb[i], T_bat[i], W_bl[i], Ts)
        for j in range(len(r)):
            out[i, j] = r[j]


def evaluate(params, soc, T_cl, T_cab, e_mode, P_bat_mg, Q_heat_cmd, v, v_next, *, T_amb, grade=0.0,
             T_bat=None, W_bl=None, Ts=1.0) -> dict:
    """Evaluate :func:`step` on arrays that broadcast together (whole grids of states and controls).

    Parameters
    ----------
    params : ParameterSet or ModelParams
    soc, T_cl, T_cab, e_mode, P_bat_mg, Q_heat_cmd, v, v_next, T_amb, grade, T_bat, W_bl : array_like
        States, controls and exogenous inputs (see module docstring). ``T_bat`` defaults to the
        resistance table's reference temperature, ``W_bl`` to the blower-flow parameter.
    Ts : float
        Step (s).

    Returns
    -------
    dict
        Every name of :data:`OUTPUTS` mapped to an array of the broadcast shape; ``feasible`` is added
        (``code == 0``).
    """
    p = params.model_params() if hasattr(params, "model_params") else params
    if T_bat is None:
        T_bat = p.T_bat_ref
    if W_bl is None:
        W_bl = p.W_bl
    arrs = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in
                                 (soc, T_cl, T_cab, e_mode, P_bat_mg, Q_heat_cmd, v, v_next, grade, T_amb,
                                  T_bat, W_bl)])
    shape = arrs[0].shape
    flat = [np.ascontiguousarray(a).ravel() for a in arrs]
    out = np.empty((flat[0].size, N_OUT))
    _evaluate_flat(p, *flat, float(Ts), out)
    res = {name: out[:, j].reshape(shape) for j, name in enumerate(OUTPUTS)}
    res["feasible"] = res["code"] == 0
    return res


@njit(cache=True)
def battery_current_array(U, R, P_bat, U_h):
    """:func:`battery_current` element by element over 1-D arrays (NaN where there is no real current)."""
    out = np.empty(P_bat.shape[0])
    for k in range(P_bat.shape[0]):
        out[k] = battery_current(U[k], R[k], P_bat[k], U_h)
    return out
