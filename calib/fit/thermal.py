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
  their prior (the posterior equals it), and the note says so. Samples with the coolant above
  :func:`regulation_limit` (the prior opening plus the span of the prior radiator) are left out too, and the
  replay restarts below it: ``T_open`` and ``k_rad`` are informed by the coolant near the opening only. The
  posterior sd includes the calibration uncertainty of the inputs (fuel rate, engine power, heater power:
  1 % each) and of the coolant sensor (0.5 K offset).

Sparse inputs: an input is bridged across its short gaps only (:func:`calib.fit.replay.fill_short`); a bin
where the engine state, the fuel rate of a running engine, the engine power, the heater heat or the ambient
is unknown is left out, and the replay restarts after it from its own initial temperature (one nuisance
parameter per run of known bins, :func:`calib.fit.replay.input_segments`). A gap is never read as zero
fuel or an engine off.

Heater heat that no channel gives (``heater=``, :data:`calib.fit.replay.HEATER_CHOICES`): declared off
(``"off"``: zero), or estimated (``"estimate"``, and by default where the log has neither a heater channel
nor a cabin temperature to infer it from) as a draw ``q_heat`` per log that ramps with the simulated coolant's
excess over the ambient up to :data:`HEATER_RAMP_K` and is constant beyond
(:func:`calib.fit.replay.coolant_replay_heater`): a nuisance parameter with a wide prior
(:data:`HEATER_PRIOR_W` +- :data:`HEATER_PRIOR_SD_W`, within 0 ... :data:`HEATER_MAX_W`). ``used`` names which.
Without a known heat sink the coolant rise fixes ``C_eng / (1 - gamma_exh)`` (the heat that stays in the
engine over its heat capacity): a parked warm-up at idle is then a calibration drive whose split of that ratio
between ``C_eng`` and ``gamma_exh`` comes from their priors.
"""
from __future__ import annotations

import numpy as np

from calib.fit.toolkit import (T_SENSOR_SD, INPUT_REL_SD, ParamEstimate, SubsystemFit, combine_with_prior, confounded_pairs, map_fit, not_fitted,
                               output_error_params, posterior_estimate)
from calib.fit.replay import (coolant_replay, coolant_replay_heater, fill_short, first_valid_mean,
                              fuel_label, input_segments, log_arrays)

#: Channels every log of the fit needs; the engine power and the heater heat come in several ways
#: (:func:`calib.fit.replay.log_arrays`).
NEEDS = ("coolant_temp_degC", "fuel_rate_g_per_s", "ambient_temp_degC")
PARAMS = ("kappa", "C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K")
MIN_ABOVE_S = 120.0
#: The estimated heater draw (W) of a log whose heater heat is not logged: prior, prior sd, upper bound, and
#: the coolant excess over the ambient (K) at which it reaches its full draw.
HEATER_PRIOR_W = 1000.0
HEATER_PRIOR_SD_W = 1500.0
HEATER_MAX_W = 8000.0
HEATER_RAMP_K = 30.0


def regulation_limit(params) -> float:
    """Coolant temperature (degC) above which the fit leaves the logged coolant out: the prior opening plus
    ``Q_rad_max / k_rad``, the span over which the prior radiator's heat grows with the coolant. Beyond it
    that radiator is saturated, so ``k_rad`` has no leverage there; a logged coolant up there is a radiator
    that did not hold it (one that cools only at a standstill, or none), and fitting it pulls ``k_rad`` to
    whatever gain mimics that structure."""
    return float(params["T_open_degC"]) + float(params["Q_rad_max_W"]) / float(params["k_rad_W_per_K"])


def fuel_input(la):
    """Logged fuel rate as a heat input: zero where the engine is known to be stopped (a fuel-flow sensor's
    noise clipped at zero would otherwise add phantom heat while the engine is off), the logged rate
    (bridged across its short gaps) where it runs, NaN where that is unknown (no engine cue reaches the bin,
    or the engine runs and no fuel sample is near)."""
    W = np.maximum(fill_short(la.ch["fuel_rate_g_per_s"], la.dt), 0.0)
    running = (la.f_on + la.f_idle) > 0
    out = np.where(running, W, 0.0)
    out[~la.known] = np.nan
    return out


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
                              f"from the engine-bay temperature ({x.size} samples)", bounds=base.param("kappa").bounds)


def fit_thermal(logs, base, *, allowed=None, heater=None) -> SubsystemFit:
    """Fit the engine thermal parameters (maximum a posteriori) from every log with coolant temperature,
    ambient temperature, fuel rate and an engine power (logged or inferred); the heater heat is logged, from
    vent temperature and blower flow, inferred from the cabin balance, declared off or estimated (``heater``).

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
        Priors (values and ``prior_sd``); ``kappa`` and the heater/cabin parameters used to derive inputs.
    allowed : set of str, optional
    heater : None, "off" or "estimate"
        The heater heat where no channel gives it (:data:`calib.fit.replay.HEATER_CHOICES`).

    Returns
    -------
    SubsystemFit
    """
    from calib.model.params import compiled_with, prior_sd_of

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
            la = log_arrays(lg, mp_b, heater=heater)
            if not la.engine_source:
                miss.append("engine power (engine_speed_rpm + engine_torque_Nm, or engine_power_W, or speed_mps "
                            "with battery power)")
        if miss:
            fit.skipped[lg.label()] = f"missing channel(s) {', '.join(miss)}"
        else:
            use.append((lg, la))
    if not use:
        return not_fitted(fit, base, names, "engine thermal parameters not fitted: no log has coolant temperature, "
                          "fuel rate, ambient temperature and an engine power ("
                          + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
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
    T_open0 = float(work["T_open_degC"])
    T_reg = regulation_limit(work)
    data, q_names, q_of, left_out, over, hot_max = [], [], {}, {}, {}, []
    for i, (lg, la) in enumerate(use):
        c = la.ch
        T = la.logged("coolant_temp_degC")
        W = fuel_input(la)
        P = la.f_on * la.P_on
        P[~la.known] = np.nan
        est = not la.heater_source
        Q = np.zeros(T.size) if est else np.maximum(la.Q_heat, 0.0)
        T_amb = fill_short(c["ambient_temp_degC"], la.dt)
        known = np.isfinite(W) & np.isfinite(P) & np.isfinite(Q) & np.isfinite(T_amb)
        # a coolant beyond the prior radiator's span is a radiator the model does not have (regulation_limit)
        hot = T > T_reg
        segs = input_segments(known & ~hot, T, la.dt)
        used = {"engine power": la.engine_source, "heater heat": la.heater_source, "fuel heat": fuel_label(lg),
                **{f"inferred {k}": v for k, v in la.inferred.items()}}
        if est:
            why = ("heater='estimate'" if heater == "estimate" else
                   "no heater channel and no cabin temperature to infer it from")
            used["heater heat"] = (f"not logged: estimated ({why}) as a draw q_heat_{i} ramping with the "
                                   f"coolant's excess over the ambient up to {HEATER_RAMP_K:g} K, prior "
                                   f"{HEATER_PRIOR_W:g} +- {HEATER_PRIOR_SD_W:g} W; declare heater='off' if it did "
                                   "not run")
        if not segs:
            fit.skipped[lg.label()] = ("no run of at least 60 s with every input known (engine state, fuel rate, "
                                       "engine power, heater heat, ambient) and the coolant logged at or below "
                                       f"{T_reg:.0f} degC (prior thermostat opening + Q_rad_max / k_rad)")
            continue
        fit.used[lg.label()] = used
        n_hot = int(np.sum(hot))
        if n_hot:
            over[lg.label()] = n_hot * la.dt
            hot_max.append(float(np.max(T[hot])))
            used["above the thermostat"] = (f"{n_hot * la.dt:.0f} s with the coolant above {T_reg:.0f} degC (prior "
                                            "opening + Q_rad_max / k_rad) left out: a radiator that regulates "
                                            "holds the coolant below that")
        in_seg = np.zeros(T.size, bool)
        for a, b in segs:
            in_seg[a:b] = True
        n_out = int(np.sum(~in_seg & ~hot))
        if n_out:
            left_out[lg.label()] = n_out * la.dt
            used["left out"] = (f"{n_out * la.dt:.0f} s where an input is unknown (no value within its short-gap "
                                f"limit) or runs shorter than 60 s; the replay restarts after each such gap "
                                f"({len(segs)} run(s))")
        qn = f"q_heat_{i}" if est else None
        if qn:
            q_names.append(qn)
            q_of[lg.label()] = qn
        for j, (a, b) in enumerate(segs):
            Tj = T[a:b]
            data.append(dict(T=Tj, ok=np.isfinite(Tj), dt=la.dt, T_amb=T_amb[a:b], W=W[a:b], P=P[a:b], Q=Q[a:b],
                             heater_on=np.full(b - a, True) if est else Q[a:b] > 200.0, T0=first_valid_mean(Tj, 5, 0.0),
                             name=f"T0_{i}" if j == 0 else f"T0_{i}_{j}", q=qn))
    if not data:
        return not_fitted(fit, base, names, "engine thermal parameters not fitted: no log has a run of known inputs ("
                          + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
    fit.logs = [lg for lg in fit.used]
    Tmax = max([float(np.nanmax(d["T"])) for d in data] + hot_max)
    fit.metrics["coolant_max_degC"] = Tmax
    if left_out:
        fit.metrics["left_out_s"] = float(sum(left_out.values()))
    fit.metrics["above_regulation_s"] = float(sum(over.values()))
    cand = [n for n in ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K")
            if n in allowed]
    above = sum(float(np.sum(d["T"][d["ok"]] > T_open0 - 5.0)) * d["dt"] for d in data)
    off_s = sum(float(np.sum(~d["heater_on"] & d["ok"] & (d["T"] > d["T_amb"] + 20))) * d["dt"] for d in data)
    fit.metrics.update(time_near_thermostat_s=above, heater_off_warm_s=off_s)
    bnd = {n: work.param(n).bounds for n in cand}
    prior = {n: float(work[n]) for n in cand}
    psd = {n: float(prior_sd_of(work.param(n))) for n in cand}
    # the estimated heater draws are nuisance parameters with their own prior
    nuis_prior = {q: HEATER_PRIOR_W for q in q_names}
    nuis_sd = {q: HEATER_PRIOR_SD_W for q in q_names}

    make0 = output_error_params(cand, bnd, prior, data)
    at_zero = set()  # estimated heater draws held at their bound 0 (see below)

    def make(vary):
        ps = make0(vary)
        for q in q_names:
            # no lower bound in the search (a bound's transform stalls the optimiser as the draw nears 0):
            # a draw that comes out negative is then held at 0 and the fit repeated
            ps.add(q, value=0.0 if q in at_zero else HEATER_PRIOR_W, min=-HEATER_MAX_W, max=HEATER_MAX_W,
                   vary=q not in at_zero)
        return ps

    def sims(ps, sW=1.0, sP=1.0, sQ=1.0):
        v = ps.valuesdict()
        mp = compiled_with(mp0, v, cand)
        out = []
        for d in data:
            if d["q"] is None:
                out.append(coolant_replay(mp, float(v[d["name"]]), d["dt"], d["T_amb"], sW * d["W"], sP * d["P"],
                                          sQ * d["Q"]))
            else:
                out.append(coolant_replay_heater(mp, float(v[d["name"]]), d["dt"], d["T_amb"], sW * d["W"],
                                                 sP * d["P"], sQ * d["Q"], sQ * float(v[d["q"]]), HEATER_RAMP_K))
        return out

    def segments(ps, dT=0.0, **scale):
        return [(s - d["T"] - dT)[d["ok"]] for s, d in zip(sims(ps, **scale), data)]

    # the replay is not affine in its inputs (thermostat, heater-core limit): central differences
    perturbed = [(lambda ps, k=k: segments(ps, **{k: 1.0 + INPUT_REL_SD}),
                  lambda ps, k=k: segments(ps, **{k: 1.0 - INPUT_REL_SD})) for k in ("sW", "sP", "sQ")]
    perturbed.append(lambda ps: segments(ps, dT=T_SENSOR_SD))
    def run():
        free = [q for q in q_names if q not in at_zero]
        # trust-region reflective: on power-only logs Levenberg-Marquardt's bound transform ran into its
        # limit of evaluations (16000) short of the mode
        return map_fit(lambda: make(set(cand)), segments, cand, prior={**prior, **{q: nuis_prior[q] for q in free}},
                       prior_sd={**psd, **{q: nuis_sd[q] for q in free}}, noise_sd=T_SENSOR_SD, perturbed=perturbed,
                       floor=0.05, trf=True)

    out = run()
    neg = {q for q in q_names if out["params"][q].value < 0.0}
    if neg:
        at_zero.update(neg)
        out = run()
    res = out["params"]
    fit.metrics.update(rmse_degC=out["rmse"], samples=int(out["n"]), n_eff=out["n_eff"],
                       noise_sd_degC=out["noise_sd"])
    fit.correlations = out["correl"]
    fit.confounded = confounded_pairs(out["correl"])
    fit.nuisance = {d["name"]: float(res[d["name"]].value) for d in data}
    fit.nuisance.update({q: float(res[q].value) for q in q_names})
    for q in q_names:
        fit.metrics[f"{q}_W"] = float(res[q].value)
    for label, q in q_of.items():
        fit.used[label]["heater heat"] += (f"; fitted draw {float(res[q].value):.0f} W"
                                           + (" (held at its bound 0: the data ask for less than no heater)"
                                              if q in at_zero else ""))
    heat_known = any(d["q"] is None and np.any(d["Q"] > 200.0) for d in data)
    for n in cand:
        note = f"MAP fit of the coolant temperature over {len(fit.logs)} log(s)"
        if n == "hA_eng_W_per_K" and not kappa_known:
            note = (f"identified only as hA_eng (1 - kappa) = {out['values'][n] * (1 - mp0.kappa):.4g} W/K; "
                    f"kappa not logged, this value assumes kappa = {mp0.kappa:g} (its prior)")
        if n in ("T_open_degC", "k_rad_W_per_K") and over:
            note += (f"; only the coolant at or below {T_reg:.0f} degC informs it ({sum(over.values()):.0f} s above "
                     "left out: the logged radiator did not hold the coolant there)")
        if n in ("T_open_degC", "k_rad_W_per_K") and above < MIN_ABOVE_S:
            note = (f"coolant never reached the thermostat ({above:.0f} s within 5 K of its prior opening, max "
                    f"{Tmax:.1f} degC): the value comes from the prior")
        if n in ("C_eng_J_per_K", "gamma_exh") and not heat_known:
            note += ("; no logged heat sink (heater heat not logged or zero): the coolant rise fixes "
                     "C_eng / (1 - gamma_exh), and their priors split it")
        fit.estimates[n] = posterior_estimate(n, out, note, prior[n])
    return fit
