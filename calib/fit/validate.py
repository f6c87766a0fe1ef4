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

A channel whose inputs the log lacks is not simulated: :func:`replay` names the missing channel in
``Replay.refused`` and no metric is computed for it; inputs inferred from a balance (engine power,
battery power, heater heat) are named in ``Replay.inferred``. :func:`diagnostics` gives per-channel
residual statistics (autocorrelation, error by regime) and :func:`plot_residuals` draws them.

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

from calib.plotting import plot_residual_comparison, plot_residuals, plot_validation  # noqa: F401 - re-exported
from calib.fit.replay import (CHANNEL_METRICS, HEATER_OFF, _fill, _split_battery_power, fill_short, first_valid_mean,
                              fuel_replay, full_replay, log_arrays)

#: Window (s) at the start of a log over which the replay's initial SOC is matched to the logged SOC.
SOC0_WINDOW_S = 60.0


@dataclass
class Replay:
    """Measured and simulated signals of one log (arrays on the log's time base)."""

    name: str
    t: np.ndarray
    measured: dict
    simulated: dict
    inputs: str = ""
    refused: dict = field(default_factory=dict)  # channel -> why it was not simulated
    inferred: dict = field(default_factory=dict)  # input -> how it was inferred
    regimes: dict = field(default_factory=dict)  # regime name -> boolean mask

    def plot(self, path=None, title=None):
        """Measured vs simulated, paper Fig. 3 style (:func:`calib.plotting.plot_validation`). Returns the
        Figure."""
        return plot_validation(self, path, title)

    def cumulative_fuel(self):
        """Cumulative measured and simulated fuel (g) per row, both summed over the same rows (the measured
        rate bridged across its short gaps only, the simulated one where the engine state is known): a row
        neither knows adds nothing to either. None when the log has no fuel rate."""
        mf, sf = self.measured.get("fuel_rate"), self.simulated.get("fuel_rate")
        if mf is None or sf is None:
            return None
        dt = float(np.median(np.diff(self.t))) if self.t.size > 1 else 1.0
        mfill = fill_short(np.asarray(mf, float), dt)
        ok = np.isfinite(mfill) & np.isfinite(sf)
        return np.cumsum(np.where(ok, mfill, 0.0)) * dt, np.cumsum(np.where(ok, sf, 0.0)) * dt

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
            # both totals over the same bins: the measured rate bridged across its short gaps only, and the
            # simulated one where the engine state is known (a long gap is neither fuel nor no fuel)
            mfill = fill_short(mf, dt)
            ok = np.isfinite(mfill) & np.isfinite(sf)
            cm = float(np.sum(mfill[ok]) * dt)
            cs = float(np.sum(sf[ok]) * dt)
            out["cumulative_fuel"] = {"measured_g": cm, "simulated_g": cs,
                                      "error_pct": 100.0 * (cs - cm) / cm if cm > 0 else float("nan"),
                                      "compared_s": float(ok.sum() * dt), "left_out_s": float((~ok).sum() * dt)}
        return out


def replay(log, params, heater=None) -> Replay:
    """Simulate ``log`` from its logged inputs with ``params`` (a ParameterSet or compiled tuple).

    A channel whose inputs the log lacks is *not* simulated: it is left out of ``simulated`` and
    ``refused`` names the missing channel(s). Inputs inferred from a balance are named in ``inferred``.
    ``heater`` as for :func:`calib.fit.replay.log_arrays` (``"off"``: a heater heat not logged is zero).
    The simulation runs through bins whose inputs are unknown (a long gap of a sparse channel: bridged for
    the state only); those bins' simulated outputs are NaN, so no metric counts them, and ``inferred``
    names how long they are.
    """
    mp = params.model_params() if hasattr(params, "model_params") else params
    la = log_arrays(log, mp, heater=heater)
    c = la.ch
    refused, inferred = {}, dict(la.inferred)
    P_e = la.f_on * la.P_on
    amb = la.has("ambient_temp_degC")
    T_amb = _fill(c["ambient_temp_degC"], -10.0)
    T_bat = _fill(c["bat_temp_degC"], mp.T_bat_ref)
    Q_heat = np.maximum(_fill(la.Q_heat, 0.0), 0.0)
    if la.battery_source:
        P_bat = _fill(la.P_bat, 0.0)
        src = f"battery power from {la.battery_source}"
    elif la.engine_source and la.has("speed_mps"):
        P_bat = _split_battery_power(mp, _fill(c["speed_mps"], 0.0), P_e, la.dt)
        src = "battery power from the power split"
        inferred["battery power"] = "power split of the logged speed and the engine power"
    else:
        P_bat = np.zeros(la.t.size)
        src = "no battery power"
        refused["soc"] = ("missing channel(s) bat_power_W (or bat_voltage_V + bat_current_A, or speed_mps with an "
                          "engine power)")
    no_engine = ("missing channel(s) engine_speed_rpm + engine_torque_Nm (or engine_power_W, or speed_mps with "
                 "battery power): the engine on/off and power are replay inputs")
    if not la.engine_source:
        refused["fuel_rate"] = no_engine
        refused["coolant_temp"] = no_engine
    if not amb:
        for k in ("coolant_temp", "cabin_temp"):
            refused.setdefault(k, "missing channel ambient_temp_degC")
    if not la.heater_source:
        why = ("missing channel(s) heater_power_W (or vent_temp_degC + blower_flow_kg_per_s, or cabin_temp_degC "
               "to infer it" + (", which heater='estimate' does not" if heater == "estimate" else "")
               + "; heater='off' declares it zero)")
        refused.setdefault("coolant_temp", why)
        refused.setdefault("cabin_temp", why)
    elif la.heater_source.startswith("inferred"):
        refused.setdefault("cabin_temp", "the heater heat was inferred from the cabin temperature itself: comparing "
                                         "the simulated cabin with it would check nothing")
    soc0 = first_valid_mean(c["soc"], 5, 0.6)
    T_cl0 = first_valid_mean(c["coolant_temp_degC"], 5, float(T_amb[0]))
    T_cab0 = first_valid_mean(c["cabin_temp_degC"], 5, float(T_amb[0]))
    soc, T_cl, T_cab, W = full_replay(mp, la.dt, soc0, T_cl0, T_cab0, la.f_on, la.P_on, la.f_idle, P_bat, T_bat,
                                      T_amb, Q_heat, f_cat=la.f_cat)
    # the initial SOC: the mean of the first samples is biased when the SOC moves at once (a cold start
    # charging hard) and a quantised reading is off by up to half a step; the offset that makes the
    # simulated SOC match the logged one over the first SOC0_WINDOW_S is the better initial state
    e0 = (c["soc"] - soc)[: max(int(round(SOC0_WINDOW_S / la.dt)), 1)]
    if np.isfinite(e0).sum() >= 5:
        soc0 += float(np.nanmean(e0))
        soc, T_cl, T_cab, W = full_replay(mp, la.dt, soc0, T_cl0, T_cab0, la.f_on, la.P_on, la.f_idle, P_bat, T_bat,
                                          T_amb, Q_heat, f_cat=la.f_cat)
    # bins whose inputs are unknown (a long gap of a sparse channel): simulated through, never compared
    unknown = ~la.known if la.engine_source else np.zeros(la.t.size, bool)
    for arr, needed in ((la.P_bat, bool(la.battery_source)), (la.Q_heat, bool(la.heater_source)),
                        (fill_short(c["ambient_temp_degC"], la.dt), amb)):
        if needed:
            unknown |= ~np.isfinite(arr)
    if unknown.any() and not unknown.all():
        inferred["bins with an unknown input"] = (f"{int(unknown.sum()) * la.dt:.0f} s where an input (engine state, "
                                                  "battery power, heater heat or ambient) has no sample within its "
                                                  "short-gap limit: simulated through, not compared")
    fuel_note = ""
    if "coolant_temp" in refused and "fuel_rate" not in refused:
        if la.has("coolant_temp_degC"):  # the cold correction then reads the measured coolant
            T_m = _fill(c["coolant_temp_degC"], 20.0)
            W = la.f_on * fuel_replay(mp, np.full(la.t.size, 3, np.int64), la.P_on, T_m) \
                + la.f_idle * fuel_replay(mp, np.full(la.t.size, 2, np.int64), np.zeros(la.t.size), T_m)
            fuel_note = "fuel rate with the measured coolant temperature (the coolant could not be simulated)"
            inferred["coolant for the fuel rate"] = "measured coolant temperature"
        else:
            refused["fuel_rate"] = "the coolant temperature can be neither simulated nor read: " + refused["coolant_temp"]
    # a stopped engine burns nothing: zero the fuel-flow reading there (sensor noise clipped at zero
    # would otherwise count as fuel)
    stopped = (la.f_on + la.f_idle == 0) & (la.mode > 0) if la.engine_source else np.zeros(la.t.size, bool)
    # (only where the log has a fuel channel: zeros put into a missing one would be scored as a perfect fit)
    W_meas = c["fuel_rate_g_per_s"]
    if np.isfinite(W_meas).any():
        W_meas = np.where(stopped, 0.0, W_meas)
    measured = {"soc": c["soc"], "coolant_temp": c["coolant_temp_degC"], "cabin_temp": c["cabin_temp_degC"],
                "fuel_rate": W_meas}
    simulated = {"soc": soc, "coolant_temp": T_cl, "cabin_temp": T_cab, "fuel_rate": W}
    if unknown.any():
        simulated = {k: np.where(unknown, np.nan, v) for k, v in simulated.items()}
    for k in list(measured):
        if not np.isfinite(measured[k]).any():
            measured.pop(k)
            refused.pop(k, None)
    for k in refused:
        simulated.pop(k, None)
    inputs = (f"{src}; engine from {la.engine_source or 'nothing'}; heater from "
              f"{'nothing (declared off)' if la.heater_source == HEATER_OFF else la.heater_source or 'nothing'}"
              + (f"; {fuel_note}" if fuel_note else ""))
    rep = Replay(la.name, la.t, measured, simulated, inputs=inputs, refused=refused, inferred=inferred)
    rep.regimes = {"engine on": (la.f_on + la.f_idle) > 0, "engine off": (la.f_on + la.f_idle) == 0,
                   "coolant cold (< 60 degC)": _fill(c["coolant_temp_degC"], 0.0) < 60.0,
                   "coolant warm (>= 60 degC)": _fill(c["coolant_temp_degC"], 0.0) >= 60.0,
                   "heater on": Q_heat > 200.0, "heater off": Q_heat <= 200.0}
    if not la.has("coolant_temp_degC"):
        for k in ("coolant cold (< 60 degC)", "coolant warm (>= 60 degC)"):
            rep.regimes.pop(k)
    if not la.heater_source:
        for k in ("heater on", "heater off"):
            rep.regimes.pop(k)
    if not la.engine_source:
        for k in ("engine on", "engine off"):
            rep.regimes.pop(k)
    return rep


def validate(logs, params, heater=None) -> dict:
    """Replay every log; returns ``{log label: metrics}`` (see :meth:`Replay.metrics`), with ``refused``
    (channel -> why it was not checked) and ``inferred`` (input -> how) where there are any. ``heater`` as
    for :func:`replay`."""
    out = {}
    for lg in logs:
        r = replay(lg, params, heater=heater)
        m = r.metrics()
        if r.refused:
            m["refused"] = dict(r.refused)
        if r.inferred:
            m["inferred"] = dict(r.inferred)
        out[r.name] = m
    return out


def diagnostics(rep: Replay, lags=(1, 10, 60)) -> dict:
    """Residual diagnostics per simulated channel: RMSE, bias, residual autocorrelation at ``lags`` (s), the
    number of effectively independent residuals, and RMSE/bias by regime (engine on/off, coolant cold/warm,
    heater on/off)."""
    from calib.fit.toolkit import neff

    dt = float(np.median(np.diff(rep.t))) if rep.t.size > 1 else 1.0
    out = {}
    for key, (_col_name, unit) in CHANNEL_METRICS.items():
        m, s = rep.measured.get(key), rep.simulated.get(key)
        if m is None or s is None:
            continue
        e = s - m
        ok = np.isfinite(e)
        if ok.sum() < 10:
            continue
        r = e[ok]
        r0 = r - r.mean()
        den = float(r0 @ r0)
        acf = {}
        for lag in lags:
            k = int(round(lag / dt))
            if 0 < k < r0.size and den > 0:
                acf[f"{lag}s"] = float(r0[k:] @ r0[:-k] / den)
        n, ne = neff([r])
        d = {"unit": unit, "rmse": float(np.sqrt(np.mean(r * r))), "bias": float(r.mean()), "n": int(r.size),
             "n_eff": float(ne), "autocorrelation": acf, "by_regime": {}}
        for name, mask in rep.regimes.items():
            mk = ok & mask
            if mk.sum() >= 10:
                d["by_regime"][name] = {"rmse": float(np.sqrt(np.mean(e[mk] ** 2))), "bias": float(np.mean(e[mk])),
                                        "n": int(mk.sum())}
        out[key] = d
    return out








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
