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

from calib.fit.replay import (CHANNEL_METRICS, _fill, _split_battery_power, first_valid_mean, fuel_replay, full_replay,
                              log_arrays)

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
    """Simulate ``log`` from its logged inputs with ``params`` (a ParameterSet or compiled tuple).

    A channel whose inputs the log lacks is *not* simulated: it is left out of ``simulated`` and
    ``refused`` names the missing channel(s). Inputs inferred from a balance are named in ``inferred``.
    """
    mp = params.model_params() if hasattr(params, "model_params") else params
    la = log_arrays(log, mp)
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
               "to infer it)")
        refused.setdefault("coolant_temp", why)
        refused.setdefault("cabin_temp", why)
    elif la.heater_source.startswith("inferred"):
        refused.setdefault("cabin_temp", "the heater heat was inferred from the cabin temperature itself: comparing "
                                         "the simulated cabin with it would check nothing")
    soc0 = first_valid_mean(c["soc"], 5, 0.6)
    T_cl0 = first_valid_mean(c["coolant_temp_degC"], 5, float(T_amb[0]))
    T_cab0 = first_valid_mean(c["cabin_temp_degC"], 5, float(T_amb[0]))
    soc, T_cl, T_cab, W = full_replay(mp, la.dt, soc0, T_cl0, T_cab0, la.f_on, la.P_on, la.f_idle, P_bat, T_bat,
                                      T_amb, Q_heat)
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
    W_meas = np.where(stopped, 0.0, c["fuel_rate_g_per_s"])
    measured = {"soc": c["soc"], "coolant_temp": c["coolant_temp_degC"], "cabin_temp": c["cabin_temp_degC"],
                "fuel_rate": W_meas}
    simulated = {"soc": soc, "coolant_temp": T_cl, "cabin_temp": T_cab, "fuel_rate": W}
    for k in list(measured):
        if not np.isfinite(measured[k]).any():
            measured.pop(k)
            refused.pop(k, None)
    for k in refused:
        simulated.pop(k, None)
    inputs = (f"{src}; engine from {la.engine_source or 'nothing'}; heater from {la.heater_source or 'nothing'}"
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


def validate(logs, params) -> dict:
    """Replay every log; returns ``{log label: metrics}`` (see :meth:`Replay.metrics`), with ``refused``
    (channel -> why it was not checked) and ``inferred`` (input -> how) where there are any."""
    out = {}
    for lg in logs:
        r = replay(lg, params)
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


def plot_residuals(rep: Replay, path=None, title=None):
    """Per simulated channel: measured vs simulated, residual over time, residual autocorrelation.
    Written atomically when ``path`` is given. Returns the Figure."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    keys = [k for k in CHANNEL_METRICS if k in rep.measured and k in rep.simulated]
    fig, ax = plt.subplots(max(len(keys), 1), 3, figsize=(12, 2.6 * max(len(keys), 1)), squeeze=False)
    t = rep.t / 60.0
    for i, k in enumerate(keys):
        m, s = rep.measured[k], rep.simulated[k]
        ok = np.isfinite(m) & np.isfinite(s)
        unit = CHANNEL_METRICS[k][1]
        a = ax[i, 0]
        a.plot(m[ok], s[ok], ".", ms=1.5, alpha=0.5)
        lo, hi = float(np.nanmin(m[ok])), float(np.nanmax(m[ok]))
        a.plot([lo, hi], [lo, hi], "k-", lw=0.8)
        a.set_xlabel(f"measured {k} [{unit}]")
        a.set_ylabel("simulated")
        a = ax[i, 1]
        a.plot(t[ok], (s - m)[ok], "-", lw=0.6)
        a.axhline(0, color="k", lw=0.6)
        a.set_ylabel(f"residual [{unit}]")
        a.set_xlabel("time [min]")
        a = ax[i, 2]
        r = (s - m)[ok]
        r = r - r.mean()
        nl = min(300, max(r.size // 3, 2))
        den = float(r @ r) or 1.0
        acf = [1.0] + [float(r[j:] @ r[:-j] / den) for j in range(1, nl)]
        a.plot(np.arange(nl), acf, "-")
        a.axhline(0, color="k", lw=0.6)
        a.set_xlabel("lag [samples]")
        a.set_ylabel("residual ACF")
    if rep.refused:
        fig.text(0.01, 0.005, "not checked: " + "; ".join(f"{k} ({v})" for k, v in rep.refused.items())[:220],
                 fontsize=7)
    fig.suptitle(title or f"Residual diagnostics: {rep.name}", fontsize=9)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    if path is not None:
        from calib.fileio import save_figure

        save_figure(fig, path)
    return fig


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
    if "fuel_rate" in rep.simulated:
        ax[4].plot(t, np.cumsum(np.nan_to_num(rep.simulated["fuel_rate"])) * dt, "r--", lw=1.0, label="simulated")
    for a, (k, _lab) in zip(ax, panels + [("fuel_rate", "")]):
        if k in rep.refused:
            a.text(0.5, 0.5, f"not simulated: {rep.refused[k]}"[:110], transform=a.transAxes, ha="center",
                   fontsize=7, color="r")
    ax[4].set_ylabel("cumulative fuel [g]")
    ax[4].set_xlabel("time [min]")
    ax[4].grid(alpha=0.3)
    m = rep.metrics()
    sub = ", ".join(f"{k} RMSE {v['rmse']:.3g}" for k, v in m.items() if "rmse" in v)
    fig.suptitle((title or f"Validation: {rep.name}") + "\n" + sub, fontsize=9)
    fig.tight_layout()
    if path is not None:
        from calib.fileio import save_figure

        save_figure(fig, path)
    return fig


def plot_residual_comparison(reps, path=None, title=None):
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
        from calib.fileio import save_figure

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
