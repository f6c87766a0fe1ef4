"""Cabin and heater-core fit (docs/model.md s.6 and s.8).

- ``C_cab``, ``UA_cab``, ``Q_sun``: output error, maximum a posteriori (:func:`calib.fit.toolkit.map_fit`).
  The cabin temperature is simulated from the logged heater
  heat and ambient temperature by eq. 10 in a compiled loop (:func:`calib.fit.validate.cabin_replay`, which
  calls :func:`calib.model.equations.cabin_rate`) and matched to the logged cabin temperature with lmfit (one
  residual vector across logs, one initial cabin temperature per log as a nuisance parameter). Standard
  errors include the calibration uncertainty of the heater power (1 %) and of the cabin sensor (0.5 K). The heater
  heat is the logged heater power, or ``W_bl c_p (T_vent - T_in)`` from vent temperature and blower flow.
- ``eps_hc``: from vent temperature, coolant temperature and blower flow where the heater-core limit
  binds. There ``T_vent - T_in = eps_hc (T_cl - T_in)``; elsewhere the ratio
  ``r = (T_vent - T_in) / (T_cl - T_in)`` is below ``eps_hc``. The binding samples are the upper cluster of
  ``r``: starting from its 90th percentile, samples within 3 noise sd (1 degC quantisation of both
  temperatures) below the current estimate are taken as binding and ``eps_hc`` re-estimated by least
  squares through the origin, until it settles. At least 60 binding samples with ``T_cl - T_in >= 10 K``
  are needed. The standard error includes a 0.5 K offset uncertainty of the coolant and vent sensors; the
  estimate is combined with the prior (precision weighting). A heater heat inferred from the cabin
  balance is never used here (it would be circular).

Sparse inputs: the heater heat and the ambient are bridged across short gaps only
(:func:`calib.fit.replay.fill_short`); a bin where either is unknown is left out and the replay restarts
after it from its own initial cabin temperature (:func:`calib.fit.replay.input_segments`). With
``heater="off"`` a log with cabin and ambient temperature but no heater channel is fitted with the heater
declared off (zero heat), and ``used`` says so.
"""
from __future__ import annotations

import numpy as np

from calib.fit.toolkit import (T_SENSOR_SD, INPUT_REL_SD, MIN_SAMPLES, SubsystemFit, combine_with_prior, confounded_pairs, inflation,
                               map_fit, not_fitted, output_error_params, posterior_estimate, prior_only, usable_logs)
from calib.model.params import compiled_with, prior_sd_of
from calib.fit.replay import HEATER_OFF, cabin_replay, fill_short, first_valid_mean, input_segments, log_arrays

NEEDS = ("cabin_temp_degC", "ambient_temp_degC")  # + heater_power_W or vent_temp_degC + blower_flow_kg_per_s
NEEDS_EPS = ("vent_temp_degC", "coolant_temp_degC", "blower_flow_kg_per_s", "ambient_temp_degC")
PARAMS = ("C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W", "eps_hc")


def _eps(use, base, fit, dT_cl=0.0, dT_vent=0.0, _propagate=True):
    mp = base.model_params()
    xs, ys = [], []
    for lg in use:
        if not lg.has(*NEEDS_EPS):
            continue
        la = log_arrays(lg, mp)
        c = la.ch
        # a cabin gap leaves the inlet air unknown there (NaN: the sample is not a candidate)
        T_in = mp.recirc * fill_short(c["cabin_temp_degC"], la.dt) + (1 - mp.recirc) * c["ambient_temp_degC"] \
            if lg.has("cabin_temp_degC") else c["ambient_temp_degC"]
        x = c["coolant_temp_degC"] + dT_cl - T_in
        y = c["vent_temp_degC"] + dT_vent - T_in
        ok = np.isfinite(x) & np.isfinite(y) & (x >= 10.0) & (c["blower_flow_kg_per_s"] > 0.005)
        xs.append(x[ok])
        ys.append(y[ok])
    if not xs or sum(v.size for v in xs) < MIN_SAMPLES:
        return None, "fewer than 60 samples with vent, coolant and ambient temperature and the coolant >= 10 K " \
                     "above the heater inlet air"
    x, y = np.concatenate(xs), np.concatenate(ys)
    r = y / x
    noise = 0.35  # degC: 1 degC quantisation (0.29) and sensor noise, each temperature
    s_r = noise * np.sqrt(1.0 + r ** 2) / x
    eps = float(np.percentile(r, 90))
    bind = np.zeros(r.size, bool)
    for _ in range(30):
        bind = r >= eps - 3.0 * s_r
        if bind.sum() < 3:
            break
        w = 1.0 / s_r[bind] ** 2
        new = float(np.sum(w * r[bind]) / np.sum(w))
        # the same binding set gives the same mean to the last bit: stop at the exact fixed point
        fixed = new == eps
        eps = new
        if fixed:
            break
    nb = int(bind.sum())
    fit.metrics.update(eps_binding_samples=nb, eps_candidate_samples=int(r.size))
    if nb < MIN_SAMPLES:
        return None, f"the heater-core limit bound in only {nb} samples (need {MIN_SAMPLES})"
    res = (y - eps * x)[bind]
    se = float(np.sqrt(np.sum(res ** 2) / max(nb - 1, 1) / np.sum(x[bind] ** 2)))
    # binding samples in log order for the autocorrelation inflation
    se *= inflation([res], 1)
    if _propagate:  # calibration uncertainty (offset) of the coolant and vent temperature sensors
        for kw in ({"dT_cl": T_SENSOR_SD}, {"dT_vent": T_SENSOR_SD}):
            e2, _ = _eps(use, base, SubsystemFit("tmp", ()), _propagate=False, **kw)
            if e2 is not None:
                se = float(np.sqrt(se ** 2 + (e2[0] - eps) ** 2))
    return (eps, se, nb), ""


def fit_cabin(logs, base, *, allowed=None, heater=None) -> SubsystemFit:
    """Fit the cabin parameters and the heater-core effectiveness.

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
    allowed : set of str, optional
    heater : None, "off" or "estimate"
        ``"off"``: logs without a heater channel are fitted with the heater declared off (zero heat);
        otherwise such logs are skipped (an estimated heater heat would leave the cabin balance undetermined).

    Returns
    -------
    SubsystemFit
    """
    allowed = set(PARAMS) if allowed is None else set(allowed)
    fit = SubsystemFit("cabin", NEEDS + ("heater_power_W",))
    names = [n for n in PARAMS if n in allowed]
    if not names:
        return fit
    if heater == "off":
        use, fit.skipped = usable_logs(logs, NEEDS, fit.subsystem)
    else:
        use, fit.skipped = usable_logs(logs, NEEDS, fit.subsystem,
                                       any_of=(("heater_power_W",), ("vent_temp_degC", "blower_flow_kg_per_s")))
    if "eps_hc" in allowed:
        e, why = _eps(logs, base, fit)
        p0 = float(base["eps_hc"])
        sd0 = float(prior_sd_of(base.param("eps_hc")))
        if e is None:
            miss = sorted({c for lg in logs for c in lg.missing(NEEDS_EPS)})
            if miss and not any(lg.has(*NEEDS_EPS) for lg in logs):
                fit.estimates["eps_hc"] = prior_only("eps_hc", p0, sd0, f"not fitted: missing channel(s) {', '.join(miss)}",
                                                        status="prior")
            else:
                fit.estimates["eps_hc"] = prior_only("eps_hc", p0, sd0, why)
        else:
            eps, se, nb = e
            fit.estimates["eps_hc"] = combine_with_prior("eps_hc", eps, se, p0, sd0,
                                                         f"{nb} samples where the heater-core limit binds",
                                                         bounds=base.param("eps_hc").bounds)
    cand = [n for n in ("C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W") if n in allowed]
    if not cand:
        return fit
    def none_fitted(why):  # the cabin parameters at their priors; eps_hc, estimated above, kept
        keep = dict(fit.estimates)
        not_fitted(fit, base, cand, f"cabin parameters not fitted: no log has {why} ("
                   + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
        fit.estimates.update(keep)
        fit.logs = []
        return fit

    if not use:
        return none_fitted("cabin temperature, ambient temperature and heater power")
    mp0 = base.model_params()
    data = []
    for i, lg in enumerate(use):
        la = log_arrays(lg, mp0, cabin_balance=False, heater="off" if heater == "off" else None)
        c = la.ch
        T = la.logged("cabin_temp_degC")
        T_amb = fill_short(c["ambient_temp_degC"], la.dt)
        Q = np.maximum(la.Q_heat, 0.0)
        segs = input_segments(np.isfinite(T_amb) & np.isfinite(Q), T, la.dt)
        if not segs:
            fit.skipped[lg.label()] = ("no run of at least 60 s with the heater heat and the ambient known and the "
                                       "cabin logged (each bridged across short gaps only)")
            continue
        used = {"heater heat": la.heater_source}
        n_out = int(T.size - sum(b - a for a, b in segs))
        if n_out:
            used["left out"] = (f"{n_out * la.dt:.0f} s where the heater heat or the ambient is unknown, or runs "
                                f"shorter than 60 s; the replay restarts after each such gap ({len(segs)} run(s))")
        fit.used[lg.label()] = used
        for j, (a, b) in enumerate(segs):
            Tj = T[a:b]
            data.append(dict(T=Tj, ok=np.isfinite(Tj), dt=la.dt, T_amb=T_amb[a:b], Q=Q[a:b],
                             T0=first_valid_mean(Tj, 5, 0.0), name=f"Tc0_{i}" if j == 0 else f"Tc0_{i}_{j}"))
    if not data:
        return none_fitted("a run of known heater heat and ambient")
    fit.logs = list(fit.used)
    bnd = {n: base.param(n).bounds for n in cand}
    prior = {n: float(base[n]) for n in cand}
    psd = {n: float(prior_sd_of(base.param(n))) for n in cand}

    make = output_error_params(cand, bnd, prior, data)

    def segments(ps, q_scale=1.0, dT=0.0):
        v = ps.valuesdict()
        mp = compiled_with(mp0, v, cand)
        return [(cabin_replay(mp, float(v[d["name"]]), d["dt"], d["T_amb"], q_scale * d["Q"]) - d["T"] - dT)[d["ok"]]
                for d in data]

    perturbed = [lambda ps: segments(ps, 1.0 + INPUT_REL_SD), lambda ps: segments(ps, dT=T_SENSOR_SD)]
    out = map_fit(lambda: make(set(cand)), segments, cand, prior=prior, prior_sd=psd, noise_sd=T_SENSOR_SD,
                  perturbed=perturbed, floor=0.05)
    res = out["params"]
    fit.metrics.update(rmse_degC=out["rmse"], samples=int(out["n"]), n_eff=out["n_eff"], noise_sd_degC=out["noise_sd"])
    fit.correlations = out["correl"]
    fit.confounded = confounded_pairs(out["correl"])
    fit.nuisance = {d["name"]: float(res[d["name"]].value) for d in data}
    for n in cand:
        fit.estimates[n] = posterior_estimate(n, out, f"MAP fit of the cabin temperature over {len(fit.logs)} log(s)"
                                              + ("; heater declared off where not logged" if any(
                                                  u["heater heat"] == HEATER_OFF for u in fit.used.values()) else ""),
                                              prior[n])
    return fit
