"""Fuel fit (docs/model.md s.4 and s.8): the warm fuel rate along the operating line, the idle fuel and a
monotone, smooth cold-correction table, by maximum a posteriori estimation.

The model is ``W_f = max(fuel_scale * P_e / (eta_ool(P_e) LHV), W_idle) f_cl(T_cl)`` with the engine on
and ``W_idle f_cl(T_cl)`` idling (:func:`calib.model.equations.fuel_rate`). Estimated:

- the warm fuel rate as a function of engine power: the entries of the efficiency table ``eta_ool`` (at
  its power breakpoints; ``fuel_scale`` stays at its base value, the table carries the level and the
  shape), each with its prior (the reference curve, :data:`calib.model.params.PRIOR_SD`) and a smoothness
  prior on the second differences of ``log(eta / eta_prior)`` (:data:`SMOOTH_SD` per breakpoint), so
  entries the logs do not reach follow their neighbours and the prior rather than jumping;
- ``W_idle_g_per_s`` from idle bins;
- ``f_cl``: 1 at the warm reference breakpoint ``r`` (:func:`calib.model.params.f_cl_ref_index`, 80 degC);
  below it ``f_cl_j = 1 + sum_{j <= k < r} d_k``, above it ``f_cl_j = 1 - sum_{r < k <= j} u_k``, with
  increments ``d_k, u_k >= 0``: monotone (non-increasing) by construction. Above the reference the factor
  can fall below 1 (a hotter engine's lower friction), with a prior of 1 and a few % sd
  (:data:`calib.model.params.F_CL_HOT_SD_PER_K`). Its prior is on the entries and a smoothness prior on
  the change of slope (:data:`F_SLOPE_SD` per K). Entries with fewer than :data:`MIN_COVER` samples near
  them (cold samples below the reference, warm ones above) are reported as not reached.

Sparse channels: the fuel rate is used in the bins where it was logged; the coolant temperature (a slow
regressor) and the engine power are bridged across short gaps only (:func:`calib.fit.replay.fill_short`),
and the engine mode comes from every cue the log has (:func:`calib.fit.replay.running_cue`): a bin where
any of them is unknown is left out, never read as an engine off or zero fuel. A fuel rate estimated from the
MAF is named as such in ``used``.

Data: the *stable* 1 s bins of every log with fuel rate and coolant temperature and an engine operating
point (logged speed x torque, logged engine power, or inferred from the power balance: see
:func:`calib.fit.replay.log_arrays`): engine mode the same in the bin and both neighbours, engine power
within 3 % of both neighbours; when the engine follows the optimal operating line (speed logged), bins
off the line by > 0.5 % mix two operating points and are dropped. The coolant temperature is smoothed
over 21 s (its 1 degC quantisation).

Noise: one sd per regime (engine mode x interval of the ``f_cl`` table the coolant falls in), not one for
every bin (:func:`_regime_scale`). A cold engine's fuel rate scatters about the model far more than a warm
one's (enrichment and catalyst heating, and a warm-up curve the table follows only at its breakpoints; the
metric ``noise_sd_by_regime_g_per_s`` prints each regime's). With one sd, that scatter set the weight of
the warm bins too, and the priors on the cold entries then outweighed them: the fit bought a smaller cold
factor with a warm level too high on its own warm bins (docs/calibration.md). The fit runs once with one
sd, sets each regime's from its residuals, and runs again from there.

The posterior sd includes the calibration uncertainty of the inputs (engine power 1 %, fuel meter 2 %,
coolant temperature 1 K and a coolant sensor response time of 20 s), propagated linearly.

Every evaluation calls :func:`calib.model.equations.fuel_rate` in a compiled loop
(:func:`calib.fit.replay.fuel_replay`). The minimiser is the trust-region reflective one with the bounds held
as bounds and an analytic Jacobian (:func:`_jacobian`): most increments of ``f_cl`` sit at their bound 0, where
Levenberg-Marquardt's bound transform stalled after tens of thousands of differenced evaluations on
power-only logs (FASTSim's), short of the posterior mode.
"""
from __future__ import annotations

import math

import numpy as np

from calib.fit.battery import hat_basis
from calib.fit.replay import fill_short, filled_note, fuel_label, fuel_replay, log_arrays
from calib.fit.toolkit import (INPUT_REL_SD, WEAK_INFORMED, ParamEstimate, SubsystemFit, confounded_pairs, map_fit,
                               not_fitted, posterior_estimate)
from calib.model.equations import IDLE, ON
from calib.model.params import compiled_with, f_cl_ref_index, prior_sd_of
from calib.units import RPM

NEEDS = ("fuel_rate_g_per_s", "coolant_temp_degC")  # + an engine operating point (logged or inferred)
PARAMS = ("eta_ool", "fuel_scale", "W_idle_g_per_s", "f_cl")
WARM_DEGC = 80.0
MIN_COVER = 30.0
OOL_TOL = 0.005
T_SD = 1.0  # degC: sensor calibration (0.5 K) plus what smoothing a 1 degC-quantised reading leaves
#: Calibration uncertainty of a fuel-flow meter (1 sd, relative) and the response time of a coolant
#: temperature sensor (s): both propagated into the posterior sd (a biased meter or a slow sensor moves
#: the estimates by about this much, whatever the amount of data).
FUEL_METER_REL_SD = 0.02
SENSOR_LAG_S = 20.0
NOISE_G_PER_S = 0.02  # a priori noise sd of a fuel-flow reading in a 1 s bin
RESOLUTION_G_PER_S = 0.002  # the smallest noise sd a fit assumes (a fuel meter's resolution)
SMOOTH_SD = 0.05  # second difference of log(eta / eta_prior) per breakpoint
F_SLOPE_SD = 0.03  # change of the f_cl slope (1/K) between adjacent intervals
#: The stable bins are operating points, not a time series: their residuals' autocorrelation (a warm-up
#: the model follows imperfectly) counts at most this many bins as one independent sample.
MAX_TAU = 10.0


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


def f_cl_from_increments(d, u=()):
    """Table values ``1 + sum_{k >= j} d_k`` below the reference entry (1), then ``1 - sum_{k <= j} u_k``
    above it (length ``len(d) + 1 + len(u)``; entry ``len(d)`` is the reference)."""
    d = np.asarray(d, float)
    u = np.asarray(u, float)
    return np.concatenate([1.0 + np.cumsum(d[::-1])[::-1], [1.0], 1.0 - np.cumsum(u)])


def _f_cl_jacobian(r, n):
    """Matrix M (n, n - 1) with f = 1 + M [d, u] (:func:`f_cl_from_increments`, reference entry r)."""
    M = np.zeros((n, n - 1))
    for j in range(r):
        M[j, j:r] = 1.0
    for j in range(r + 1, n):
        M[j, r:j] = -1.0
    return M


def _jacobian(mode, P, T, Pbp, Tbp, rT, mp0, eta_names, fit_idle, d_names, u_names, f_sd, f_bounds, tables):
    """``jac(ps) -> (J_data, J_extra)`` of the fuel fit, in the order of the varied parameters: the
    derivatives of :func:`calib.model.equations.fuel_rate` (interpolation weights of the efficiency and
    ``f_cl`` tables, the idle floor, the table's clip at its bounds) and of the smoothness priors. It steers
    the minimiser only: the residuals are :func:`calib.fit.replay.fuel_replay`'s, and the posterior
    covariance is differenced from them (tests/test_fit_speed.py checks this Jacobian against differences)."""
    on = mode == ON
    HP, HT = hat_basis(P, Pbp), hat_basis(T, Tbp)
    M = _f_cl_jacobian(rT, len(Tbp))
    inc = list(d_names) + list(u_names)
    keep = np.arange(len(Tbp)) != rT
    D1 = np.diff(np.eye(len(Tbp)), axis=0) / np.diff(Tbp)[:, None]  # slope of f per interval
    D2T = np.diff(D1, axis=0) / F_SLOPE_SD
    m = len(Pbp) - 1
    D2P = np.diff(np.eye(m), 2, axis=0) / SMOOTH_SD

    def jac(ps):
        names = [k for k in ps if ps[k].vary]
        col = {k: i for i, k in enumerate(names)}
        v = ps.valuesdict()
        eta, f = tables(v)
        W_idle = float(v.get("W_idle_g_per_s", mp0.W_idle))
        fk = HT @ f
        ek = HP @ eta
        wmap = mp0.fuel_scale * P / (ek * mp0.LHV)
        above = on & (wmap > W_idle)
        wm = np.where(above, wmap, W_idle)
        Jd = np.zeros((P.size, len(names)))
        Je = []
        if eta_names:
            dW = np.where(above, -wmap / ek * fk, 0.0)
            for j, nm in enumerate(eta_names, start=1):
                Jd[:, col[nm]] = dW * HP[:, j]
            je = np.zeros((m - 2, len(names)))
            for j, nm in enumerate(eta_names, start=1):
                je[:, col[nm]] = D2P[:, j - 1] / eta[j]
            Je.append(je)
        if fit_idle:
            Jd[:, col["W_idle_g_per_s"]] = np.where(above, 0.0, fk)
        if inc:
            # an entry held at the table's bounds does not move with the increments
            free = (f > f_bounds[0]) & (f < f_bounds[1])
            Mc = M * free[:, None]
            dF = (HT @ Mc) * wm[:, None]
            jf = np.zeros((int(keep.sum()) + D2T.shape[0], len(names)))
            for i, nm in enumerate(inc):
                Jd[:, col[nm]] = dF[:, i]
                jf[:, col[nm]] = np.concatenate([Mc[keep, i] / f_sd[keep], D2T @ Mc[:, i]])
            Je.append(jf)
        return Jd, (np.vstack(Je) if Je else np.zeros((0, len(names))))

    return jac


def _data_start(mode, P, T, W, mp0, Tbp, rT, eta_names, d_names, u_names, eta_bounds):
    """A second starting point from the data: the measured over the prior warm fuel rate of the engine-on
    bins, averaged near each coolant breakpoint (weights of linear interpolation). Its value near the
    reference is the warm level (it scales the efficiency table), the others over it the ``f_cl`` entries
    (held monotone). A car far from the prior (a cold factor of 4, a level 10 % off, a hot engine that
    burns less) otherwise leaves the fit in a mode near the prior. ``[]`` when the data cannot say."""
    on = mode == ON
    if not (d_names or u_names) or on.sum() < MIN_COVER:
        return []
    w0 = fuel_replay(mp0._replace(f_cl=np.ones_like(mp0.f_cl)), mode[on], P[on], T[on])
    ok = w0 > 0
    H = hat_basis(T[on][ok], Tbp)
    wt = H.sum(axis=0)
    ratio = W[on][ok] / w0[ok]
    if wt[rT] < MIN_COVER:
        return []
    m = np.where(wt >= MIN_COVER, (H * ratio[:, None]).sum(axis=0) / np.maximum(wt, 1e-12), np.nan)
    # the warm level from the samples on both sides of the reference, and from those at or above it only
    # (a table whose far end falls steeply puts the two modes of the posterior on either side)
    hot = T[on][ok] >= Tbp[rT]
    wh = H[hot, rT].sum()
    levels = [m[rT]] + ([float((H[hot, rT] * ratio[hot]).sum() / wh)] if u_names and wh >= MIN_COVER else [])
    starts = []
    for level in (levels if eta_names else [1.0]):
        g = m / level
        g[rT] = 1.0
        for j in range(rT - 1, -1, -1):  # colder: never below the next warmer entry
            g[j] = max(g[j] if np.isfinite(g[j]) else g[j + 1], g[j + 1])
        for j in range(rT + 1, len(Tbp)):  # hotter: never above the next colder entry
            g[j] = min(g[j] if np.isfinite(g[j]) else g[j - 1], g[j - 1])
        start = {nm: float(g[j] - g[j + 1]) for j, nm in enumerate(d_names)}
        start.update({nm: float(g[j - 1] - g[j]) for j, nm in enumerate(u_names, start=rT + 1)})
        start.update({nm: float(np.clip(mp0.eta_ool[j] / level, *eta_bounds))
                      for j, nm in enumerate(eta_names, start=1)})
        starts.append(start)
    return starts


def _regime_groups(mode, T, Tbp):
    """Regime of every bin: the engine mode and the interval of the coolant table the bin falls in."""
    return np.searchsorted(np.asarray(Tbp, float), T) * 4 + np.asarray(mode)


def _regime_scale(r, groups):
    """Scatter of the residuals ``r`` in each regime over their overall scatter (1 in a regime with fewer
    than :data:`MIN_COVER` bins; never below :data:`RESOLUTION_G_PER_S`).

    A cold engine's fuel rate scatters more about any smooth model than a warm one's (enrichment, wall
    wetting, catalyst heating, and a warm-up curve the coolant table follows only at its breakpoints): with
    one noise sd for every bin, that scatter sets the weight of the warm bins too, and priors then outweigh
    what the warm bins say about the warm level. Each regime gets its own sd (a variance component per
    regime), estimated from a first fit's residuals."""
    r = np.asarray(r, float)
    ok = np.isfinite(r)
    tot = math.sqrt(float(np.mean(r[ok] ** 2))) if ok.any() else 0.0
    out = np.ones(r.size)
    if tot <= 0.0:
        return out
    for g in np.unique(groups):
        sel = (groups == g) & ok
        if sel.sum() >= MIN_COVER:
            out[groups == g] = max(math.sqrt(float(np.mean(r[sel] ** 2))), RESOLUTION_G_PER_S) / max(tot, RESOLUTION_G_PER_S)
    return out


def _regime_sd_text(sd, groups, Tbp):
    """``{"engine on, 20-60 degC": sd, ...}`` (g/s) of the regimes :func:`_regime_groups` forms."""
    edges = [-math.inf] + [float(x) for x in Tbp] + [math.inf]
    names = {ON: "engine on", IDLE: "idle"}
    out = {}
    for g in np.unique(groups):
        k, m = divmod(int(g), 4)
        lo, hi = edges[k], edges[k + 1]
        span = f"below {hi:g}" if lo == -math.inf else (f"above {lo:g}" if hi == math.inf else f"{lo:g}-{hi:g}")
        out[f"{names.get(m, m)}, {span} degC"] = float(np.median(sd[groups == g]))
    return out


def _gather(use, mp0, fit):
    mode, P, T, W, seg, TL = [], [], [], [], [], []
    for lg in use:
        la = log_arrays(lg, mp0)
        used = {"engine power": la.engine_source, "fuel": fuel_label(lg), "coolant": "coolant_temp_degC"}
        used.update({f"inferred {k}": v for k, v in la.inferred.items() if k != "heater power"})
        # the coolant is a slow regressor: bridged across its short gaps (a sensor polled every few seconds),
        # never across long ones; the fuel rate (the output) only where logged
        T_cl = smooth(fill_short(la.ch["coolant_temp_degC"], la.dt), 21)
        W_log = la.logged("fuel_rate_g_per_s")
        note = filled_note(lg, "fuel_rate_g_per_s")
        if note:
            used["warning"] = note
        ok = la.stable & np.isin(la.mode, (ON, IDLE)) & np.isfinite(W_log) & np.isfinite(T_cl)
        ok &= np.isfinite(la.P_e) & _steady_power(la.P_e)
        if la.has("engine_speed_rpm", "engine_torque_Nm"):
            # bins whose mean speed and torque lie off the optimal operating line mix two operating points
            # (mean speed x mean torque is then not the mean power): drop them, when the engine follows its
            # line at all (a real engine that does not keeps all its bins)
            w = la.ch["engine_speed_rpm"] * RPM
            dev = np.abs(np.interp(np.nan_to_num(la.P_e), mp0.P_ool, mp0.w_ool) / np.maximum(w, 1e-9) - 1.0)
            on_ok = ok & (la.mode == ON)
            if on_ok.sum() and np.mean(dev[on_ok] < OOL_TOL) >= 0.5:
                ok &= (la.mode != ON) | (dev < OOL_TOL)
                used["bins"] = "stable bins on the operating line"
        fit.used[lg.label()] = used
        mode.append(la.mode[ok])
        P.append(np.nan_to_num(la.P_e[ok]))
        T.append(T_cl[ok])
        # the coolant as a sensor lagging by SENSOR_LAG_S would have read it: the reading leads by that much
        tt = la.t
        okT = np.isfinite(T_cl)
        TL.append(np.interp(tt + SENSOR_LAG_S, tt[okT], T_cl[okT])[ok] if okT.sum() > 1 else T_cl[ok])
        W.append(W_log[ok])
        seg.append(int(ok.sum()))
    return (np.concatenate(mode).astype(np.int64), np.concatenate(P), np.concatenate(T), np.concatenate(W),
            np.cumsum(seg)[:-1], np.concatenate(TL))


def fit_fuel(logs, base, *, allowed=None) -> SubsystemFit:
    """Fit the warm fuel rate (``eta_ool``), ``W_idle_g_per_s`` and the ``f_cl`` table.

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
        Priors (values and ``prior_sd``).
    allowed : set of str, optional

    Returns
    -------
    SubsystemFit
    """
    import lmfit

    allowed = set(PARAMS) if allowed is None else set(allowed)
    fit = SubsystemFit("fuel", NEEDS)
    names = [n for n in PARAMS if n in allowed and n != "fuel_scale"]
    if not names:
        return fit
    mp0 = base.model_params()
    use = []
    for lg in logs:
        miss = lg.missing(NEEDS)
        if not miss and not log_arrays(lg, mp0).engine_source:
            miss.append("engine operating point (engine_speed_rpm + engine_torque_Nm, or engine_power_W, or "
                        "speed_mps with battery power)")
        if miss:
            fit.skipped[lg.label()] = f"missing channel(s) {', '.join(miss)}"
        else:
            use.append(lg)
    if not use:
        return not_fitted(fit, base, names, "no log has fuel rate, coolant temperature and an engine operating point ("
                          + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
    fit.logs = [lg.label() for lg in use]
    mode, P, T, W, bounds_idx, TL = _gather(use, mp0, fit)
    on, idle = mode == ON, mode == IDLE
    warm_on = int(np.sum(on & (T >= WARM_DEGC)))
    n_idle = int(np.sum(idle))
    pe, pf = base.param("eta_ool"), base.param("f_cl")
    Pbp, eta0 = np.array(pe.x, float), np.array(pe.value, float)
    eta_sd = np.array(prior_sd_of(pe), float)
    Tbp, f0 = np.array(pf.x, float), np.array(pf.value, float)
    f_sd = np.array(prior_sd_of(pf), float)
    rT = f_cl_ref_index(Tbp)
    cold = T < WARM_DEGC
    coverT = hat_basis(T[cold], Tbp).sum(axis=0) if cold.any() else np.zeros(len(Tbp))
    # above the reference: the warm samples near each breakpoint
    coverT[rT + 1:] = (hat_basis(T[~cold], Tbp).sum(axis=0) if (~cold).any() else np.zeros(len(Tbp)))[rT + 1:]
    coverP = hat_basis(P[on], Pbp).sum(axis=0) if on.any() else np.zeros(len(Pbp))
    fit.metrics.update(samples=int(P.size), warm_on_samples=warm_on, idle_samples=n_idle,
                       cold_samples=int(cold.sum()), engine_power_max_W=float(P[on].max()) if on.any() else 0.0)

    # isolated engine-on bins (a power range with fewer than MIN_COVER bins) cannot be told from transients:
    # left out, so the table there follows its prior and its neighbours
    if on.any():
        Hb = hat_basis(P, Pbp)
        support = (Hb > 0) @ (coverP >= MIN_COVER)
        sparse = on & (support == 0)
        if sparse.any():
            keep0 = ~sparse
            fit.metrics["sparse_power_bins_dropped"] = int(sparse.sum())
            sizes = np.diff(np.concatenate([[0], bounds_idx, [mode.size]]))
            seg_id = np.repeat(np.arange(sizes.size), sizes)
            mode, P, T, W, TL = mode[keep0], P[keep0], T[keep0], W[keep0], TL[keep0]
            seg_id = seg_id[keep0]
            bounds_idx = np.cumsum(np.bincount(seg_id, minlength=sizes.size))[:-1]
            on, idle = mode == ON, mode == IDLE
            cold = T < WARM_DEGC
    fit_eta = "eta_ool" in allowed
    fit_idle = "W_idle_g_per_s" in allowed
    fit_fcl = "f_cl" in allowed
    # eta entries from the second breakpoint (the first is at zero power, where the idle floor rules)
    eta_names = [f"eta_{j}" for j in range(1, len(Pbp))] if fit_eta else []
    d_names = [f"d_{j}" for j in range(rT)] if fit_fcl else []
    u_names = [f"u_{j}" for j in range(rT + 1, len(Tbp))] if fit_fcl else []
    d0 = np.maximum(-np.diff(f0), 0.0)  # d0[j]: f0[j] - f0[j + 1]; u_j starts at d0[j - 1]
    prior, psd, bnd = {}, {}, {}
    for j, nm in enumerate(eta_names, start=1):
        prior[nm], psd[nm], bnd[nm] = float(eta0[j]), float(eta_sd[j]), pe.bounds
    if fit_idle:
        pw = base.param("W_idle_g_per_s")
        prior["W_idle_g_per_s"], psd["W_idle_g_per_s"] = float(pw.value), float(prior_sd_of(pw))
        bnd["W_idle_g_per_s"] = pw.bounds
    cand = eta_names + (["W_idle_g_per_s"] if fit_idle else []) + d_names + u_names

    def make_params(init=None):
        ps = lmfit.Parameters()
        for nm in eta_names + (["W_idle_g_per_s"] if fit_idle else []):
            lo, hi = bnd[nm]
            ps.add(nm, value=prior[nm], min=lo, max=hi)
        for j, nm in enumerate(d_names):
            ps.add(nm, value=max(float(d0[j]), 1e-4), min=0.0, max=5.0)
        for j, nm in enumerate(u_names, start=rT + 1):
            # the table's lower bound over the increments above the reference
            ps.add(nm, value=max(float(d0[j - 1]), 2e-3), min=0.0, max=(1.0 - pf.bounds[0]) / max(len(u_names), 1))
        for nm, v in (init or {}).items():
            ps[nm].set(value=float(np.clip(v, ps[nm].min, ps[nm].max)))
        return ps

    def tables(v):
        eta = eta0.copy()
        for j, nm in enumerate(eta_names, start=1):
            eta[j] = v[nm]
        # within the parameter's bounds (the increments alone do not bound their sum)
        f = np.clip(f_cl_from_increments([v[nm] for nm in d_names], [v[nm] for nm in u_names]),
                    *pf.bounds) if fit_fcl else f0
        return eta, f

    def model_of(ps, sP=1.0, dT=0.0, lag=False):
        v = ps.valuesdict()
        eta, f = tables(v)
        mp = compiled_with(mp0, {**v, "eta_ool": eta, "f_cl": f}, ("eta_ool", "f_cl", "W_idle_g_per_s"))
        return fuel_replay(mp, mode, sP * P, (TL if lag else T) + dT)

    def extra(ps):
        v = ps.valuesdict()
        eta, f = tables(v)
        out = []
        if eta_names:
            le = np.log(eta[1:] / eta0[1:])
            out.append(np.diff(le, 2) / SMOOTH_SD)
        if fit_fcl:
            keep = np.arange(len(f)) != rT
            out.append((f[keep] - f0[keep]) / f_sd[keep])
            slope = np.diff(f) / np.diff(Tbp)
            out.append(np.diff(slope) / F_SLOPE_SD)
        return np.concatenate(out) if out else np.zeros(0)

    # residuals in units of their regime's scatter (:func:`_regime_scale`; 1 until the first fit has set it)
    wsc = np.ones(W.size)

    def segments(ps, sW=1.0, **kw):
        return np.split((model_of(ps, **kw) - sW * W) / wsc, bounds_idx)

    jac0 = _jacobian(mode, P, T, Pbp, Tbp, rT, mp0, eta_names, fit_idle, d_names, u_names, f_sd, pf.bounds,
                     tables)

    def jac(ps):
        jd, je = jac0(ps)
        return jd / wsc[:, None], je

    # the fuel rate is not proportional to the engine power: the power's shift by a central difference
    perturbed = [(lambda ps: segments(ps, sP=1.0 + INPUT_REL_SD), lambda ps: segments(ps, sP=1.0 - INPUT_REL_SD)),
                 lambda ps: segments(ps, dT=T_SD),
                 lambda ps: segments(ps, sW=1.0 + FUEL_METER_REL_SD), lambda ps: segments(ps, lag=True)]
    kw = dict(prior=prior, prior_sd=psd, noise_sd=NOISE_G_PER_S, extra=extra, perturbed=perturbed, floor=RESOLUTION_G_PER_S,
              max_tau=MAX_TAU, jac=jac)
    out = map_fit(make_params, segments, cand, **kw,
                  starts=_data_start(mode, P, T, W, mp0, Tbp, rT, eta_names, d_names, u_names, pe.bounds))
    groups = _regime_groups(mode, T, Tbp)
    scale = _regime_scale(np.concatenate(segments(out["params"])), groups)
    if np.any(np.abs(scale - 1.0) > 0.05):
        wsc[:] = scale
        first = {nm: out["values"][nm] for nm in cand}
        out = map_fit(lambda: make_params(first), segments, cand, **kw)
    resid = np.concatenate(segments(out["params"])) * wsc
    resid = resid[np.isfinite(resid)]
    sd = out["noise_sd"] * wsc  # g/s, each bin's regime
    # noise_sd_g_per_s: the root mean square of the bins' sds (one sd for all when no regime stands out)
    fit.metrics.update(rmse_g_per_s=float(np.sqrt(np.mean(resid ** 2))) if resid.size else math.nan,
                       n_eff=out["n_eff"], noise_sd_g_per_s=float(np.sqrt(np.mean(sd ** 2))) if sd.size else math.nan,
                       noise_sd_by_regime_g_per_s=_regime_sd_text(sd, groups, Tbp))
    fit.correlations = {k: v for k, v in out["correl"].items()}
    fit.confounded = confounded_pairs(out["correl"])
    names_cov = out["cov_names"]
    cov = out["cov"]
    ix = {k: i for i, k in enumerate(names_cov)}
    if fit_eta:
        v = out["values"]
        eta, _ = tables({nm: v[nm] for nm in eta_names + d_names + u_names})
        post = np.concatenate([[float(eta_sd[0])], [out["post_sd"][nm] for nm in eta_names]])
        inf = np.concatenate([[0.0], [out["informed"][nm] for nm in eta_names]])
        st = ["estimated" if x >= WEAK_INFORMED else "weak" for x in inf]
        st[0] = "prior"
        covered = [f"{Pbp[j] / 1e3:g}" for j in range(len(Pbp)) if coverP[j] >= MIN_COVER]
        note = (f"warm fuel rate along the operating line; data informed {100 * np.mean(inf[1:]):.0f} % on average; "
                f"breakpoints with >= {MIN_COVER:g} engine-on samples: {', '.join(covered) or 'none'} kW; "
                f"the entry at 0 W is under the idle floor (prior). fuel_scale stays at {mp0.fuel_scale:g}: "
                f"the table carries the level")
        fit.estimates["eta_ool"] = ParamEstimate(
            "eta_ool", [float(x) for x in eta], [float(x) for x in post],
            "estimated" if any(s == "estimated" for s in st) else "weak", note, prior=list(map(float, eta0)),
            entry_status=st, prior_sd=list(map(float, eta_sd)), informed=[float(x) for x in inf])
    if fit_idle:
        fit.estimates["W_idle_g_per_s"] = posterior_estimate("W_idle_g_per_s", out, f"{n_idle} stable idle samples",
                                                              prior["W_idle_g_per_s"])
    if fit_fcl:
        v = out["values"]
        inc = d_names + u_names
        f = tables(v)[1]
        # posterior sd of the entries: f = 1 + M [d, u] (delta method on the joint covariance of the increments)
        M = _f_cl_jacobian(rT, len(Tbp))
        idx = [ix[nm] for nm in inc]
        post = np.sqrt(np.maximum(np.diag(M @ cov[np.ix_(idx, idx)] @ M.T), 0.0))
        jd = [cand.index(nm) for nm in inc]
        ref = np.sqrt(np.maximum(np.diag(M @ out["prior_cov"][np.ix_(jd, jd)] @ M.T), 0.0))
        inf = np.where(ref > 0, np.maximum(0.0, 1.0 - post / np.maximum(ref, 1e-12)), 0.0)
        inf[rT] = 0.0
        st = ["estimated" if x >= WEAK_INFORMED else "weak" for x in inf]
        st[rT] = "fixed"
        keep = np.arange(len(Tbp)) != rT
        reach = [f"{Tbp[j]:g}" for j in range(rT) if coverT[j] >= MIN_COVER]
        reach_hot = [f"{Tbp[j]:g}" for j in range(rT + 1, len(Tbp)) if coverT[j] >= MIN_COVER]
        moved = float(np.max(np.abs((f[keep] - f0[keep]) / f_sd[keep])))
        hot = (f"; above it (may fall below 1), breakpoints with >= {MIN_COVER:g} warm samples: "
               f"{', '.join(reach_hot) or 'none'} degC" if rT + 1 < len(Tbp) else "")
        note = (f"posterior up to {moved:.1f} prior sd from the prior; "
                f"monotone (non-increasing increments), smooth; entry at {Tbp[rT]:g} degC is the warm reference "
                f"(1); breakpoints with >= {MIN_COVER:g} cold samples: {', '.join(reach) or 'none'} degC{hot}")
        fit.metrics["f_cl_hot_weak_degC"] = [float(Tbp[j]) for j in range(rT + 1, len(Tbp)) if st[j] == "weak"]
        fit.estimates["f_cl"] = ParamEstimate(
            "f_cl", [float(x) for x in f], [float(x) for x in post],
            "estimated" if any(s == "estimated" for s in st) else "weak", note, prior=list(map(float, f0)),
            entry_status=st, prior_sd=list(map(float, f_sd)), informed=[float(x) for x in inf])
    if "fuel_scale" in allowed:
        fs = base.param("fuel_scale")
        fit.estimates["fuel_scale"] = ParamEstimate(
            "fuel_scale", float(fs.value), float(prior_sd_of(fs)), "prior",
            "not fitted separately: the warm fuel rate is fitted as the eta_ool table (level and shape)"
            if fit_eta else "not fitted: the warm fuel rate is fitted through eta_ool, which was not selected",
            prior=float(fs.value), prior_sd=float(prior_sd_of(fs)), informed=0.0)
    fit.metrics["warm_fuel_covered_kW"] = [float(Pbp[j] / 1e3) for j in range(len(Pbp)) if coverP[j] >= MIN_COVER]
    fit.metrics["f_cl_covered_degC"] = [float(Tbp[j]) for j in range(len(Tbp)) if coverT[j] >= MIN_COVER]
    if not math.isfinite(out["rmse"]):
        fit.message = "fuel fit had no usable bins"
    return fit
