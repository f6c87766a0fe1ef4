"""Validation of a parameter set on a drive log: replay simulation, error metrics, Fig. 3-style plots.

The replay drives the model of :mod:`calib.model` with the *inputs* a log records and compares the
*outputs* it simulates with the ones the log measured:

- inputs: the engine operating point (logged speed x torque gives ``P_e``; the engine mode is read from
  the logged speed and torque), the battery terminal power ``V I`` (or, when voltage/current are missing,
  the power split from the logged speed and engine power), the heat drawn by the heater core (logged, or
  ``W_bl c_p (T_vent - T_in)`` from vent temperature and blower flow), ambient and battery temperature;
- simulated outputs: SOC (eq. 1 with the calibrated ``U_oc``, ``R_int``, ``C_bat``), coolant temperature
  (eq. 3 fed with the *simulated* fuel rate, so the cold factor acts on the simulated coolant), cabin
  temperature (eq. 10), fuel rate (eqs. 4-5) and cumulative fuel.

The initial states are the mean of the first five valid logged values. The measured fuel rate is taken
as zero where the engine is stopped (speed below 150 rpm). The loop is compiled (``numba``) and calls the same
equation functions as the simulator and the fitters.

Also here: :func:`log_arrays`, the per-log input arrays every fitter uses (engine mode classification,
engine power, heater power), so all fits read a log the same way.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from .model import IDLE, OFF, ON, battery, coolant_flows, cabin_rate, fuel_rate, power_split, traction_power

RPM = 2.0 * math.pi / 60.0

#: Validated channels: name -> (log column, unit).
CHANNEL_METRICS = {
    "soc": ("soc", "-"),
    "coolant_temp": ("coolant_temp_degC", "degC"),
    "cabin_temp": ("cabin_temp_degC", "degC"),
    "fuel_rate": ("fuel_rate_g_per_s", "g/s"),
}


# --------------------------------------------------------------------------------------------------
# reading a log into arrays
# --------------------------------------------------------------------------------------------------
def _col(df, name):
    if name in df.columns:
        return df[name].to_numpy(dtype=float)
    return np.full(len(df), np.nan)


def _fill(a, default=np.nan):
    """Linear interpolation over NaN (held flat at the ends); ``default`` when all NaN."""
    a = np.asarray(a, dtype=float)
    ok = np.isfinite(a)
    if not ok.any():
        return np.full(a.shape, default)
    if ok.all():
        return a.copy()
    idx = np.arange(a.size)
    return np.interp(idx, idx[ok], a[ok])


def engine_mode(n_rpm, tau_Nm, n_idle_rpm=1000.0):
    """Engine mode per sample from logged speed and torque: 1 off, 2 idle, 3 on, 0 unknown/mixed.

    Off: speed below 150 rpm. Idle: speed within 15 % of the idle speed and torque below 2 N m. On: torque
    above 2 N m and speed above 500 rpm. Anything else (a 1 s bin that straddles a start or stop) is 0.
    """
    n = np.asarray(n_rpm, float)
    tq = np.asarray(tau_Nm, float)
    mode = np.zeros(n.shape, dtype=np.int64)
    mode[n < 150.0] = OFF
    mode[(np.abs(n - n_idle_rpm) < 0.15 * n_idle_rpm) & (np.abs(tq) < 2.0)] = IDLE
    mode[(tq >= 2.0) & (n > 500.0)] = ON
    mode[~(np.isfinite(n) & np.isfinite(tq))] = 0
    return mode


def stable_mode(mode):
    """True where the mode is known and the same at k-1, k and k+1 (bins not straddling a transition)."""
    m = np.asarray(mode)
    s = m > 0
    s[1:] &= m[1:] == m[:-1]
    s[:-1] &= m[:-1] == m[1:]
    return s


def operating_point(n_rpm, tau_Nm, mode, stable, mp):
    """Split every 1 s bin into engine-on (power ``P_on``), idle and off fractions.

    A resampled bin holds the *means* of speed and torque over the bin, so ``mean(n) * mean(tau)`` is
    not the engine power when the operating point changed within it (an engine start or stop, or a
    controller that toggles the engine every second). The engine is taken to follow the model's optimal
    operating line (OOL) when at least half of the engine-on bins have their mean speed within 0.5 % of
    ``w_ool(n tau)``. Then:

    - a bin on the line is one operating point, its power read from its mean speed along the line;
    - a bin near the line (torque within 10 % of the line's at its mean speed) mixes nearby on-line
      points: its mean power is read from its mean speed;
    - a bin far off the line is a mixture: the engine ran on the line for a fraction ``f`` of the bin and was
      off or idling (as a neighbour bin) for the rest; ``f`` and the power solve
      ``n_mean = f w_ool(P) + (1 - f) n_other`` and ``tau_mean = f P / w_ool(P)``; when no such
      solution exists the bin mixes two on-line points and its power is read from its mean speed.

    An engine that does not follow the line (a real engine with its own calibration) keeps
    ``P = n tau``, with the mixture solution only for bins next to an off/idle bin.

    Returns
    -------
    f_on, P_on, f_idle : ndarray
    """
    w = np.asarray(n_rpm, float) * RPM
    tq = np.asarray(tau_Nm, float)
    n = w.size
    f_on = np.zeros(n)
    P_on = np.zeros(n)
    f_idle = np.zeros(n)
    valid = np.isfinite(w) & np.isfinite(tq)
    onb = valid & (tq >= 2.0) & (w > 500 * RPM)
    increasing = bool(np.all(np.diff(mp.w_ool) > 0))
    dev = np.full(n, np.inf)
    dev[onb] = np.abs(np.interp(w[onb] * tq[onb], mp.P_ool, mp.w_ool) / w[onb] - 1.0)
    follows = increasing and onb.sum() >= 10 and np.mean(dev[onb] < OOL_TOL) >= 0.5
    for k in range(n):
        wk, tk = w[k], tq[k]
        if not valid[k] or wk < 50 * RPM:
            continue
        if tk < 1.0:
            f_idle[k] = min(wk / mp.w_idle, 1.0)
            continue
        nb = [mode[j] for j in (k - 1, k + 1) if 0 <= j < n]
        if follows:
            P_w = np.interp(wk, mp.w_ool, mp.P_ool)  # power on the line at the mean speed
            if dev[k] < OOL_TOL or abs(wk * tk / max(P_w, 1.0) - 1.0) < 0.1:
                # on the line, or two nearby on-line points: the mean speed gives the mean power
                f_on[k], P_on[k] = 1.0, P_w
                continue
        elif (stable[k] and mode[k] == ON) or not any(m in (OFF, IDLE) for m in nb):
            f_on[k], P_on[k] = 1.0, wk * tk
            continue
        w_o = mp.w_idle if IDLE in nb else 0.0
        f, P = _mixture(wk, tk, w_o, mp)
        if f < 0:
            f_on[k] = 1.0
            P_on[k] = np.interp(wk, mp.w_ool, mp.P_ool) if follows else wk * tk
            continue
        f_on[k], P_on[k] = f, P
        if w_o > 0:
            f_idle[k] = 1.0 - f
    return f_on, P_on, f_idle


def _mixture(wk, tk, w_o, mp):
    """(f, P) of a bin mixing the OOL point P (fraction f) with speed w_o at zero torque; (-1, 0) if none."""

    def g(f):
        om = (wk - (1.0 - f) * w_o) / f
        P = tk * om / f
        return om - np.interp(P, mp.P_ool, mp.w_ool), P

    # the root with the largest on-fraction (and a feasible power): scan down from f = 1
    prev_f, prev_g = 1.0, g(1.0)[0]
    lo = hi = -1.0
    for fc in np.linspace(1.0, 0.05, 96)[1:]:
        gc, Pc = g(fc)
        if Pc > mp.P_e_max:
            break
        if gc * prev_g <= 0.0:
            lo, hi = fc, prev_f
            break
        prev_f, prev_g = fc, gc
    if lo < 0:
        return -1.0, 0.0
    glo = g(lo)[0]
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        gm = g(mid)[0]
        if gm * glo > 0:
            lo, glo = mid, gm
        else:
            hi = mid
    f = 0.5 * (lo + hi)
    return f, g(f)[1]


OOL_TOL = 0.005


@dataclass
class LogArrays:
    """One log as numpy arrays on its uniform time base (NaN where not logged)."""

    name: str
    dt: float
    t: np.ndarray
    ch: dict = field(default_factory=dict)  # raw channels (NaN where missing)
    mode: np.ndarray = None
    stable: np.ndarray = None
    P_e: np.ndarray = None  # W
    Q_heat: np.ndarray = None  # W, heat drawn by the heater core (logged or from vent temp)
    T_in: np.ndarray = None  # heater inlet air
    heater_source: str = ""
    f_on: np.ndarray = None  # fraction of each bin with the engine on, at power P_on
    P_on: np.ndarray = None
    f_idle: np.ndarray = None  # fraction of each bin idling

    def has(self, *names) -> bool:
        return all(np.isfinite(self.ch.get(n, np.array([np.nan]))).any() for n in names)


def log_arrays(log, mp) -> LogArrays:
    """Extract the arrays the fitters and the replay need from a :class:`calib.drivelog.DriveLog`."""
    df = log.data
    names = ["speed_mps", "bat_current_A", "bat_voltage_V", "soc", "bat_temp_degC", "engine_speed_rpm",
             "engine_torque_Nm", "fuel_rate_g_per_s", "coolant_temp_degC", "bay_temp_degC",
             "ambient_temp_degC", "cabin_temp_degC", "heater_power_W", "vent_temp_degC",
             "blower_flow_kg_per_s"]
    ch = {n: _col(df, n) for n in names}
    t = df.index.to_numpy(dtype=float)
    la = LogArrays(name=log.label() if hasattr(log, "label") else "log", dt=float(log.dt), t=t, ch=ch)
    n_idle = mp.w_idle / RPM
    la.mode = engine_mode(ch["engine_speed_rpm"], ch["engine_torque_Nm"], n_idle)
    la.stable = stable_mode(la.mode)
    la.P_e = np.where(la.mode == ON, ch["engine_speed_rpm"] * RPM * ch["engine_torque_Nm"], 0.0)
    la.P_e[~np.isfinite(la.P_e)] = np.nan
    la.f_on, la.P_on, la.f_idle = operating_point(ch["engine_speed_rpm"], ch["engine_torque_Nm"], la.mode,
                                                  la.stable, mp)
    T_amb = ch["ambient_temp_degC"]
    T_in = mp.recirc * _fill(ch["cabin_temp_degC"], 0.0) + (1.0 - mp.recirc) * T_amb
    la.T_in = T_in
    if np.isfinite(ch["heater_power_W"]).any():
        la.Q_heat = ch["heater_power_W"].copy()
        la.heater_source = "heater_power_W"
    elif np.isfinite(ch["vent_temp_degC"]).any() and np.isfinite(ch["blower_flow_kg_per_s"]).any():
        la.Q_heat = np.maximum(ch["blower_flow_kg_per_s"] * mp.cp_air * (ch["vent_temp_degC"] - T_in), 0.0)
        la.heater_source = "vent_temp_degC + blower_flow_kg_per_s"
    else:
        la.Q_heat = np.full(t.size, np.nan)
    return la


def first_valid(a, default=np.nan):
    a = np.asarray(a, float)
    i = np.flatnonzero(np.isfinite(a))
    return float(a[i[0]]) if i.size else default


def first_valid_mean(a, n=5, default=np.nan):
    """Mean of the first ``n`` valid samples (less sensitive to noise than one sample)."""
    a = np.asarray(a, float)
    i = np.flatnonzero(np.isfinite(a))
    return float(np.mean(a[i[:n]])) if i.size else default


# --------------------------------------------------------------------------------------------------
# compiled output-error / replay loops
# --------------------------------------------------------------------------------------------------
@njit(cache=True)
def coolant_replay(p, T0, dt, T_amb, W_f, P_e, Q_heat):
    """Coolant temperature (eq. 3) from logged fuel rate, engine power, heater heat and ambient."""
    n = T_amb.shape[0]
    T = np.empty(n)
    T[0] = T0
    for k in range(n - 1):
        d = coolant_flows(p, T[k], T_amb[k], p.LHV * W_f[k], P_e[k], Q_heat[k])[0]
        T[k + 1] = T[k] + dt * d
    return T


@njit(cache=True)
def cabin_replay(p, T0, dt, T_amb, Q_heat):
    """Cabin temperature (eq. 10) from logged heater heat and ambient."""
    n = T_amb.shape[0]
    T = np.empty(n)
    T[0] = T0
    for k in range(n - 1):
        d = cabin_rate(p, T[k], T_amb[k], Q_heat[k])[0]
        T[k + 1] = T[k] + dt * d
    return T


@njit(cache=True)
def fuel_replay(p, mode, P_e, T_cl):
    """Fuel rate (eqs. 4-5) for logged engine modes and powers at given coolant temperatures."""
    n = mode.shape[0]
    W = np.empty(n)
    for k in range(n):
        W[k] = fuel_rate(p, mode[k], P_e[k], T_cl[k]) if mode[k] > 0 else np.nan
    return W


@njit(cache=True)
def full_replay(p, dt, soc0, T_cl0, T_cab0, f_on, P_on, f_idle, P_bat, T_bat, T_amb, Q_heat):
    """SOC, coolant, cabin and fuel rate from logged inputs (the validation simulation)."""
    n = f_on.shape[0]
    soc = np.empty(n)
    T_cl = np.empty(n)
    T_cab = np.empty(n)
    W = np.empty(n)
    soc[0], T_cl[0], T_cab[0] = soc0, T_cl0, T_cab0
    for k in range(n):
        W[k] = f_on[k] * fuel_rate(p, ON, P_on[k], T_cl[k]) + f_idle[k] * fuel_rate(p, IDLE, 0.0, T_cl[k])
        P_e = f_on[k] * P_on[k]
        if k == n - 1:
            break
        I, V, U, R, code = battery(p, soc[k], P_bat[k], T_bat[k])
        if not np.isfinite(I):
            I = P_bat[k] / U
        soc[k + 1] = soc[k] - I * dt / p.C_bat_As
        d_cl = coolant_flows(p, T_cl[k], T_amb[k], p.LHV * W[k], P_e, Q_heat[k])[0]
        T_cl[k + 1] = T_cl[k] + dt * d_cl
        d_cab = cabin_rate(p, T_cab[k], T_amb[k], Q_heat[k])[0]
        T_cab[k + 1] = T_cab[k] + dt * d_cab
    return soc, T_cl, T_cab, W


@njit(cache=True)
def _split_battery_power(p, v, P_e, dt):
    """Battery terminal power from the power split when V and I are not logged."""
    n = v.shape[0]
    P = np.empty(n)
    for k in range(n):
        vn = v[k + 1] if k + 1 < n else v[k]
        Pt = traction_power(p, v[k], vn, 0.0, dt)
        if P_e[k] > 0.0:
            P_em = Pt - p.eta_mech * P_e[k]
            Pbm = P_em / p.eta_em if P_em >= 0.0 else P_em * p.eta_em
        else:
            Pbm = power_split(p, OFF, 0.0, Pt)[1]
        P[k] = Pbm + p.P_aux
    return P


# --------------------------------------------------------------------------------------------------
# replay and metrics
# --------------------------------------------------------------------------------------------------
@dataclass
class Replay:
    """Measured and simulated signals of one log (arrays on the log's time base)."""

    name: str
    t: np.ndarray
    measured: dict
    simulated: dict
    inputs: str = ""

    def metrics(self) -> dict:
        """Per channel RMSE, max abs error, bias (sim - meas) and sample count; cumulative fuel error."""
        out = {}
        for key in CHANNEL_METRICS:
            m, s = self.measured.get(key), self.simulated.get(key)
            if m is None or s is None:
                continue
            ok = np.isfinite(m) & np.isfinite(s)
            if ok.sum() < 2:
                continue
            e = s[ok] - m[ok]
            out[key] = {"rmse": float(np.sqrt(np.mean(e * e))), "max_abs": float(np.max(np.abs(e))),
                        "bias": float(np.mean(e)), "n": int(ok.sum()), "unit": CHANNEL_METRICS[key][1]}
        mf, sf = self.measured.get("fuel_rate"), self.simulated.get("fuel_rate")
        if mf is not None and sf is not None and np.isfinite(mf).sum() > 2:
            dt = float(np.median(np.diff(self.t))) if self.t.size > 1 else 1.0
            cm = float(np.nansum(_fill(mf, 0.0)) * dt)
            cs = float(np.nansum(sf) * dt)
            out["cumulative_fuel"] = {"measured_g": cm, "simulated_g": cs,
                                      "error_pct": 100.0 * (cs - cm) / cm if cm > 0 else float("nan")}
        return out


def replay(log, params) -> Replay:
    """Simulate ``log`` from its logged inputs with ``params`` (a ParameterSet or compiled tuple)."""
    mp = params.model_params() if hasattr(params, "model_params") else params
    la = log_arrays(log, mp)
    c = la.ch
    n = la.t.size
    P_e = la.f_on * la.P_on
    T_amb = _fill(c["ambient_temp_degC"], -10.0)
    T_bat = _fill(c["bat_temp_degC"], mp.T_bat_ref)
    Q_heat = np.maximum(_fill(la.Q_heat, 0.0), 0.0)
    if la.has("bat_current_A", "bat_voltage_V"):
        P_bat = _fill(c["bat_current_A"] * c["bat_voltage_V"], 0.0)
        src = "battery power V*I"
    else:
        P_bat = _split_battery_power(mp, _fill(c["speed_mps"], 0.0), P_e, la.dt)
        src = "battery power from the power split"
    soc0 = first_valid_mean(c["soc"], 5, 0.6)
    T_cl0 = first_valid_mean(c["coolant_temp_degC"], 5, float(T_amb[0]))
    T_cab0 = first_valid_mean(c["cabin_temp_degC"], 5, float(T_amb[0]))
    soc, T_cl, T_cab, W = full_replay(mp, la.dt, soc0, T_cl0, T_cab0, la.f_on, la.P_on, la.f_idle, P_bat, T_bat,
                                      T_amb, Q_heat)
    # a stopped engine burns nothing: zero the fuel-flow reading there (sensor noise clipped at zero
    # would otherwise count as fuel)
    W_meas = np.where((la.f_on + la.f_idle > 0) | ~np.isfinite(c["engine_speed_rpm"]), c["fuel_rate_g_per_s"], 0.0)
    measured = {"soc": c["soc"], "coolant_temp": c["coolant_temp_degC"], "cabin_temp": c["cabin_temp_degC"],
                "fuel_rate": W_meas}
    simulated = {"soc": soc, "coolant_temp": T_cl, "cabin_temp": T_cab, "fuel_rate": W}
    for k in list(measured):
        if not np.isfinite(measured[k]).any():
            measured.pop(k)
    return Replay(la.name, la.t, measured, simulated, inputs=f"{src}; heater from {la.heater_source or 'none'}")


def validate(logs, params) -> dict:
    """Replay every log; returns ``{log label: metrics}`` (see :meth:`Replay.metrics`)."""
    return {r.name: r.metrics() for r in (replay(lg, params) for lg in logs)}


def plot_validation(rep: Replay, path=None, title=None):
    """Measured vs simulated (paper Fig. 3 style): SOC, coolant, cabin, fuel rate and cumulative fuel.

    Written atomically when ``path`` is given (Agg backend). Returns the Figure.
    """
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    t = rep.t / 60.0
    fig, ax = plt.subplots(5, 1, figsize=(8, 11), sharex=True)
    panels = [("soc", "SOC [-]"), ("coolant_temp", "coolant temp. [degC]"), ("cabin_temp", "cabin temp. [degC]"),
              ("fuel_rate", "fuel rate [g/s]")]
    for a, (k, lab) in zip(ax, panels):
        if k in rep.measured:
            a.plot(t, rep.measured[k], "k-", lw=0.8, label="measured")
        if k in rep.simulated:
            a.plot(t, rep.simulated[k], "r--", lw=1.0, label="simulated")
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
    ax[0].legend(loc="best", fontsize=8)
    dt = float(np.median(np.diff(rep.t))) if rep.t.size > 1 else 1.0
    if "fuel_rate" in rep.measured:
        ax[4].plot(t, np.cumsum(_fill(rep.measured["fuel_rate"], 0.0)) * dt, "k-", lw=0.8, label="measured")
    ax[4].plot(t, np.cumsum(np.nan_to_num(rep.simulated["fuel_rate"])) * dt, "r--", lw=1.0, label="simulated")
    ax[4].set_ylabel("cumulative fuel [g]")
    ax[4].set_xlabel("time [min]")
    ax[4].grid(alpha=0.3)
    m = rep.metrics()
    sub = ", ".join(f"{k} RMSE {v['rmse']:.3g}" for k, v in m.items() if "rmse" in v)
    fig.suptitle((title or f"Validation: {rep.name}") + "\n" + sub, fontsize=9)
    fig.tight_layout()
    if path is not None:
        from .fileio import save_figure

        save_figure(fig, path)
    return fig


def plot_residuals(reps, path=None, title=None):
    """Residuals (simulated - measured) of SOC, coolant, cabin temperature and fuel rate, one line per log.

    ``reps`` is a list of ``(label, Replay)``; fitted and held-out logs side by side show whether the fit
    only follows the logs it was fitted on. Written atomically when ``path`` is given. Returns the Figure.
    """
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = [("soc", "SOC [-]"), ("coolant_temp", "coolant [degC]"), ("cabin_temp", "cabin [degC]"),
              ("fuel_rate", "fuel rate [g/s]")]
    fig, ax = plt.subplots(len(panels), 1, figsize=(8, 8.5), sharex=True)
    for i, (label, rep) in enumerate(reps):
        for a, (k, _) in zip(ax, panels):
            m, s = rep.measured.get(k), rep.simulated.get(k)
            if m is None or s is None:
                continue
            a.plot(rep.t / 60.0, s - m, lw=0.7, color=f"C{i}", label=label)
    for a, (_, lab) in zip(ax, panels):
        a.axhline(0.0, color="k", lw=0.6)
        a.set_ylabel("residual " + lab, fontsize=8)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 1.45), ncol=2, frameon=False)
    ax[-1].set_xlabel("time [min]")
    fig.suptitle(title or "residuals: simulated - measured", fontsize=9)
    fig.tight_layout()
    if path is not None:
        from .fileio import save_figure

        save_figure(fig, path)
    return fig


def truth_comparison(params, truth) -> list[dict]:
    """Estimated parameters next to the truth they were simulated from (SYNTHETIC logs only).

    One row per scalar parameter that the calibration estimated or tried (status not ``prior``/``fixed``):
    estimate, standard error, truth, error in % of the truth and in standard errors, and whether the truth
    lies within two standard errors. Tables are summarised by their largest entry error.
    """
    rows = []
    for n in params:
        p = params.param(n)
        if p.status in ("prior", "fixed") or n not in truth:
            continue
        tv = truth.param(n).value
        if p.is_table:
            est, tru = np.asarray(p.value, float), np.asarray(tv, float)
            if est.shape != tru.shape:
                continue
            j = int(np.argmax(np.abs(est - tru)))
            rows.append({"parameter": f"{n} (largest entry error, {p.x_name} {p.x[j]:g})", "estimate": float(est[j]),
                         "stderr": None, "truth": float(tru[j]), "unit": p.unit,
                         "error %": 100.0 * (est[j] - tru[j]) / tru[j] if tru[j] else float("nan"),
                         "error / stderr": None, "status": p.status_text()})
            continue
        se = p.stderr if isinstance(p.stderr, (int, float)) and math.isfinite(p.stderr) and p.stderr > 0 else None
        err = float(p.value) - float(tv)
        rows.append({"parameter": n, "estimate": float(p.value), "stderr": se, "truth": float(tv), "unit": p.unit,
                     "error %": 100.0 * err / float(tv) if tv else float("nan"),
                     "error / stderr": err / se if se else None, "status": p.status_text()})
    return rows
