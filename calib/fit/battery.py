"""Battery fit (docs/model.md s.3 and s.8): U_oc(SOC), R_int(SOC) tables, hysteresis, capacity, R_int(T).

- Tables: the terminal voltage ``V = U_oc(SOC) - R_int(SOC) exp(-tc (T_bat - T_ref)) I`` is linear in the
  table values given SOC, current and temperature. With the piecewise-linear (hat-function) basis
  ``h_j(SOC)`` of the breakpoints, ``V = sum_j h_j U_j - sum_j h_j g I R_j`` is solved by direct linear
  least squares over all logs. Only breakpoints the data covers (sum of hat weights >= 30 samples, and
  for R also a current spread) are unknowns; each estimate is combined with the entry's prior (precision
  weighting); the others are the prior, with the prior sd, flagged weak. The hysteresis ``U_hyst_V`` (``V =
  U_oc - U_hyst sgn(I) - R I``) is one more column, ``-sgn(I)``, fitted when both charging and discharging
  samples are steady; samples within ``I_SIGN_A`` of zero current then leave the fit.
- Logs with battery power and SOC but no current and voltage (:func:`_fit_from_power`): the SOC balance
  of the replay fitted by maximum a posteriori gives the capacity (the energy: OCV x capacity), the level
  of the resistance (a factor on the prior table: the losses quadratic in the current), the hysteresis
  (the losses linear in it) and the resistance's temperature coefficient; the OCV
  table keeps its prior. Where some logs have current and voltage, the tables come from those and the
  power-only logs join the Coulomb counting with their current inferred from the fitted tables.
- Capacity: Coulomb counting (with the current inferred from ``bat_power_W`` and the fitted OCV/resistance
  tables, eq. 1 solved for I, for logs that have power but no current). The logged SOC (0.5 % steps) is regressed on the integrated current,
  ``SOC(t) = SOC0_log - Q(t) / (3600 C_bat)``, one intercept per log and one common slope, over every
  sample of the whole log (the quantisation averages out over long windows; the standard error is
  inflated for the autocorrelated quantisation error).
- Sensor calibration (voltage 0.1 %, current 0.5 %, 1 sd) is added to the table and capacity sd: a bias
  that more data does not average out.
- ``R_int_tc_per_K``: only when the logged battery temperatures span >= 10 K; profile of the table fit's
  residual sum of squares over the coefficient (scipy's bounded scalar minimiser), standard error from its curvature.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize_scalar

from calib.fit.replay import fill_short, gap_limit, known_runs, logged_column
from calib.fit.toolkit import (WEAK_INFORMED, ParamEstimate, SubsystemFit, combine_with_prior, inflation, not_fitted,
                               prior_only, usable_logs)
from calib.model.params import prior_sd_of

NEEDS = ("bat_current_A", "bat_voltage_V", "soc")
PARAMS = ("U_oc_V", "R_int_ohm", "C_bat_Ah", "R_int_tc_per_K", "U_hyst_V")
MIN_COVER = 30.0  # sum of hat weights for a breakpoint to be an unknown
I_SIGN_A = 1.0  # A: samples nearer zero current leave the hysteresis fit (the sign of a noisy current is uncertain)
MIN_T_SPAN = 10.0  # K, for the temperature coefficient
V_CAL_REL_SD = 0.001  # calibration uncertainty (1 sd, relative) of the pack voltage sensor
I_CAL_REL_SD = 0.005  # ... of the current sensor (a gain error scales the Coulomb count)


def hat_basis(x, bp):
    """Matrix (len(x), len(bp)) of piecewise-linear interpolation weights (flat beyond the ends)."""
    x = np.clip(np.asarray(x, float), bp[0], bp[-1])
    j = np.clip(np.searchsorted(bp, x, side="right") - 1, 0, len(bp) - 2)
    w = (x - bp[j]) / (bp[j + 1] - bp[j])
    H = np.zeros((x.size, len(bp)))
    H[np.arange(x.size), j] = 1.0 - w
    H[np.arange(x.size), j + 1] += w
    return H


def _gather(logs, T_ref):
    rows = []
    for lg in logs:
        d = lg.data
        I = d["bat_current_A"].to_numpy(float)
        V = d["bat_voltage_V"].to_numpy(float)
        s = logged_column(lg, "soc")  # the SOC's own samples (crossings between logged values only)
        T = d["bat_temp_degC"].to_numpy(float) if "bat_temp_degC" in d and d["bat_temp_degC"].notna().any() \
            else np.full(I.size, np.nan)
        T_given = np.isfinite(T).any()
        # temperature and SOC are slow regressors: bridged across short gaps, unknown across long ones (those
        # samples leave the table fit); the SOC's own samples stay for the Coulomb counting
        T = fill_short(T, lg.dt) if T_given else np.full(I.size, T_ref)
        rows.append(dict(name=lg.label(), I=I, V=V, soc=s, soc_f=fill_short(s, lg.dt), T=T, T_logged=T_given,
                         dt=lg.dt))
    return rows


def steady(I, tol_A=2.0):
    """Samples whose current differs from both neighbours by < tol_A (+2 %): the 1 s bin means of
    current and voltage then describe the same operating point even when the two channels were sampled
    at different instants."""
    I = np.asarray(I, float)
    ok = np.isfinite(I)
    d = np.full(I.size, np.inf)
    d[1:-1] = np.maximum(np.abs(I[1:-1] - I[:-2]), np.abs(I[2:] - I[1:-1]))
    return ok & (d < tol_A + 0.02 * np.abs(I))


def _table_fit(rows, bpU, bpR, U0, R0, tc, T_ref, varyU, varyR, h=0.0, varyH=False):
    """Linear LS for the table entries flagged in varyU/varyR and, with ``varyH``, the hysteresis ``U_hyst_V``
    (else fixed at ``h``); returns (U, R, cov, resid per log, sse, n, h); the hysteresis is cov's last row."""
    A_parts, y_parts, seg_len = [], [], []
    for r in rows:
        ok = steady(r["I"]) & np.isfinite(r["V"]) & np.isfinite(r["soc_f"]) & np.isfinite(r["T"])
        if varyH:
            ok &= np.abs(r["I"]) > I_SIGN_A
        HU = hat_basis(r["soc_f"][ok], bpU)
        HR = hat_basis(r["soc_f"][ok], bpR)
        gI = (np.exp(-tc * (r["T"][ok] - T_ref)) * r["I"][ok])[:, None]
        sg = np.sign(r["I"][ok])[:, None]
        y = r["V"][ok] - HU[:, ~varyU] @ U0[~varyU] + (HR[:, ~varyR] * gI) @ R0[~varyR] + (0.0 if varyH else h) * sg[:, 0]
        A = np.hstack([HU[:, varyU], -HR[:, varyR] * gI] + ([-sg] if varyH else []))
        A_parts.append(A)
        y_parts.append(y)
        seg_len.append(int(ok.sum()))
    A = np.vstack(A_parts)
    y = np.concatenate(y_parts)
    theta, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ theta
    sse = float(res @ res)
    nu = max(A.shape[0] - A.shape[1], 1)
    s2 = sse / nu
    try:
        cov = s2 * np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        cov = np.full((A.shape[1], A.shape[1]), np.nan)
    segs = np.split(res, np.cumsum(seg_len)[:-1])
    nU = int(varyU.sum())
    U = U0.copy()
    R = R0.copy()
    nR = int(varyR.sum())
    U[varyU] = theta[:nU]
    R[varyR] = theta[nU:nU + nR]
    return U, R, cov, segs, sse, A.shape[0], (float(theta[-1]) if varyH else h)


def _capacity(rows):
    """Common slope 1/(3600 C_Ah) and per-log intercepts: Coulomb counting against logged SOC.

    A quantised SOC signal is exact where it *changes*: between two consecutive samples with different
    values the true SOC crossed the midpoint of the two levels. The regression therefore uses the
    level crossings (midpoint value against the charge integrated up to the crossing, half a sample
    between the two), which spans the whole log (a long window) and is free of the quantisation error;
    for an unquantised signal every sample is a crossing and this is ordinary Coulomb counting.
    """
    X_parts, y_parts, segs_len = [], [], []
    # the charge is counted only across the current's short gaps: a long one ends a run, and each run has
    # its own intercept (the charge moved in the gap is unknown)
    runs = []
    for r in rows:
        I = fill_short(r["I"], r["dt"])
        runs += [(r, I, a, b) for a, b in known_runs(np.isfinite(I), 2)]
    L = len(runs)
    n_cross = 0
    for i, (r, I, a, b) in enumerate(runs):
        Ir = I[a:b]
        Q = np.concatenate([[0.0], np.cumsum(0.5 * (Ir[1:] + Ir[:-1]) * r["dt"])])  # A s
        s = r["soc"][a:b]
        k, k2 = soc_crossings(s, r["dt"])
        if k.size < 3:
            continue
        yv = 0.5 * (s[k] + s[k2])
        Qc = 0.5 * (Q[k] + Q[k2])
        X = np.zeros((k.size, L + 1))
        X[:, i] = 1.0
        X[:, L] = -Qc / 3600.0  # slope b = 1/C_Ah
        X_parts.append(X)
        y_parts.append(yv)
        segs_len.append(k.size)
        n_cross += k.size
    if not X_parts:
        return None, None, None, None, 0, L
    X = np.vstack(X_parts)
    y = np.concatenate(y_parts)
    keep = np.any(X[:, :L] != 0, axis=0).tolist() + [True]
    X = X[:, keep]
    theta, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ theta
    nu = max(X.shape[0] - X.shape[1], 1)
    s2 = float(res @ res) / nu
    try:
        cov = s2 * np.linalg.inv(X.T @ X)
    except np.linalg.LinAlgError:
        return None, None, None, None, n_cross, L
    segs = np.split(res, np.cumsum(segs_len)[:-1])
    f = inflation(segs, X.shape[1])
    b, sb = theta[-1], math.sqrt(cov[-1, -1]) * f
    return b, sb, segs, f, n_cross, L


def soc_crossings(s, dt=1.0):
    """Pairs ``(k, k2)`` of consecutive logged SOC samples (``k2`` the next finite bin after ``k``, at most
    the SOC's short-gap limit later, :func:`calib.fit.replay.gap_limit`) whose values differ: the SOC crossed
    the midpoint of the two levels between them. For a SOC logged in every bin these are neighbours; for one
    polled every few seconds, the samples either side of each poll interval."""
    s = np.asarray(s, float)
    f = np.flatnonzero(np.isfinite(s))
    if f.size < 2:
        return np.zeros(0, int), np.zeros(0, int)
    k, k2 = f[:-1], f[1:]
    keep = (s[k2] != s[k]) & ((k2 - k) * dt <= gap_limit(s, dt) + 1e-9)
    return k[keep], k2[keep]


def _join_prior(U, U0, est):
    """Table with estimated entries, and undetermined ones at the prior unless that breaks monotonicity,
    in which case the prior's shape is shifted to join the nearest estimated entry (interior gaps are
    interpolated)."""
    out = np.where(est, U, U0).astype(float)
    e = np.flatnonzero(est)
    e0, e1 = e[0], e[-1]
    if np.any(U0[e1 + 1:] < U[e1]):
        out[e1 + 1:] = U0[e1 + 1:] + (U[e1] - U0[e1])
    if np.any(U0[:e0] > U[e0]):
        out[:e0] = U0[:e0] + (U[e0] - U0[e0])
    for a, b in zip(e[:-1], e[1:]):
        if b > a + 1 and np.any(np.diff(out[a:b + 1]) < 0):
            out[a + 1:b] = np.interp(np.arange(a + 1, b), [a, b], [U[a], U[b]])
    return np.maximum.accumulate(out)


def fit_battery(logs, base, *, allowed=None) -> SubsystemFit:
    """Fit the battery parameters from every log with current, voltage and SOC.

    Parameters
    ----------
    logs : list of DriveLog
    base : ParameterSet
        Priors (values and ``prior_sd``).
    allowed : set of str, optional
        Parameters that may be estimated (default all of :data:`PARAMS`).

    Returns
    -------
    SubsystemFit
    """
    allowed = set(PARAMS) if allowed is None else set(allowed)
    fit = SubsystemFit("battery", NEEDS)
    use, fit.skipped = usable_logs(logs, NEEDS, "fit the battery")
    names = [n for n in PARAMS if n in allowed]
    if not names:
        return fit
    if not use:
        rows = _power_rows(logs, base, fit)
        if not rows:
            return not_fitted(fit, base, names, "no log has battery current, voltage and SOC, nor battery power and "
                              "SOC (" + "; ".join(f"{k}: {v}" for k, v in fit.skipped.items()) + ")")
        _fit_from_power(fit, rows, base, names)
        return fit
    inferred = _inferred_current_rows(logs, use, base, fit) if "C_bat_Ah" in allowed else []
    fit.logs = [lg.label() for lg in use] + [r["name"] for r in inferred]
    for lg in use:
        fit.used[lg.label()] = {"current": "bat_current_A", "voltage": "bat_voltage_V", "soc": "soc"}
        n_gap = int((~np.isfinite(fill_short(lg.data["bat_current_A"].to_numpy(float), lg.dt))).sum())
        if n_gap:
            fit.used[lg.label()]["left out"] = (f"{n_gap * lg.dt:.0f} s where the current is unknown (no sample within "
                                                "its short-gap limit): no charge is counted there")
    T_ref = float(base["T_bat_ref_degC"])
    rows = _gather(use, T_ref)
    pU, pR = base.param("U_oc_V"), base.param("R_int_ohm")
    bpU, bpR = np.array(pU.x), np.array(pR.x)
    U0, R0 = np.array(pU.value, float), np.array(pR.value, float)
    tc = float(base["R_int_tc_per_K"])
    # coverage
    oks = [np.isfinite(r["soc_f"]) & np.isfinite(r["V"]) & steady(r["I"]) & np.isfinite(r["T"]) for r in rows]
    socs = np.concatenate([r["soc_f"][ok] for r, ok in zip(rows, oks)])
    Is = np.concatenate([r["I"][ok] for r, ok in zip(rows, oks)])
    coverU = hat_basis(socs, bpU).sum(axis=0)
    HR = hat_basis(socs, bpR)
    coverR = HR.sum(axis=0)
    spreadR = np.sqrt((HR * Is[:, None] ** 2).sum(axis=0) / np.maximum(coverR, 1e-9))
    fitU = "U_oc_V" in allowed
    fitR = "R_int_ohm" in allowed
    varyU = (coverU >= 1.0) & fitU
    varyR = (coverR >= 1.0) & (spreadR >= 1.0) & fitR
    whyU = {j: f"SOC {bpU[j]:g} not covered by the data (hat weight {coverU[j]:.1f} < {MIN_COVER:g})"
            for j in range(len(bpU)) if not varyU[j]}
    whyR = {j: f"SOC {bpR[j]:g} not covered (hat weight {coverR[j]:.1f}, rms current {spreadR[j]:.1f} A)"
            for j in range(len(bpR)) if not varyR[j]}
    # hysteresis: a step of the terminal voltage where the current changes sign, so it needs both
    h0 = float(base["U_hyst_V"])
    n_dis, n_chg = int((Is > I_SIGN_A).sum()), int((Is < -I_SIGN_A).sum())
    varyH = "U_hyst_V" in allowed and min(n_dis, n_chg) >= MIN_COVER
    tf = lambda c: _table_fit(rows, bpU, bpR, U0, R0, c, T_ref, varyU, varyR, h0, varyH)  # noqa: E731

    # temperature coefficient (profile), only with a wide enough temperature span
    T_all = np.concatenate([r["T"][np.isfinite(r["T"])] for r in rows])
    T_span = float(np.nanmax(T_all) - np.nanmin(T_all)) if any(r["T_logged"] for r in rows) else 0.0
    tc_est = None
    tc_sd = float(prior_sd_of(base.param("R_int_tc_per_K")))
    if "R_int_tc_per_K" in allowed:
        if not any(r["T_logged"] for r in rows):
            fit.estimates["R_int_tc_per_K"] = prior_only(
                "R_int_tc_per_K", tc, tc_sd, "no battery temperature logged: tables fitted at T_ref assumed")
        elif T_span < MIN_T_SPAN:
            fit.estimates["R_int_tc_per_K"] = prior_only(
                "R_int_tc_per_K", tc, tc_sd, f"battery temperature spans {T_span:.1f} K < {MIN_T_SPAN:g} K")
        else:
            lo, hi = base.param("R_int_tc_per_K").bounds
            sse = lambda c: tf(c)[4]  # noqa: E731
            c = float(minimize_scalar(sse, bounds=(lo, min(hi, 0.08)), method="bounded",
                                      options={"xatol": 1e-10}).x)
            h = max(1e-4, 0.02 * abs(c))
            U_, R_, cov_, segs_, s0, n0, _ = tf(c)
            curv = (sse(c + h) - 2 * s0 + sse(c - h)) / h ** 2
            s2 = s0 / max(n0 - int(varyU.sum() + varyR.sum() + varyH) - 1, 1)
            se = math.sqrt(2 * s2 / curv) * inflation(segs_, 1) if curv > 0 else None
            e = combine_with_prior("R_int_tc_per_K", c, se, tc, tc_sd, f"battery temperature span {T_span:.0f} K",
                                   bounds=base.param("R_int_tc_per_K").bounds)
            fit.estimates["R_int_tc_per_K"] = e
            if e.status == "estimated":
                tc_est = float(e.value)
    tc_use = tc_est if tc_est is not None else tc

    # tables: every entry the data touches is an unknown (so a poorly covered neighbour left at its
    # prior cannot bias the others); each is then judged, and undetermined ones are reported at the prior.
    U, R, cov, segs, sse_, n, H = tf(tc_use)
    f = inflation(segs, int(varyU.sum() + varyR.sum() + varyH))
    se_all = np.sqrt(np.clip(np.diag(cov), 0, None)) * f if cov.size else np.array([])
    nU = int(varyU.sum())
    seU = np.full(len(bpU), np.nan)
    seR = np.full(len(bpR), np.nan)
    seU[varyU] = se_all[:nU]
    seR[varyR] = se_all[nU:nU + int(varyR.sum())]
    seH = float(se_all[-1]) if varyH else float("nan")
    if tc_est is not None:  # the tables are conditional on tc: add its uncertainty
        se_tc = fit.estimates["R_int_tc_per_K"].stderr
        h = max(1e-5, 0.05 * se_tc)
        U2, R2, *_, H2 = tf(tc_use + h)
        seU = np.sqrt(seU ** 2 + ((U2 - U) / h * se_tc) ** 2)
        seR = np.sqrt(seR ** 2 + ((R2 - R) / h * se_tc) ** 2)
        seH = math.hypot(seH, (H2 - H) / h * se_tc)
    # calibration of the voltage and current sensors (V_CAL_REL_SD, I_CAL_REL_SD): a bias the amount of
    # data does not average out
    seU = np.sqrt(seU ** 2 + (V_CAL_REL_SD * U) ** 2)
    seR = np.sqrt(seR ** 2 + (np.hypot(V_CAL_REL_SD, I_CAL_REL_SD) * R) ** 2)
    estU, estR = varyU.copy(), varyR.copy()
    # entries the data barely touch (hat weight < MIN_COVER samples) keep the prior: a regression on a
    # handful of samples has an unreliable standard error; the others are combined with their prior
    for j in np.flatnonzero(varyU):
        if coverU[j] < MIN_COVER or not np.isfinite(seU[j]):
            estU[j] = False
            whyU[j] = f"SOC {bpU[j]:g}: hat weight {coverU[j]:.1f} < {MIN_COVER:g} samples"
    for j in np.flatnonzero(varyR):
        if coverR[j] < MIN_COVER or not np.isfinite(seR[j]):
            estR[j] = False
            whyR[j] = f"SOC {bpR[j]:g}: hat weight {coverR[j]:.1f} < {MIN_COVER:g} samples"
    for _ in range(len(bpU)):  # estimated U_oc entries must not decrease: revert the less certain one
        e = np.flatnonzero(estU)
        bad = [(e[i], e[i + 1]) for i in range(e.size - 1) if U[e[i + 1]] < U[e[i]]]
        if not bad:
            break
        k = max(bad[0], key=lambda k: seU[k])
        estU[k] = False
        whyU[k] = f"SOC {bpU[k]:g}: estimate {U[k]:.2f} V breaks the monotonicity of U_oc"
    U_fill = _join_prior(U, U0, estU) if estU.any() else U0.copy()
    shifted = [j for j in range(len(bpU)) if not estU[j] and abs(U_fill[j] - U0[j]) > 1e-9]
    if shifted:
        whyU["shift"] = ("U_oc must not decrease with SOC, so undetermined entries at SOC "
                         + ", ".join(f"{bpU[j]:g}" for j in shifted)
                         + " keep the prior's shape shifted to join the nearest estimated entry (still undetermined)")
    varyU, varyR = estU, estR
    fit.metrics.update(table_rmse_V=math.sqrt(sse_ / max(n, 1)), table_samples=n, se_inflation=f,
                       soc_min=float(socs.min()), soc_max=float(socs.max()), bat_temp_span_K=T_span)

    def table_est(name, vals, prior, se, vary, why, fill=None):
        # per entry: the regression estimate combined with the entry's Gaussian prior (precision-weighted);
        # entries the data does not reach are the prior (or the prior's shape joined to the estimates)
        # with the prior sd
        psd = np.array(prior_sd_of(base.param(name)), float)
        fill = prior if fill is None else fill
        val, ses, inf, st = [], [], [], []
        for j, v in enumerate(vals):
            if vary[j] and np.isfinite(se[j]) and se[j] > 0:
                w1, w0 = 1.0 / se[j] ** 2, 1.0 / psd[j] ** 2
                val.append(float((w1 * v + w0 * prior[j]) / (w1 + w0)))
                ses.append(float(math.sqrt(1.0 / (w1 + w0))))
            else:
                val.append(float(fill[j]))
                ses.append(float(psd[j]))
            inf.append(max(0.0, 1.0 - ses[-1] / psd[j]))
            st.append("estimated" if inf[-1] >= WEAK_INFORMED else "weak")
        if name == "U_oc_V":
            val = list(np.maximum.accumulate(val))
        status = "estimated" if "estimated" in st else "weak"
        keys = sorted(k for k in why if not isinstance(k, str))
        note = ("entries not determined: " + "; ".join(why[j] for j in keys)) if keys else ""
        if "shift" in why:
            note += ". " + why["shift"]
        return ParamEstimate(name, val, ses, status, note, prior=list(map(float, prior)), entry_status=st,
                             prior_sd=list(map(float, psd)), informed=inf)

    if "U_hyst_V" in allowed:
        hsd = float(prior_sd_of(base.param("U_hyst_V")))
        if varyH and np.isfinite(seH):
            # the voltage sensor's calibration does not reach a step at the sign change; the current's gain
            # error scales R I only
            e = combine_with_prior("U_hyst_V", H, seH, h0, hsd, f"terminal voltage step where the current changes "
                                   f"sign ({n_dis} discharging, {n_chg} charging steady samples)",
                                   bounds=base.param("U_hyst_V").bounds)
            fit.estimates["U_hyst_V"] = e
        else:
            fit.estimates["U_hyst_V"] = prior_only(
                "U_hyst_V", h0, hsd, f"too few steady samples on one side of zero current ({n_dis} discharging, "
                f"{n_chg} charging; {MIN_COVER:g} needed)")
    if fitU:
        fit.estimates["U_oc_V"] = table_est("U_oc_V", U, U0, seU, varyU, whyU, fill=U_fill)
    if fitR:
        fit.estimates["R_int_ohm"] = table_est("R_int_ohm", R, R0, seR, varyR, whyR)

    if "C_bat_Ah" in allowed:
        if inferred:  # logs with power only: their current from the tables just fitted
            fitted = {n: fit.estimates[n].value for n in ("U_oc_V", "R_int_ohm", "U_hyst_V") if n in fit.estimates}
            inferred = _inferred_current_rows(logs, use, base.with_values(**fitted), fit, "fitted")
        _fit_capacity(fit, rows, inferred, base)
    return fit


def _fit_capacity(fit, rows, inferred, base):
    """C_bat by Coulomb counting over the logs with current (and those with current inferred from power)."""
    Cp = float(base["C_bat_Ah"])
    b, sb, segs, fcap, n_cross, n_runs = _capacity(rows + inferred)
    span = max((np.nanmax(r["soc"]) - np.nanmin(r["soc"])) for r in rows + inferred)
    Csd = float(prior_sd_of(base.param("C_bat_Ah")))
    if b is None or not (b > 0):
        fit.estimates["C_bat_Ah"] = prior_only("C_bat_Ah", Cp, Csd, "Coulomb counting gave no positive slope")
    else:
        C = 1.0 / b
        se = math.hypot(C * sb / b, I_CAL_REL_SD * C)
        fit.metrics.update(capacity_soc_span=float(span), capacity_se_inflation=fcap,
                           capacity_soc_crossings=n_cross, capacity_runs=n_runs)
        src = "Coulomb counting" + (f" (current inferred from bat_power_W and the OCV/resistance tables in "
                                    f"{len(inferred)} log(s))" if inferred else "")
        restart = (f"; the count restarts after {n_runs - len(rows + inferred)} long gap(s) of the current, each run "
                   "with its own initial SOC" if n_runs > len(rows + inferred) else "")
        fit.estimates["C_bat_Ah"] = combine_with_prior("C_bat_Ah", C, se, Cp, Csd,
                                                       f"{src} over SOC span {span:.3f} ({n_cross} level crossings)"
                                                       f"{restart}", bounds=base.param("C_bat_Ah").bounds)


def _inferred_current_rows(logs, use, base, fit, which="prior"):
    """Rows for Coulomb counting from logs with battery power and SOC but no current: the current is eq. 1
    solved for I with the OCV/resistance tables of ``base`` (``which``: prior or fitted; stated in
    ``fit.used``)."""
    from calib.fit.replay import current_from_power, log_arrays

    mp = base.model_params()
    names = {lg.label() for lg in use}
    out = []
    for lg in logs:
        if lg.label() in names or not lg.has("soc") or lg.has("bat_current_A"):
            continue
        la = log_arrays(lg, mp, cabin_balance=False)
        if not la.battery_source:
            continue
        T_logged = bool(np.isfinite(la.ch["bat_temp_degC"]).any())
        T = fill_short(la.ch["bat_temp_degC"], la.dt) if T_logged else np.full(la.t.size, mp.T_bat_ref)
        soc_f = fill_short(la.ch["soc"], la.dt)
        I = current_from_power(mp, np.nan_to_num(soc_f, nan=0.6), np.nan_to_num(la.P_bat), np.nan_to_num(T, nan=mp.T_bat_ref))
        # no current where its power, SOC or temperature is unknown (a long gap): the charge count stops there
        I[~(np.isfinite(la.P_bat) & np.isfinite(soc_f) & np.isfinite(T))] = np.nan
        out.append(dict(name=lg.label(), I=I, V=np.full(I.size, np.nan), soc=la.logged("soc"), soc_f=soc_f, T=T,
                        T_logged=False, dt=lg.dt))
        fit.used[lg.label()] = {"current": f"inferred from {la.battery_source} and the {which} OCV/resistance "
                                           "tables (capacity only)", "soc": "soc"}
        fit.skipped.pop(lg.label(), None)
    return out


# ------------------------------------------------------------------------------------------------
# logs with battery power and SOC but no current or voltage
# ------------------------------------------------------------------------------------------------
#: What the SOC balance of power-only logs fits (``R_scale``: a factor on the prior resistance table).
BALANCE = ("C_bat_Ah", "R_scale", "R_int_tc_per_K", "U_hyst_V")
#: A priori sd of the logged SOC at its level crossings (the fit re-estimates it from the residuals).
SOC_NOISE_SD = 0.002


def _power_rows(logs, base, fit):
    """Rows for the power/SOC balance: logs with battery power (logged, as the replay takes it) and SOC."""
    from calib.fit.replay import log_arrays

    mp = base.model_params()
    out = []
    for lg in logs:
        if not lg.has("soc"):
            continue
        la = log_arrays(lg, mp, cabin_balance=False)
        if not la.battery_source or not np.isfinite(la.P_bat).any():
            continue
        T_logged = bool(np.isfinite(la.ch["bat_temp_degC"]).any())
        T = fill_short(la.ch["bat_temp_degC"], la.dt) if T_logged else np.full(la.t.size, mp.T_bat_ref)
        soc_f = fill_short(la.ch["soc"], la.dt)
        # the SOC balance integrates the current only across short gaps of its inputs: each run of known power,
        # SOC and temperature is its own row, with its own initial SOC
        runs = known_runs(np.isfinite(la.P_bat) & np.isfinite(soc_f) & np.isfinite(T), 2)
        for a, b in runs:
            out.append(dict(name=lg.label(), P=la.P_bat[a:b], soc=la.logged("soc")[a:b], soc_f=soc_f[a:b], T=T[a:b],
                            T_logged=T_logged, dt=float(lg.dt), source=la.battery_source,
                            left_out_s=float((la.t.size - sum(y - x for x, y in runs)) * la.dt)))
        if runs:
            fit.skipped.pop(lg.label(), None)
    return out


def current_from_power_table(P, soc, T, base, R_scale=1.0, tc=None, U_h=None):
    """Eq. 1 solved for the current (vectorised) with the OCV table of ``base`` and its resistance table
    scaled by ``R_scale``; where the power exceeds what the pack can give (``U^2 < 4 R P``) the current is
    ``P / U``, as in the validation replay (:func:`calib.fit.replay.full_replay`)."""
    pU, pR = base.param("U_oc_V"), base.param("R_int_ohm")
    tc = float(base["R_int_tc_per_K"]) if tc is None else tc
    U = np.interp(soc, pU.x, pU.value)
    R = R_scale * np.interp(soc, pR.x, pR.value) * np.exp(-tc * (T - float(base["T_bat_ref_degC"])))
    from calib.model.equations import battery_current_array

    U, R, P = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (U, R, P)))
    flat = [np.ascontiguousarray(a).ravel() for a in (U, R, P)]
    I = battery_current_array(*flat, float(base["U_hyst_V"]) if U_h is None else U_h).reshape(U.shape)
    return np.where(np.isnan(I), P / U, I)


def _fit_from_power(fit, rows, base, names):
    """Capacity, effective resistance and its temperature coefficient from battery power and logged SOC.

    The SOC balance of the replay, ``SOC(t) = SOC_0 - sum I(P, SOC, T) dt / (3600 C_bat)`` with ``I`` from eq.
    1, is fitted to the logged SOC at its level crossings (exact for a quantised signal, see
    :func:`_capacity`), with one initial SOC per log (nuisance), by :func:`calib.fit.toolkit.map_fit`. The net
    charge moved is ``~ (integral P dt + R / U^2 integral P^2 dt) / U``: the first term (signed) determines the
    energy capacity, the second (always positive) the losses, so the two separate when the battery is
    both charged and discharged. Only the level of the resistance is identifiable (a factor on the prior
    table; its SOC shape stays the prior's), and only the product of OCV and capacity (the energy), so the
    OCV table keeps its prior and ``C_bat_Ah`` is the capacity at that OCV.
    """
    from calib.fit.toolkit import INPUT_REL_SD, confounded_pairs, map_fit, posterior_estimate

    import lmfit

    fit.logs = list(dict.fromkeys(r["name"] for r in rows))
    for r in rows:
        fit.used[r["name"]] = {"power": r["source"], "soc": "soc",
                               "current": f"inferred from {r['source']} by eq. 1 solved for I (prior OCV table, fitted "
                                          "resistance level and hysteresis)", "battery temperature": "bat_temp_degC" if r["T_logged"]
                               else "not logged: T_bat_ref assumed"}
        if r["left_out_s"] > 0:
            fit.used[r["name"]]["left out"] = (f"{r['left_out_s']:.0f} s where the battery power, SOC or temperature is "
                                               "unknown (no sample within its short-gap limit); the SOC balance restarts "
                                               "after each such gap")
    pR = base.param("R_int_ohm")
    R0 = np.array(pR.value, float)
    R_rel_sd = float(np.median(np.array(prior_sd_of(pR), float) / R0))
    Rlo, Rhi = pR.bounds
    tc0 = float(base["R_int_tc_per_K"])
    tc_sd = float(prior_sd_of(base.param("R_int_tc_per_K")))
    C0 = float(base["C_bat_Ah"])
    C_sd = float(prior_sd_of(base.param("C_bat_Ah")))
    h0 = float(base["U_hyst_V"])
    h_sd = float(prior_sd_of(base.param("U_hyst_V")))
    T_logged = any(r["T_logged"] for r in rows)
    vary = {"C_bat_Ah": "C_bat_Ah" in names, "R_scale": "R_int_ohm" in names,
            "R_int_tc_per_K": "R_int_tc_per_K" in names and T_logged, "U_hyst_V": "U_hyst_V" in names}
    prior = {"C_bat_Ah": C0, "R_scale": 1.0, "R_int_tc_per_K": tc0, "U_hyst_V": h0}
    psd = {"C_bat_Ah": C_sd, "R_scale": R_rel_sd, "R_int_tc_per_K": tc_sd, "U_hyst_V": h_sd}
    bounds = {"C_bat_Ah": base.param("C_bat_Ah").bounds, "R_scale": (Rlo / R0.min(), Rhi / R0.max()),
              "R_int_tc_per_K": base.param("R_int_tc_per_K").bounds, "U_hyst_V": base.param("U_hyst_V").bounds}
    cand = [n for n in BALANCE if vary[n]]
    for r in rows:
        s = r["soc"]
        k, k2 = soc_crossings(s, r["dt"])
        r["k"], r["k2"], r["y"] = k, k2, 0.5 * (s[k] + s[k2])
    rows = [r for r in rows if r["k"].size >= 3]
    if not rows or not cand:
        fit.logs = []
        not_fitted(fit, base, names, "the logged SOC never changes level (fewer than 3 level crossings in every log)"
                   if not rows else "none of C_bat_Ah, R_int_ohm, R_int_tc_per_K, U_hyst_V may vary")
        return

    def make_params():
        ps = lmfit.Parameters()
        for n in BALANCE:
            # a start exactly on a bound (U_hyst_V's prior 0) stalls lmfit's bound transform: step inside
            v0 = min(max(prior[n], bounds[n][0] + 0.01 * psd[n]), bounds[n][1] - 0.01 * psd[n])
            ps.add(n, value=v0, min=bounds[n][0], max=bounds[n][1], vary=vary[n])
        for i, r in enumerate(rows):
            ps.add(f"soc0_{i}", value=float(r["y"][0]), min=0.0, max=1.0)
        return ps

    def segments(ps, gain=1.0):
        v = ps.valuesdict()
        out = []
        for i, r in enumerate(rows):
            I = current_from_power_table(gain * r["P"], r["soc_f"], r["T"], base, v["R_scale"], v["R_int_tc_per_K"],
                                         v["U_hyst_V"])
            Q = np.concatenate([[0.0], np.cumsum(I[:-1] * r["dt"])])  # A s, as the replay steps
            out.append(v[f"soc0_{i}"] - 0.5 * (Q[r["k"]] + Q[r["k2"]]) / (3600.0 * v["C_bat_Ah"]) - r["y"])
        return out

    out = map_fit(make_params, segments, cand, prior={n: prior[n] for n in cand}, prior_sd={n: psd[n] for n in cand},
                  noise_sd=SOC_NOISE_SD, perturbed=[lambda ps: segments(ps, 1.0 + INPUT_REL_SD)], floor=1e-4)
    src = (f"SOC balance of battery power ({', '.join(sorted({r['source'] for r in rows}))}) against the logged "
           f"SOC over {len({r['name'] for r in rows})} log(s), {sum(r['k'].size for r in rows)} SOC level crossings")
    ps = out["params"]
    if "C_bat_Ah" in names:
        fit.estimates["C_bat_Ah"] = (posterior_estimate("C_bat_Ah", out, src + "; capacity at the prior OCV table "
                                                        "(the balance determines the energy, OCV x capacity)", C0)
                                     if vary["C_bat_Ah"] else prior_only("C_bat_Ah", C0, C_sd, "not allowed to vary"))
    if "R_int_ohm" in names:
        if vary["R_scale"]:
            e = posterior_estimate("R_scale", out, "", 1.0)
            sc, sd_sc = float(ps["R_scale"].value), out["post_sd"]["R_scale"]
            st = e.status
            fit.estimates["R_int_ohm"] = ParamEstimate(
                "R_int_ohm", list(map(float, sc * R0)), list(map(float, sd_sc * R0)), st,
                f"{src}; effective resistance (all losses between terminal power and SOC): the prior table scaled by "
                f"{sc:.3f} +- {sd_sc:.3f} (its SOC shape is the prior's: power and SOC do not separate it); {e.note}",
                prior=list(map(float, R0)), entry_status=[st] * len(R0), prior_sd=list(map(float, prior_sd_of(pR))),
                informed=[float(e.informed)] * len(R0))
        else:
            fit.estimates["R_int_ohm"] = prior_only("R_int_ohm", list(R0), prior_sd_of(pR), "not allowed to vary")
    if "R_int_tc_per_K" in names:
        fit.estimates["R_int_tc_per_K"] = (
            posterior_estimate("R_int_tc_per_K", out, src, tc0) if vary["R_int_tc_per_K"]
            else prior_only("R_int_tc_per_K", tc0, tc_sd, "no battery temperature logged"))
    if "U_hyst_V" in names:
        fit.estimates["U_hyst_V"] = posterior_estimate(
            "U_hyst_V", out, src + "; the losses linear in |I| (R_int's are quadratic): discharge and charge at "
            "several power levels separate the two", h0)
    if "U_oc_V" in names:
        pU = base.param("U_oc_V")
        fit.estimates["U_oc_V"] = ParamEstimate(
            "U_oc_V", pU.value, prior_sd_of(pU), "prior", "not fitted: no log has battery voltage; with power and SOC "
            "only the energy (OCV x capacity) is determined, so the OCV table keeps its prior and C_bat_Ah is the "
            "capacity at it", prior=pU.value, prior_sd=prior_sd_of(pU), informed=[0.0] * len(pU.value))
    fit.correlations = {k: v for k, v in out["correl"].items()}
    fit.confounded = confounded_pairs(out["correl"])
    U_mid = float(np.interp(0.6, base.param("U_oc_V").x, base.param("U_oc_V").value))
    fit.metrics.update(soc_balance_rmse=out["rmse"], soc_balance_noise_sd=out["noise_sd"], soc_crossings=out["n"],
                       soc_crossings_eff=out["n_eff"], R_scale=float(ps["R_scale"].value),
                       energy_capacity_kWh_at_soc_0_6=float(ps["C_bat_Ah"].value) * U_mid / 1000.0)
