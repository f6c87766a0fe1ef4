"""Engine thermal fit (docs/model.md s.5 and s.8) by output error, maximum a posteriori.

- ``kappa``: when a log carries the engine-bay (compartment) temperature, directly from eq. 8,
  ``T_com - T_amb = kappa (T_cl - T_amb)`` (linear least squares through the origin over samples with the
  coolant more than 10 K above ambient), combined with its prior. Otherwise its prior: it enters eq. 3 only
  as ``hA_eng (1 - kappa)``.
- ``C_eng``, ``gamma_exh``, ``hA_eng``, ``T_open``, ``k_rad``: :func:`calib.fit.toolkit.map_fit` on the
  coolant temperature *simulated* from the logged inputs (fuel rate -> ``Q_fuel``; engine power from speed x
  torque, the logged engine power or the power balance; heater heat logged, from vent temperature and
  blower flow, or from the cabin balance: :func:`calib.fit.replay.log_arrays`; ambient) by eq. 3 in a
  compiled loop (:func:`calib.fit.replay.coolant_replay`, which calls
  :func:`calib.model.equations.coolant_flows`), against the logged coolant temperature; one residual vector
  across logs, one initial temperature per log as a nuisance parameter. Samples where the coolant was not
  logged are left out. A log whose coolant never nears the thermostat leaves ``T_open`` and ``k_rad`` at
  their prior (the posterior equals it), and the note says so. The posterior sd includes the calibration
  uncertainty of the inputs (fuel rate, engine power, heater power: 1 % each) and of the coolant sensor
  (0.5 K offset).
"""
from __future__ import annotations

import numpy as np

from calib.fit.toolkit import (T_SENSOR_SD, INPUT_REL_SD, ParamEstimate, SubsystemFit, combine_with_prior, confounded_pairs, map_fit, not_fitted,
                               output_error_params, posterior_estimate)
from calib.fit.replay import _fill, coolant_replay, first_valid_mean, log_arrays

#: Channels every log of the fit needs; the engine power and the heater heat come in several ways
#: (:func:`calib.fit.replay.log_arrays`).
NEEDS = ("coolant_temp_degC", "fuel_rate_g_per_s", "ambient_temp_degC")
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
    fit.metrics["kappa_samples"] = int(x.size)
    from calib.model.params import prior_sd_of

    return combine_with_prior("kappa", k, se, float(base["kappa"]), float(prior_sd_of(base.param("kappa"))),
                              f"from the engine-bay temperature ({x.size} samples)")


def fit_thermal(logs, base, *, allowed=None) -> SubsystemFit:
    """Fit the engine thermal parameters (maximum a posteriori) from every log with coolant temperature,
    ambient temperature, fuel rate, an engine power (logged or inferred) and a heater heat (logged,
    from vent temperature and blower flow, or inferred from the cabin balance).

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
        Priors (values and ``prior_sd``); ``kappa`` and the heater/cabin parameters used to derive inputs.
    allowed : set of str, optional

    Returns
    -------
    SubsystemFit
    """
    from calib.model.params import prior_sd_of

    allowed = set(PARAMS) if allowed is None else set(allowed)
    fit = SubsystemFit("thermal", NEEDS)
    names = [n for n in PARAMS if n in allowed]
    if not names:
        return fit
    mp_b = base.model_params()
    use = []
    for lg in logs:
        miss = lg.missing(NEEDS)
        la = None
        if not miss:
            la = log_arrays(lg, mp_b)
            if not la.engine_source:
                miss.append("engine power (engine_speed_rpm + engine_torque_Nm, or engine_power_W, or speed_mps "
                            "with battery power)")
            if not la.heater_source:
                miss.append("heater heat (heater_power_W, or vent_temp_degC + blower_flow_kg_per_s, or "
                            "cabin_temp_degC to infer it)")
        if miss:
            fit.skipped[lg.label()] = f"missing channel(s) {', '.join(miss)}"
        else:
            use.append((lg, la))
    if not use:
        return not_fitted(fit, base, names, "engine thermal parameters not fitted: no log has coolant temperature, "
                          "fuel rate, ambient temperature, an engine power and a heater heat ("
                          + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
    fit.logs = [lg.label() for lg, _ in use]
    for lg, la in use:
        fit.used[lg.label()] = {"engine power": la.engine_source, "heater heat": la.heater_source,
                                "fuel heat": "fuel_rate_g_per_s", **{f"inferred {k}": v for k, v in la.inferred.items()}}
    work = base
    if "kappa" in allowed:
        ke = _kappa([lg for lg, _ in use], fit, base)
        if ke is None:
            fit.estimates["kappa"] = ParamEstimate(
                "kappa", float(base["kappa"]), float(prior_sd_of(base.param("kappa"))), "weak",
                "no log carries the engine-bay temperature; kappa enters the coolant equation only as "
                "hA_eng (1 - kappa), so it is the prior", prior=float(base["kappa"]),
                prior_sd=float(prior_sd_of(base.param("kappa"))), informed=0.0)
        else:
            fit.estimates["kappa"] = ke
            if ke.status == "estimated":
                work = base.with_values(kappa=ke.value)
    kappa_known = "kappa" in fit.estimates and fit.estimates["kappa"].status == "estimated"
    mp0 = work.model_params()
    data = []
    for i, (_lg, la) in enumerate(use):
        c = la.ch
        T = c["coolant_temp_degC"]
        data.append(dict(T=T, ok=np.isfinite(T), dt=la.dt, T_amb=_fill(c["ambient_temp_degC"], 0.0),
                         W=fuel_input(la),
                         P=_fill(la.f_on * la.P_on, 0.0), Q=np.maximum(_fill(la.Q_heat, 0.0), 0.0),
                         heater_on=_fill(la.Q_heat, 0.0) > 200.0,
                         T0=first_valid_mean(T, 5, 0.0), name=f"T0_{i}"))
    Tmax = max(float(np.nanmax(d["T"])) for d in data)
    fit.metrics["coolant_max_degC"] = Tmax
    cand = [n for n in ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K")
            if n in allowed]
    T_open0 = float(work["T_open_degC"])
    above = sum(float(np.sum(d["T"][d["ok"]] > T_open0 - 5.0)) * d["dt"] for d in data)
    off_s = sum(float(np.sum(~d["heater_on"] & d["ok"] & (d["T"] > d["T_amb"] + 20))) * d["dt"] for d in data)
    fit.metrics.update(time_near_thermostat_s=above, heater_off_warm_s=off_s)
    bnd = {n: work.param(n).bounds for n in cand}
    prior = {n: float(work[n]) for n in cand}
    psd = {n: float(prior_sd_of(work.param(n))) for n in cand}

    make = output_error_params(cand, bnd, prior, data)

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

    # the replay is not affine in its inputs (thermostat, heater-core limit): central differences
    perturbed = [(lambda ps, k=k: segments(ps, **{k: 1.0 + INPUT_REL_SD}),
                  lambda ps, k=k: segments(ps, **{k: 1.0 - INPUT_REL_SD})) for k in ("sW", "sP", "sQ")]
    perturbed.append(lambda ps: segments(ps, dT=T_SENSOR_SD))
    out = map_fit(lambda: make(set(cand)), segments, cand, prior=prior, prior_sd=psd, noise_sd=T_SENSOR_SD,
                  perturbed=perturbed, floor=0.05)
    res = out["params"]
    fit.metrics.update(rmse_degC=out["rmse"], samples=int(out["n"]), n_eff=out["n_eff"],
                       noise_sd_degC=out["noise_sd"])
    fit.correlations = out["correl"]
    fit.confounded = confounded_pairs(out["correl"])
    fit.nuisance = {d["name"]: float(res[d["name"]].value) for d in data}
    for n in cand:
        note = f"MAP fit of the coolant temperature over {len(use)} log(s)"
        if n == "hA_eng_W_per_K" and not kappa_known:
            note = (f"identified only as hA_eng (1 - kappa) = {out['values'][n] * (1 - mp0.kappa):.4g} W/K; "
                    f"kappa not logged, this value assumes kappa = {mp0.kappa:g} (its prior)")
        if n in ("T_open_degC", "k_rad_W_per_K") and above < MIN_ABOVE_S:
            note = (f"coolant never reached the thermostat ({above:.0f} s within 5 K of its prior opening, max "
                    f"{Tmax:.1f} degC): the value comes from the prior")
        fit.estimates[n] = posterior_estimate(n, out, note, prior[n])
    return fit
