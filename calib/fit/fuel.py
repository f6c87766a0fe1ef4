"""Fuel fit (docs/model.md s.4 and s.8): warm map scale, idle fuel, cold factor table.

The model is ``W_f = max(fuel_scale * P_e / (eta_ool(P_e) LHV), W_idle) f_cl(T_cl)`` with the engine on and
``W_idle f_cl(T_cl)`` idling (:func:`calib.model.equations.fuel_rate`). One lmfit least-squares fit over the
*stable* 1 s bins of all logs (engine mode the same in the bin and both neighbours, see
:func:`calib.fit.validate.stable_mode`, and engine power within 3 % of both neighbours, so that the bin's mean
speed and torque describe one operating point; when the engine follows the optimal operating line,
bins whose mean speed is off the line by > 0.5 % are mixtures of two operating points and are dropped):

- warm engine-on bins (coolant >= 80 degC, where ``f_cl`` is 1 by definition) determine ``fuel_scale``;
- idle bins determine ``W_idle`` (through ``f_cl`` when cold);
- cold bins determine the ``f_cl`` entries (at the coolant temperature smoothed over 21 s, which removes
  most of its 1 degC quantisation) (the ratio of measured to nominal fuel rate), each entry only
  if its hat-function weight over the cold bins is >= 30 samples; the last breakpoint (80 degC) is the
  warm reference and stays 1.

Standard errors include the calibration uncertainty of the inputs (engine power 1 %, coolant
temperature 0.5 K), propagated by refitting with each input moved by one sd.

Every evaluation calls :func:`calib.model.equations.fuel_rate` in a compiled loop
(:func:`calib.fit.validate.fuel_replay`).
"""
from __future__ import annotations

import numpy as np

from calib.fit.toolkit import T_SENSOR_SD, INPUT_REL_SD, MIN_SAMPLES, ParamEstimate, SubsystemFit, lmfit_identify, not_fitted, usable_logs
from calib.fit.battery import hat_basis
from calib.model.equations import IDLE, ON
from calib.fit.replay import fuel_replay, log_arrays
from calib.units import RPM

NEEDS = ("engine_speed_rpm", "engine_torque_Nm", "fuel_rate_g_per_s", "coolant_temp_degC")
PARAMS = ("fuel_scale", "W_idle_g_per_s", "f_cl")
WARM_DEGC = 80.0
MIN_COVER = 30.0
OOL_TOL = 0.005


def smooth(x, n=21):
    """Centred moving average over ``n`` samples ignoring NaN (NaN stays NaN): removes most of the 1 degC
    quantisation of a slowly varying temperature before it is used as a regressor."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    k = np.ones(n)
    num = np.convolve(np.where(ok, x, 0.0), k, mode="same")
    den = np.convolve(ok.astype(float), k, mode="same")
    out = np.where(ok & (den > 0), num / np.maximum(den, 1.0), np.nan)
    return out


def _steady_power(P, rel=0.03, abs_W=300.0):
    """Bins whose engine power differs from both neighbours by < 3 % (+300 W): the two model steps a 1 s
    bin mixes then have the same operating point, so mean speed x mean torque is the engine power even
    when speed and torque were sampled at different instants."""
    P = np.nan_to_num(np.asarray(P, float), nan=-1e9)
    d = np.full(P.size, np.inf)
    d[1:-1] = np.maximum(np.abs(P[1:-1] - P[:-2]), np.abs(P[2:] - P[1:-1]))
    return d < abs_W + rel * np.abs(P)


def fit_fuel(logs, base, *, allowed=None) -> SubsystemFit:
    """Fit ``fuel_scale``, ``W_idle_g_per_s`` and the ``f_cl`` table from every log with the fuel channels.

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
    allowed : set of str, optional

    Returns
    -------
    SubsystemFit
    """
    import lmfit

    allowed = set(PARAMS) if allowed is None else set(allowed)
    fit = SubsystemFit("fuel", NEEDS)
    names = [n for n in PARAMS if n in allowed]
    use, fit.skipped = usable_logs(logs, NEEDS, "fit the fuel map")
    if not names:
        return fit
    if not use:
        return not_fitted(fit, base, names, "no log has engine speed, torque, fuel rate and coolant temperature ("
                          + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
    fit.logs = [lg.label() for lg in use]
    mp0 = base.model_params()
    mode, P, T, W, seg = [], [], [], [], []
    ool_filtered = []
    for lg in use:
        la = log_arrays(lg, mp0)
        T_cl = smooth(la.ch["coolant_temp_degC"], 21)
        ok = la.stable & np.isin(la.mode, (ON, IDLE)) & np.isfinite(la.ch["fuel_rate_g_per_s"]) & np.isfinite(T_cl)
        ok &= np.isfinite(la.P_e) & _steady_power(la.P_e)
        # bins whose mean speed and torque lie off the optimal operating line mix two operating points
        # (mean speed x mean torque is then not the mean power): drop them, when the engine follows its
        # line at all (it does in the model; a real engine that does not keeps all its bins)
        w = la.ch["engine_speed_rpm"] * RPM
        dev = np.abs(np.interp(np.nan_to_num(la.P_e), mp0.P_ool, mp0.w_ool) / np.maximum(w, 1e-9) - 1.0)
        on_ok = ok & (la.mode == ON)
        if on_ok.sum() and np.mean(dev[on_ok] < OOL_TOL) >= 0.5:
            ok &= (la.mode != ON) | (dev < OOL_TOL)
            ool_filtered.append(lg.label())
        mode.append(la.mode[ok])
        P.append(np.nan_to_num(la.P_e[ok]))
        T.append(T_cl[ok])
        W.append(la.ch["fuel_rate_g_per_s"][ok])
        seg.append(int(ok.sum()))
    mode = np.concatenate(mode).astype(np.int64)
    P, T, W = np.concatenate(P), np.concatenate(T), np.concatenate(W)
    bounds_idx = np.cumsum(seg)[:-1]
    on, idle = mode == ON, mode == IDLE
    warm_on = int(np.sum(on & (T >= WARM_DEGC)))
    n_idle = int(np.sum(idle))
    pf = base.param("f_cl")
    Tbp = np.array(pf.x)
    f0 = np.array(pf.value, float)
    cold = T < WARM_DEGC
    cover = hat_basis(T[cold], Tbp).sum(axis=0)
    fit.metrics.update(ool_filtered_logs=len(ool_filtered), samples=int(P.size), warm_on_samples=warm_on,
                       idle_samples=n_idle,
                       cold_samples=int(cold.sum()))

    pre = {}
    cand = []
    if "fuel_scale" in allowed:
        cand.append("fuel_scale")
        if warm_on < MIN_SAMPLES:
            pre["fuel_scale"] = (f"only {warm_on} stable warm engine-on samples (coolant >= {WARM_DEGC:g} degC), "
                                 f"need {MIN_SAMPLES}")
    if "W_idle_g_per_s" in allowed:
        cand.append("W_idle_g_per_s")
        if n_idle < MIN_SAMPLES:
            pre["W_idle_g_per_s"] = f"only {n_idle} stable idle samples, need {MIN_SAMPLES}"
    fcl_names = []
    if "f_cl" in allowed:
        for j in range(len(Tbp) - 1):  # the last breakpoint is the warm reference (1)
            nm = f"f_cl_{j}"
            fcl_names.append(nm)
            cand.append(nm)
            if cover[j] < MIN_COVER:
                pre[nm] = f"T_cl {Tbp[j]:g} degC: hat weight of cold samples {cover[j]:.1f} < {MIN_COVER:g}"
            elif "fuel_scale" in pre:
                pre[nm] = f"T_cl {Tbp[j]:g} degC: the warm map scale is not determined, so neither is the ratio"
    bnd = {"fuel_scale": base.param("fuel_scale").bounds, "W_idle_g_per_s": base.param("W_idle_g_per_s").bounds}
    for j, nm in enumerate(fcl_names):
        bnd[nm] = pf.bounds
    prior = {"fuel_scale": float(base["fuel_scale"]), "W_idle_g_per_s": float(base["W_idle_g_per_s"])}
    prior.update({nm: float(f0[j]) for j, nm in enumerate(fcl_names)})

    def make_params(vary):
        ps = lmfit.Parameters()
        for nm in cand:
            lo, hi = bnd[nm]
            ps.add(nm, value=prior[nm], min=lo, max=hi, vary=nm in vary)
        return ps

    def model_of(ps, sP=1.0, dT=0.0):
        v = ps.valuesdict()
        f = f0.copy()
        for j, nm in enumerate(fcl_names):
            f[j] = v[nm]
        mp = mp0._replace(fuel_scale=float(v.get("fuel_scale", mp0.fuel_scale)),
                          W_idle=float(v.get("W_idle_g_per_s", mp0.W_idle)), f_cl=f)
        return fuel_replay(mp, mode, sP * P, T + dT)

    def residual(ps):
        return model_of(ps) - W

    # input calibration uncertainty: engine power (1 %), coolant temperature (0.5 K)
    perturbed = [lambda ps: model_of(ps, sP=1.0 + INPUT_REL_SD) - W, lambda ps: model_of(ps, dT=T_SENSOR_SD) - W]

    def segments(ps):
        return np.split(residual(ps), bounds_idx)

    if all(c in pre for c in cand):
        out = {"undetermined": pre, "values": {}, "stderr": {}, "correl": {}, "vary": [], "n": P.size,
               "n_eff": float("nan"), "factor": float("nan"), "conf": {}}
    else:
        out = lmfit_identify(make_params, residual, cand, bounds=bnd, segments=segments, fixed_reason=pre,
                             perturbed=perturbed)
        r = residual(out["result"].params)
        fit.metrics.update(rmse_g_per_s=float(np.sqrt(np.mean(r ** 2))), n_eff=out["n_eff"],
                           se_inflation=out["factor"])
    fit.correlations = out["correl"]
    und = out["undetermined"]
    for nm in ("fuel_scale", "W_idle_g_per_s"):
        if nm not in cand:
            continue
        if nm in out["vary"]:
            fit.estimates[nm] = ParamEstimate(nm, out["values"][nm], out["stderr"][nm], "estimated",
                                              f"{P.size} stable samples", prior=prior[nm])
        else:
            fit.estimates[nm] = ParamEstimate(nm, prior[nm], None, "undetermined", und.get(nm, ""), prior=prior[nm])
    if fcl_names:
        est = [nm in out["vary"] for nm in fcl_names] + [False]
        vals = [out["values"][nm] if e else f0[j] for j, (nm, e) in enumerate(zip(fcl_names, est))] + [f0[-1]]
        ses = [out["stderr"][nm] if e else float("nan") for nm, e in zip(fcl_names, est)] + [float("nan")]
        # f_cl must not increase with temperature: revert the less certain offending entry
        for _ in range(len(vals)):
            bad = [j for j in range(len(vals) - 1) if vals[j + 1] > vals[j] + 1e-12]
            if not bad:
                break
            j = bad[0]
            cands = [k for k in (j, j + 1) if est[k]]
            if not cands:
                break
            k = max(cands, key=lambda k: ses[k])
            est[k] = False
            und[fcl_names[k]] = f"T_cl {Tbp[k]:g} degC: estimate {vals[k]:.3f} breaks the monotonicity of f_cl"
            vals[k], ses[k] = f0[k], float("nan")
        st = ["estimated" if e else "undetermined" for e in est]
        st[-1] = "fixed"
        why = [und[nm] for nm in fcl_names if nm in und]
        note = f"entry at {Tbp[-1]:g} degC is the warm reference (1)"
        if why:
            note = "entries not determined: " + "; ".join(why) + ". " + note
        fit.estimates["f_cl"] = ParamEstimate("f_cl", [float(v) for v in vals], [float(s) for s in ses],
                                              "estimated" if any(est) else "undetermined", note,
                                              prior=list(map(float, f0)), entry_status=st)
    return fit
