"""Engine thermal fit (docs/model.md s.5 and s.8) by output error.

- ``kappa``: when a log carries the engine-bay (compartment) temperature, directly from eq. 8,
  ``T_com - T_amb = kappa (T_cl - T_amb)`` (linear least squares through the origin over samples with the
  coolant at least 10 K above ambient). Otherwise fixed: it enters eq. 3 only as ``hA_eng (1 - kappa)``.
- ``C_eng``, ``gamma_exh``, ``hA_eng`` (and ``T_open``, ``k_rad`` when the coolant spent >= 120 s above
  the thermostat): lmfit least squares on the coolant temperature *simulated* from the logged inputs
  (fuel rate -> ``Q_fuel``, engine speed x torque -> ``P_e``, heater power, ambient) by eq. 3 in a compiled
  loop (:func:`calib.fit.validate.coolant_replay`, which calls :func:`calib.model.equations.coolant_flows`), against the
  logged coolant temperature; one residual vector across logs, one initial temperature per log as a
  nuisance parameter. Samples where the coolant was not logged (long gaps) are left out of the residual.
  Standard errors include the calibration uncertainty of the inputs (fuel rate, engine power, heater power:
  1 % each) and of the coolant sensor (0.5 K offset).
"""
from __future__ import annotations

import numpy as np

from calib.fit.toolkit import T_SENSOR_SD, output_error_params, usable_logs, INPUT_REL_SD, KEY_PARAMETERS, ParamEstimate, SubsystemFit, judge, lmfit_identify, not_fitted
from calib.fit.replay import _fill, coolant_replay, first_valid_mean, log_arrays

NEEDS = ("coolant_temp_degC", "fuel_rate_g_per_s", "engine_speed_rpm", "engine_torque_Nm", "ambient_temp_degC")
HEATER = ("heater_power_W",)  # or vent_temp_degC + blower_flow_kg_per_s
PARAMS = ("kappa", "C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K")
MIN_ABOVE_S = 120.0


def fuel_input(la):
    """Logged fuel rate as a heat input, zero where the engine is stopped (speed < 150 rpm): a fuel-flow
    sensor's noise clipped at zero would otherwise add phantom heat while the engine is off."""
    W = np.maximum(_fill(la.ch["fuel_rate_g_per_s"], 0.0), 0.0)
    running = (la.f_on + la.f_idle) > 0
    return np.where(running, W, 0.0)


def _kappa(use, fit, base):
    """kappa from logged bay temperature, or None."""
    xs, ys = [], []
    for lg in use:
        if not lg.has("bay_temp_degC"):
            continue
        d = lg.data
        Tb, Tc, Ta = (d[c].to_numpy(float) for c in ("bay_temp_degC", "coolant_temp_degC", "ambient_temp_degC"))
        ok = np.isfinite(Tb) & np.isfinite(Tc) & np.isfinite(Ta) & (Tc - Ta > 10.0)
        xs.append(Tc[ok] - Ta[ok])
        ys.append(Tb[ok] - Ta[ok])
    if not xs or sum(x.size for x in xs) < 60:
        return None
    from calib.fit.toolkit import inflation

    x, y = np.concatenate(xs), np.concatenate(ys)
    k = float(x @ y / (x @ x))
    res = [yy - k * xx for xx, yy in zip(xs, ys)]
    r = np.concatenate(res)
    se = float(np.sqrt((r @ r) / max(x.size - 1, 1) / (x @ x))) * inflation(res, 1)
    ok, why = judge("kappa", k, se, base.param("kappa").bounds)
    fit.metrics["kappa_samples"] = int(x.size)
    if ok:
        return ParamEstimate("kappa", k, se, "estimated", f"from the engine-bay temperature ({x.size} samples)",
                             prior=float(base["kappa"]))
    return ParamEstimate("kappa", float(base["kappa"]), None, "undetermined", f"engine-bay temperature: {why}",
                         prior=float(base["kappa"]))


def fit_thermal(logs, base, *, allowed=None) -> SubsystemFit:
    """Fit the engine thermal parameters from every log with coolant temperature and the heat inputs.

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
        Priors; ``kappa`` and (for the heater power computed from vent temperature) ``W_bl``, ``recirc``.
    allowed : set of str, optional

    Returns
    -------
    SubsystemFit
    """
    allowed = set(PARAMS) if allowed is None else set(allowed)
    fit = SubsystemFit("thermal", NEEDS + HEATER)
    names = [n for n in PARAMS if n in allowed]
    if not names:
        return fit
    use, fit.skipped = usable_logs(logs, NEEDS, fit.subsystem,
                                   any_of=(("heater_power_W",), ("vent_temp_degC", "blower_flow_kg_per_s")))
    if not use:
        return not_fitted(fit, base, names, "engine thermal parameters not fitted: no log has coolant temperature, "
                          "fuel rate, engine speed/torque, heater power and ambient temperature ("
                          + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
    fit.logs = [lg.label() for lg in use]
    work = base
    if "kappa" in allowed:
        ke = _kappa(use, fit, base)
        if ke is None:
            fit.estimates["kappa"] = ParamEstimate(
                "kappa", float(base["kappa"]), None, "prior",
                "not fitted: no log carries the engine-bay temperature; kappa enters the coolant equation only as "
                "hA_eng (1 - kappa), so it stays at its prior", prior=float(base["kappa"]))
        else:
            fit.estimates["kappa"] = ke
            if ke.status == "estimated":
                work = base.with_values(kappa=ke.value)
    kappa_known = "kappa" in fit.estimates and fit.estimates["kappa"].status == "estimated"
    mp0 = work.model_params()
    data = []
    for i, lg in enumerate(use):
        la = log_arrays(lg, mp0)
        c = la.ch
        T = c["coolant_temp_degC"]
        data.append(dict(T=T, ok=np.isfinite(T), dt=la.dt, T_amb=_fill(c["ambient_temp_degC"], 0.0),
                         W=fuel_input(la),
                         P=_fill(la.f_on * la.P_on, 0.0), Q=np.maximum(_fill(la.Q_heat, 0.0), 0.0),
                         T0=first_valid_mean(T, 5, 0.0), name=f"T0_{i}"))
    Tmax = max(float(np.nanmax(d["T"])) for d in data)
    fit.metrics["coolant_max_degC"] = Tmax
    cand = [n for n in ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K")
            if n in allowed]
    pre = {}
    T_open0 = float(work["T_open_degC"])
    above = sum(float(np.sum(d["T"][d["ok"]] > T_open0 - 5.0)) * d["dt"] for d in data)
    for n in ("T_open_degC", "k_rad_W_per_K"):
        if n in cand and above < MIN_ABOVE_S:
            pre[n] = (f"coolant never reached the thermostat: {above:.0f} s within 5 K of its prior opening "
                      f"temperature (max {Tmax:.1f} degC), need {MIN_ABOVE_S:.0f} s; undetermined, left at prior")
    bnd = {n: work.param(n).bounds for n in cand}
    prior = {n: float(work[n]) for n in cand}

    make_params = output_error_params(cand, bnd, prior, data)

    def sims(ps, sW=1.0, sP=1.0, sQ=1.0):
        v = ps.valuesdict()
        mp = mp0._replace(C_eng=float(v.get("C_eng_J_per_K", mp0.C_eng)),
                          gamma_exh=float(v.get("gamma_exh", mp0.gamma_exh)),
                          hA_eng=float(v.get("hA_eng_W_per_K", mp0.hA_eng)),
                          T_open=float(v.get("T_open_degC", mp0.T_open)),
                          k_rad=float(v.get("k_rad_W_per_K", mp0.k_rad)))
        return [coolant_replay(mp, float(v[d["name"]]), d["dt"], d["T_amb"], sW * d["W"], sP * d["P"],
                               sQ * d["Q"]) for d in data]

    def segments(ps, dT=0.0, **scale):
        return [(s - d["T"] - dT)[d["ok"]] for s, d in zip(sims(ps, **scale), data)]

    def residual(ps):
        return np.concatenate(segments(ps))

    u = 1.0 + INPUT_REL_SD
    perturbed = [lambda ps, k=k: np.concatenate(segments(ps, **{k: u})) for k in ("sW", "sP", "sQ")]
    perturbed.append(lambda ps: np.concatenate(segments(ps, dT=T_SENSOR_SD)))
    out = lmfit_identify(make_params, residual, cand, bounds=bnd, segments=segments, fixed_reason=pre,
                         conf_keys=KEY_PARAMETERS, perturbed=perturbed)
    res = out["result"]
    # thermostat: also require time above the *fitted* opening temperature
    if "T_open_degC" in out["vary"]:
        To = out["values"]["T_open_degC"]
        t_above = sum(float(np.sum(d["T"][d["ok"]] > To + 1.0)) * d["dt"] for d in data)
        fit.metrics["time_above_thermostat_s"] = t_above
        if t_above < MIN_ABOVE_S:
            why = (f"coolant above the fitted thermostat opening ({To:.1f} degC) for only {t_above:.0f} s "
                   f"< {MIN_ABOVE_S:.0f} s")
            # they stay free in this fit (nuisance), so the others are not biased by their priors
            for n in ("T_open_degC", "k_rad_W_per_K"):
                if n in out["vary"]:
                    out["vary"].remove(n)
                    out["undetermined"][n] = why
    r = residual(res.params)
    fit.metrics.update(rmse_degC=float(np.sqrt(np.mean(r ** 2))), samples=int(r.size), n_eff=out["n_eff"],
                       se_inflation=out["factor"])
    fit.correlations = out["correl"]
    fit.conf_intervals = out["conf"]
    fit.nuisance = {d["name"]: float(res.params[d["name"]].value) for d in data}
    und = out["undetermined"]
    for n in cand:
        if n in out["vary"]:
            note = f"output-error fit of the coolant temperature over {len(use)} log(s)"
            if n == "hA_eng_W_per_K" and not kappa_known:
                note = (f"identified only as hA_eng (1 - kappa) = {out['values'][n] * (1 - mp0.kappa):.4g} W/K; "
                        f"kappa not logged, this value assumes kappa = {mp0.kappa:g} (its prior)")
            fit.estimates[n] = ParamEstimate(n, out["values"][n], out["stderr"][n], "estimated", note, prior=prior[n])
        else:
            fit.estimates[n] = ParamEstimate(n, prior[n], None, "undetermined", und.get(n, ""), prior=prior[n])
    return fit
