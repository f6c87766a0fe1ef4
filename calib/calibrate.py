"""Calibration: identify the model of spec/model.md from drive logs, with uncertainty and validation.

:func:`calibrate` runs one fitter per subsystem over all logs that carry the channels it declares in
``NEEDS`` (one residual vector across logs), merges the estimates into a
:class:`calib.params.ParameterSet` and validates the result on held-out logs (:mod:`calib.validate`):

========================  ==========================================================================
:mod:`calib.fit_battery`  ``U_oc_V``, ``R_int_ohm`` tables (direct linear least squares on the table
                          values, hat-function basis), ``C_bat_Ah`` (Coulomb counting against logged
                          SOC), ``R_int_tc_per_K`` (profile over the coefficient, when the battery
                          temperature spans >= 10 K)
:mod:`calib.fit_fuel`     ``fuel_scale``, ``W_idle_g_per_s``, ``f_cl`` (lmfit on stable 1 s bins)
:mod:`calib.fit_thermal`  ``kappa`` (bay temperature, linear), ``C_eng_J_per_K``, ``gamma_exh``,
                          ``hA_eng_W_per_K``, ``T_open_degC``, ``k_rad_W_per_K`` (output error)
:mod:`calib.fit_cabin`    ``C_cab_J_per_K``, ``UA_cab_W_per_K``, ``Q_sun_W`` (output error),
                          ``eps_hc`` (vent temperature where the heater-core limit binds)
========================  ==========================================================================

Uncertainty
-----------
Standard errors come from the fit's covariance (lmfit ``leastsq``: ``s^2 (J^T J)^-1``), and then:

- **inflated for correlated residuals**: output-error and quantised residuals are strongly
  autocorrelated, so the number of independent samples is ``n_eff = sum_logs n / tau`` with ``tau`` the
  larger of the integrated autocorrelation time and a batch-means estimate (:func:`neff`); every standard
  error is multiplied by ``sqrt(n / n_eff)``;
- **plus the calibration uncertainty of the logged inputs** (heater power, fuel rate, engine power:
  :data:`INPUT_REL_SD` = 1 %; temperature sensors: 0.5 K offset): each input is moved by one sd, the fit
  repeated, and the shift of every estimate added in quadrature;
- **plus the prior uncertainty of parameters held at their prior** (:data:`PRIOR_REL_SD` = 25 % of the
  value, or the absolute :data:`PRIOR_ABS_SD`), propagated the same way, so that an estimate leaning on a
  doubtful prior is judged with that doubt.

Confidence intervals (lmfit ``conf_interval``, F-test on the profile) of the key thermal and cabin
parameters (:data:`KEY_PARAMETERS`) use the same ``n_eff`` (``nfree`` is set to ``n_eff - nvarys``).

Identifiability criteria (a parameter is *determined* only if all hold)
-----------------------------------------------------------------------
1. Enough data in its regime: e.g. >= 60 warm engine-on samples for ``fuel_scale``, >= 30 sample-weights
   (sum of the hat-function weights) for a table breakpoint, coolant above the fitted thermostat
   temperature for >= 120 s for ``T_open``/``k_rad``, a battery temperature span >= 10 K for the
   resistance temperature coefficient, a log with the engine-bay temperature for ``kappa``.
2. A finite standard error (non-singular covariance: the data is sensitive to it).
3. Relative standard error <= :data:`REL_SE_MAX` = 1/30, i.e. the 3-sigma interval lies within +-10 %
   of the value (the accuracy the issue asks of an identified parameter). Table entries of ``U_oc_V``
   must in addition have a standard error <= :data:`U_OC_SE_MAX_V` (the whole table spans only ~20 V).
   A parameter whose true value is near zero (``Q_sun_W``) therefore cannot be reported as determined.
4. Not nearly collinear with another fitted parameter: ``|corr| > CORR_MAX = 0.999`` flags the less
   precise of the two unless its relative standard error is below ``REL_SE_MAX / 2`` (the standard errors
   already account for correlation; this catches fits where only a combination is determined).
5. Not stuck at a bound.

A parameter failing any of these is *undetermined*: it keeps its prior value, its status is
``undetermined``, it has no standard error, and its note says which criterion failed. In the
output-error and fuel fits it stays free in the fit as a nuisance parameter (so a wrong prior cannot bias
the others, and their standard errors include the correlation with it); a parameter with no sensitivity
at all, stuck at a bound, or without data in its regime (criterion 1) is held at its prior instead (with
its prior uncertainty propagated, above). Note the consequence: the calibrated set then combines
estimates with priors, and a held-out log that exercises an undetermined parameter is predicted with
its prior (the validation metrics show it). Parameters of a subsystem whose channels no log carries keep
status ``prior`` with a note naming the missing channels. Fixed parameters (``fix=``) keep status
``fixed``.

``hA_eng_W_per_K`` and ``kappa`` enter the coolant equation only as ``hA_eng (1 - kappa)`` unless a log
carries the engine-bay temperature. Without it, ``kappa`` stays at its prior and ``hA_eng`` is reported
as the value that, *with that kappa*, reproduces the identified product; its note says so.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field

import numpy as np

REL_SE_MAX = 1.0 / 30.0
CORR_MAX = 0.999
#: Prior uncertainty (1 sd) of parameters left at their prior, propagated into the others' standard
#: errors: relative to the value, except where an absolute value (unit of the parameter) is given.
PRIOR_REL_SD = 0.25
#: Calibration uncertainty (1 sd, relative) of logged inputs of the output-error fits: heater power,
#: fuel rate, engine power (speed x torque, resampled to 1 s bins). Propagated into the standard errors.
INPUT_REL_SD = 0.01
PRIOR_ABS_SD = {"T_open_degC": 4.0, "kappa": 0.1, "Q_sun_W": 100.0}
U_OC_SE_MAX_V = 0.5
MIN_SAMPLES = 60

#: Parameters whose lmfit confidence intervals are computed (when fitted).
KEY_PARAMETERS = ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "C_cab_J_per_K", "UA_cab_W_per_K")


# ------------------------------------------------------------------------------------------------
# result types shared by the fitters
# ------------------------------------------------------------------------------------------------
@dataclass
class ParamEstimate:
    """Outcome for one parameter (scalar or table).

    ``status`` is ``estimated``, ``undetermined`` (left at ``prior``), ``fixed`` or ``prior`` (not
    attempted). For tables ``value``/``stderr`` are lists and ``entry_status`` gives each entry's status
    (``stderr`` is NaN for entries not estimated).
    """

    name: str
    value: object
    stderr: object
    status: str
    note: str = ""
    prior: object = None
    entry_status: list | None = None


@dataclass
class SubsystemFit:
    """Result of one subsystem fitter."""

    subsystem: str
    needs: tuple
    estimates: dict = field(default_factory=dict)
    correlations: dict = field(default_factory=dict)  # "a|b" -> r (fitted pairs)
    conf_intervals: dict = field(default_factory=dict)  # name -> {"1sigma": [lo, hi], ...}
    metrics: dict = field(default_factory=dict)
    logs: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)  # log label -> why not used
    message: str = ""  # why nothing was fitted
    nuisance: dict = field(default_factory=dict)  # per-log initial states etc.

    @property
    def fitted(self) -> bool:
        return any(e.status == "estimated" for e in self.estimates.values())


def usable_logs(logs, needs, subsystem, any_of=()):
    """Split logs into those with every channel of ``needs`` and a dict label -> missing-channel reason.

    ``any_of``: alternative channel groups of which a log needs at least one, e.g.
    ``(("heater_power_W",), ("vent_temp_degC", "blower_flow_kg_per_s"))``.
    """
    use, skipped = [], {}
    for lg in logs:
        miss = lg.missing(needs)
        if any_of and not any(lg.has(*group) for group in any_of):
            first, *rest = [" + ".join(g) for g in any_of]
            miss.append(first + "".join(f" (or {r})" for r in rest))
        if miss:
            skipped[lg.label()] = f"missing channel(s) {', '.join(miss)}"
        else:
            use.append(lg)
    return use, skipped


def output_error_params(names, bounds, prior, data):
    """``make_params(vary)`` for an output-error fit: the physical parameters ``names`` (bounded, at their
    prior, varied when in ``vary``) plus each log's initial temperature ``d["name"]`` (always fitted,
    within 5 K of its first measured value ``d["T0"]``)."""
    import lmfit

    def make_params(vary):
        ps = lmfit.Parameters()
        for n in names:
            lo, hi = bounds[n]
            ps.add(n, value=prior[n], min=lo, max=hi, vary=n in vary)
        for d in data:
            ps.add(d["name"], value=d["T0"], min=d["T0"] - 5.0, max=d["T0"] + 5.0, vary=True)
        return ps

    return make_params


def not_fitted(fit: SubsystemFit, base, names, reason):
    """Mark ``names`` as not attempted (status prior) with ``reason``."""
    fit.message = reason
    for n in names:
        p = base.param(n)
        fit.estimates[n] = ParamEstimate(n, p.value, None, "prior", f"not fitted: {reason}", prior=p.value)
    return fit


# ------------------------------------------------------------------------------------------------
# statistics helpers
# ------------------------------------------------------------------------------------------------
def neff(residual_segments) -> tuple[int, float]:
    """(n, n_eff) over per-log residual arrays.

    ``n_eff = n / tau`` per log with ``tau`` the largest of: the integrated autocorrelation time
    ``1 + 2 sum_k rho_k`` (summed until the autocorrelation first drops below 0.05, at most n/5 lags), the
    batch-means estimate ``B var(block means) / var(residual)`` with blocks of ``B = max(20, sqrt(n))``
    samples (sensitive to slow drifts), and the AR(1) value ``(1 + rho_1) / (1 - rho_1)``.
    """
    n_tot, n_eff = 0, 0.0
    for r in residual_segments:
        r = np.asarray(r, float)
        r = r[np.isfinite(r)]
        if r.size < 3:
            continue
        r0 = r - r.mean()
        m = r0.size
        nfft = 1 << (2 * m - 1).bit_length()
        fr = np.fft.rfft(r0, nfft)
        ac = np.fft.irfft(fr * np.conj(fr), nfft)[:m]
        if ac[0] <= 0:
            continue
        rho = ac / ac[0]
        kmax = max(2, m // 5)
        below = np.flatnonzero(rho[1:kmax] < 0.05)
        K = int(below[0]) + 1 if below.size else kmax
        tau = 1.0 + 2.0 * float(np.sum(rho[1:K]))
        r1 = min(max(float(rho[1]), 0.0), 0.995)
        # batch means (blocks of ~sqrt(n) samples) catch slow drifts that carry little variance
        B = max(20, int(math.sqrt(m)))
        nb = m // B
        if nb >= 4:
            bm = r0[: nb * B].reshape(nb, B).mean(axis=1)
            tau_bm = B * float(np.var(bm)) / (ac[0] / m)
        else:
            tau_bm = 1.0
        tau = max(tau, tau_bm, (1.0 + r1) / (1.0 - r1), 1.0)
        n_tot += m
        n_eff += m / tau
    return n_tot, max(n_eff, 1.0)


def inflation(residual_segments, nvarys=0) -> float:
    """Factor on standard errors for correlated residuals: sqrt((n - p) / (n_eff - p)), >= 1."""
    n, ne = neff(residual_segments)
    if n == 0:
        return 1.0
    return float(math.sqrt(max(n - nvarys, 1) / max(ne - nvarys, 1.0)))


def judge(name, value, se, bounds, rel_max=REL_SE_MAX):
    """(ok, reason) for criteria 2, 3 and 5 of the module docstring."""
    if se is None or not np.isfinite(se) or se <= 0:
        return False, "no finite standard error (the data is not sensitive to it / singular covariance)"
    rel = se / abs(value) if value != 0 else math.inf
    if rel > rel_max:
        return False, f"relative standard error {100 * rel:.3g} % > {100 * rel_max:.3g} %"
    lo, hi = bounds
    span = hi - lo
    if span > 0 and (value - lo < 1e-4 * span or hi - value < 1e-4 * span):
        return False, f"estimate {value:.6g} stuck at its bound [{lo:g}, {hi:g}]"
    return True, ""


def collinear(names, stderr, values, correl):
    """Names flagged by criterion 4: {name: reason}."""
    flagged = {}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            r = correl.get(f"{a}|{b}")
            if r is None or abs(r) <= CORR_MAX:
                continue
            ra = stderr[a] / abs(values[a]) if values[a] else math.inf
            rb = stderr[b] / abs(values[b]) if values[b] else math.inf
            worse, other, rw = (a, b, ra) if ra >= rb else (b, a, rb)
            if rw > REL_SE_MAX / 2:
                flagged[worse] = f"correlation {r:+.3f} with {other} (relative se {100 * rw:.3g} %)"
    return flagged


def lmfit_identify(make_params, residual, candidates, *, bounds, segments, conf_keys=(), fixed_reason=None,
                   perturbed=()):
    """Fit with lmfit and judge every candidate parameter (criteria of the module docstring).

    Parameters
    ----------
    make_params : callable(vary: set) -> lmfit.Parameters
        Builds the parameters (at their priors) with ``vary`` True exactly for the names given (plus
        nuisance parameters such as initial states, always varied).
    residual : callable(params) -> ndarray
        Residual vector over all logs.
    candidates : list of str
        Model parameters that may be estimated.
    bounds : dict name -> (lo, hi)
    segments : callable(params) -> list of ndarray
        Per-log residuals (for the autocorrelation inflation).
    conf_keys : names whose lmfit confidence intervals are wanted (when estimated).
    fixed_reason : dict name -> reason
        Parameters known beforehand to be undetermined (no data in their regime): held at the prior,
        whose uncertainty is propagated into the others' standard errors.
    perturbed : sequence of callable(params) -> ndarray
        Residual functions with one logged input scaled by one standard deviation of its calibration
        uncertainty (:data:`INPUT_REL_SD`); the shift of the estimates when refitted is added in
        quadrature to their standard errors (errors in the inputs, not only in the output).

    Notes
    -----
    Parameters that the data reaches but does not determine (large relative standard error, near
    collinearity) stay *free* in the fit, as nuisance parameters, so that the estimates of the others
    are not biased by a wrong prior and their standard errors include the correlation; they are then
    reported undetermined at their prior. A parameter with no sensitivity at all (singular covariance)
    or stuck at a bound is instead held at its prior and the fit repeated.

    Returns
    -------
    dict with ``result`` (lmfit MinimizerResult), ``stderr``, ``values``, ``correl`` (inflated se,
    pairwise correlations of the free model parameters), ``undetermined`` {name: reason}, ``vary``
    (estimated names), ``factor``, ``conf`` {name: {sigma: [lo, hi]}}, ``n``, ``n_eff``.
    """
    import lmfit

    fixed = dict(fixed_reason or {})
    free = [c for c in candidates if c not in fixed]
    res = mini = None
    stderr, values, correl, factor, segs = {}, {}, {}, 1.0, []
    for _ in range(len(candidates) + 1):
        params = make_params(set(free))
        mini = lmfit.Minimizer(residual, params)
        res = mini.minimize(method="leastsq")
        segs = segments(res.params)
        factor = inflation(segs, res.nvarys)
        values = {n: float(res.params[n].value) for n in free}
        stderr = {}
        for n in free:
            se = res.params[n].stderr
            stderr[n] = float(se) * factor if se is not None and np.isfinite(se) else None
        # no sensitivity / at a bound: hold at the prior and refit
        drop = {}
        for n in free:
            lo, hi = bounds[n]
            span = hi - lo
            if span > 0 and (values[n] - lo < 1e-4 * span or hi - values[n] < 1e-4 * span):
                drop[n] = f"estimate {values[n]:.6g} stuck at its bound [{lo:g}, {hi:g}]"
        if not drop and any(stderr[n] is None for n in free):
            # covariance singular: drop the candidate with the largest relative step to explain it
            n = next(n for n in free if stderr[n] is None) if all(stderr[m] is None for m in free) else \
                next(n for n in free if stderr[n] is None)
            drop[n] = "no finite standard error (the data is not sensitive to it / singular covariance)"
        if not drop:
            break
        fixed.update(drop)
        free = [c for c in free if c not in drop]
        if not free:
            break
    correl = {}
    for i, a in enumerate(free):
        ca = res.params[a].correl or {}
        for b in free[i + 1:]:
            if b in ca:
                correl[f"{a}|{b}"] = float(ca[b])
    # prior uncertainty of the parameters held at their prior
    if fixed and free:
        shift = {n: 0.0 for n in free}
        for u in fixed:
            if u not in bounds:
                continue
            p0 = make_params(set(free))
            if u not in p0:
                continue
            v0 = float(p0[u].value)
            sd = PRIOR_ABS_SD.get(u, PRIOR_REL_SD * abs(v0))
            lo, hi = bounds[u]
            v1 = v0 + sd if v0 + sd <= hi else v0 - sd
            if sd == 0 or not lo <= v1 <= hi:
                continue
            p0[u].set(value=v1)
            for n in res.params:
                if res.params[n].vary and n in p0:
                    p0[n].set(value=res.params[n].value)
            r1 = lmfit.Minimizer(residual, p0).minimize(method="leastsq")
            for n in free:
                shift[n] += (float(r1.params[n].value) - values[n]) ** 2
        for n in free:
            if stderr[n] is not None and shift[n] > 0:
                stderr[n] = math.sqrt(stderr[n] ** 2 + shift[n])
    # calibration uncertainty of the logged inputs
    for rfun in perturbed:
        if not free:
            break
        p0 = make_params(set(free))
        for n in res.params:
            if res.params[n].vary and n in p0:
                p0[n].set(value=res.params[n].value)
        r1 = lmfit.Minimizer(rfun, p0).minimize(method="leastsq")
        for n in free:
            if stderr[n] is not None:
                stderr[n] = math.sqrt(stderr[n] ** 2 + (float(r1.params[n].value) - values[n]) ** 2)
    und = dict(fixed)
    for n in free:
        ok, why = judge(n, values[n], stderr[n], bounds[n])
        if not ok:
            und[n] = why
    okse = {n: stderr[n] for n in free if n not in und}
    und.update(collinear(list(okse), okse, values, correl))
    est = [n for n in free if n not in und]
    n_tot, ne = neff(segs)
    conf = {}
    keys = [k for k in conf_keys if k in est]
    if keys:
        try:
            res.nfree = max(int(ne) - res.nvarys, 1)
            ci = lmfit.conf_interval(mini, res, p_names=keys, sigmas=[1, 2])
            for k, rows in ci.items():
                d = {}
                for prob, val in rows:
                    d.setdefault(round(prob, 4), []).append(float(val))
                conf[k] = {f"{lev}sigma": [min(d[p]), max(d[p])] for lev, p in
                           ((1, 0.6827), (2, 0.9545)) if p in d}
                conf[k]["best"] = float(res.params[k].value)
        except Exception as exc:  # noqa: BLE001 - lmfit raises plain exceptions on degenerate profiles
            conf["_error"] = f"conf_interval failed: {str(exc)[:120]}"
    return {"result": res, "stderr": stderr, "values": values, "correl": correl, "undetermined": und,
            "factor": factor, "conf": conf, "n": n_tot, "n_eff": float(ne), "vary": est}


# ------------------------------------------------------------------------------------------------
# calibration driver
# ------------------------------------------------------------------------------------------------
SUBSYSTEM_PARAMS = {
    "battery": ["U_oc_V", "R_int_ohm", "C_bat_Ah", "R_int_tc_per_K"],
    "fuel": ["fuel_scale", "W_idle_g_per_s", "f_cl"],
    "thermal": ["kappa", "C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "T_open_degC", "k_rad_W_per_K"],
    "cabin": ["C_cab_J_per_K", "UA_cab_W_per_K", "Q_sun_W", "eps_hc"],
}


@dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    Attributes
    ----------
    params : ParameterSet
        Calibrated set: estimated values with ``stderr``, ``status``, ``note`` and ``logs`` filled;
        undetermined parameters at their prior.
    fits : dict subsystem -> SubsystemFit
    validation : dict log label -> channel -> metrics (RMSE, max_abs, bias; cumulative fuel error %)
    logs : list of dict (name, sha256, source, synthetic, duration_s, channels)
    wall_s : float
    """

    params: object
    fits: dict
    validation: dict
    logs: list
    validation_logs: list
    wall_s: float
    date: str
    version: str

    def calibration_section(self) -> dict:
        sec = {"software": f"iptm/calib {self.version}", "date_utc": self.date, "wall_s": round(self.wall_s, 3),
               "criteria": {"rel_se_max": REL_SE_MAX, "corr_max": CORR_MAX, "u_oc_se_max_V": U_OC_SE_MAX_V},
               "logs": self.logs, "subsystems": {}}
        for name, f in self.fits.items():
            d = {"logs": list(f.logs), "metrics": _clean(f.metrics), "message": f.message}
            if f.skipped:
                d["skipped"] = dict(f.skipped)
            hi = {k: round(v, 4) for k, v in f.correlations.items() if abs(v) > 0.9}
            if hi:
                d["correlations_above_0_9"] = hi
            ci = {k: v for k, v in f.conf_intervals.items() if not k.startswith("_")}
            if ci:
                d["conf_intervals"] = _clean(ci)
            if "_error" in f.conf_intervals:
                d["conf_interval_error"] = f.conf_intervals["_error"]
            sec["subsystems"][name] = d
        return sec

    def to_dict(self) -> dict:
        d = self.params.to_dict()
        d["calibration"] = self.calibration_section()
        d["validation"] = {"logs": self.validation_logs, "metrics": _clean(self.validation)}
        return d

    def to_artifact(self, path) -> None:
        """Write the artifact (TOML or JSON): the parameter set plus [calibration] and [validation].

        ``ParameterSet.load(path)`` reads it back as a parameter set.
        """
        from pathlib import Path

        from .errors import ParameterError
        from .fileio import write_json, write_text
        from .params import _strip_none

        path = Path(path)
        d = self.to_dict()
        if path.suffix.lower() == ".json":
            write_json(path, d)
        elif path.suffix.lower() == ".toml":
            import tomli_w

            text = "# iptm calibration artifact" + (" (SYNTHETIC logs)" if any(lg["synthetic"] for lg in self.logs)
                                                    else "") + "\n"
            write_text(path, text + tomli_w.dumps(_strip_none(_clean(d))))
        else:
            raise ParameterError(f"{path}: calibration artifacts are .toml or .json")

    def report(self) -> str:
        """Text fit report: per parameter value, standard error, status; fit metrics; validation."""
        L = [f"Calibration ({self.date}, calib {self.version}) from {len(self.logs)} log(s) in {self.wall_s:.1f} s"]
        for lg in self.logs:
            L.append(f"  log {lg['name']}{' [SYNTHETIC]' if lg['synthetic'] else ''}: {lg['duration_s']:.0f} s, "
                     f"sha256 {lg['sha256'][:12] or '-'}")
        for name, f in self.fits.items():
            L.append("")
            L.append(f"[{name}] logs used: {', '.join(f.logs) or 'none'}")
            if f.message:
                L.append(f"  {f.message}")
            for lg, why in f.skipped.items():
                L.append(f"  skipped {lg}: {why}")
            for k, v in f.metrics.items():
                if isinstance(v, (int, float)):
                    L.append(f"  {k}: {v:.4g}")
            for e in f.estimates.values():
                p = self.params.param(e.name)
                if p.is_table:
                    L.append(f"  {e.name:18s} [{e.status}] {p.unit}")
                    se = e.stderr if isinstance(e.stderr, list) else [None] * len(p.value)
                    for x, v, s, st in zip(p.x, p.value, se, e.entry_status or [e.status] * len(p.value)):
                        ss = f"+- {s:.3g}" if s is not None and np.isfinite(s) else ""
                        L.append(f"      {p.x_name}={x:<8g} {v:12.6g} {ss:12s} {st}")
                else:
                    ss = f"+- {e.stderr:.3g}" if isinstance(e.stderr, float) and np.isfinite(e.stderr) else ""
                    L.append(f"  {e.name:18s} {p.value:12.6g} {ss:14s} {p.unit:10s} [{e.status}]")
                if e.note and e.status != "estimated" or (e.note and "only as" in e.note):
                    L.append(f"      note: {e.note}")
            hi = {k: v for k, v in f.correlations.items() if abs(v) > 0.9}
            for k, v in hi.items():
                L.append(f"  correlation {k}: {v:+.3f}")
            for k, v in f.conf_intervals.items():
                if k.startswith("_"):
                    L.append(f"  {v}")
                else:
                    L.append(f"  CI {k}: " + ", ".join(f"{s} [{ab[0]:.5g}, {ab[1]:.5g}]" for s, ab in v.items()
                                                         if s != "best"))
        if self.validation:
            L.append("")
            L.append("Validation (simulated - measured):")
            for lg, m in self.validation.items():
                L.append(f"  {lg}")
                for ch, v in m.items():
                    if ch == "cumulative_fuel":
                        L.append(f"    cumulative fuel: measured {v['measured_g']:.1f} g, simulated "
                                 f"{v['simulated_g']:.1f} g, error {v['error_pct']:+.2f} %")
                    else:
                        L.append(f"    {ch:13s} RMSE {v['rmse']:.4g} max {v['max_abs']:.4g} bias {v['bias']:+.4g} "
                                 f"{v['unit']}")
        return "\n".join(L)


def _clean(o):
    """JSON/TOML-friendly copy: numpy scalars to float, non-finite floats kept (TOML has nan/inf)."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items() if v is not None}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    return o


def _log_info(lg) -> dict:
    return {"name": lg.name, "source": lg.meta.source, "sha256": lg.meta.sha256 or "",
            "synthetic": bool(lg.meta.synthetic), "duration_s": float(lg.duration_s),
            "channels": lg.channels()}


def calibrate(logs, *, base=None, fit=None, fix=None, validate=None, progress=True) -> CalibrationResult:
    """Calibrate the model from drive logs.

    Parameters
    ----------
    logs : list of DriveLog
        Logs to fit (one residual vector across logs per subsystem).
    base : ParameterSet, optional
        Priors and fixed values (default :func:`calib.params.default_parameters`). Bounds of the fits are
        the parameters' bounds.
    fit : iterable of str, optional
        Only these parameters are estimated (others stay at ``base``, status unchanged).
    fix : iterable of str, optional
        Parameters held at their ``base`` value (status ``fixed``).
    validate : list of DriveLog, optional
        Held-out logs: replayed with the calibrated parameters (:func:`calib.validate.validate`).
    progress : bool
        Show a tqdm progress bar (on stderr).

    Returns
    -------
    CalibrationResult
    """
    import time

    from tqdm.auto import tqdm

    from . import __version__
    from .errors import IptmError, ParameterError
    from .fit_battery import fit_battery
    from .fit_cabin import fit_cabin
    from .fit_fuel import fit_fuel
    from .fit_thermal import fit_thermal
    from .params import default_parameters
    from .validate import validate as run_validation

    t0 = time.perf_counter()
    logs = list(logs)
    if not logs:
        raise IptmError("calibrate: no logs given")
    base = (base or default_parameters()).copy()
    known = set(base.names())
    sel = set(fit) if fit is not None else None
    fixed = set(fix or ())
    for n in (sel or set()) | fixed:
        if n not in known:
            raise ParameterError(f"unknown parameter {n!r} in fit/fix (known: {', '.join(base.names())})")
    allowed = {n for names in SUBSYSTEM_PARAMS.values() for n in names}
    if sel is not None:
        allowed &= sel
    allowed -= fixed

    steps = [("battery", fit_battery), ("fuel", fit_fuel), ("thermal", fit_thermal), ("cabin", fit_cabin)]
    work = base.copy()
    fits = {}
    bar = tqdm(total=len(steps) + (1 if validate else 0), desc="calibrate", disable=not progress, leave=False)
    for name, fn in steps:
        bar.set_postfix_str(name)
        f = fn(logs, work, allowed=allowed)
        fits[name] = f
        _merge(work, f, allowed, fixed)
        bar.update(1)
    for n in fixed:
        work.param(n).status = "fixed"
        work.param(n).note = "held at the base value (fix=)"
    work.validate()
    stamp = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
    work.meta.update(name=f"calibrated from {len(logs)} log(s)", origin="calib.calibrate", date_utc=stamp,
                     software=f"calib {__version__}",
                     synthetic=any(lg.meta.synthetic for lg in logs))
    val = {}
    if validate:
        bar.set_postfix_str("validation")
        val = run_validation(validate, work)
        bar.update(1)
    bar.close()
    return CalibrationResult(params=work, fits=fits, validation=val, logs=[_log_info(lg) for lg in logs],
                             validation_logs=[_log_info(lg) for lg in (validate or [])],
                             wall_s=time.perf_counter() - t0, date=stamp, version=__version__)


def _merge(ps, fit: SubsystemFit, allowed, fixed):
    """Write a subsystem's estimates into the parameter set (undetermined ones stay at the prior)."""
    for n, e in fit.estimates.items():
        if n in fixed or n not in allowed:
            continue
        p = ps.param(n)
        p.logs = list(fit.logs)
        p.note = e.note
        if e.status == "estimated":
            p.value = [float(v) for v in e.value] if p.is_table else float(e.value)
            p.stderr = ([float(s) if s is not None else float("nan") for s in e.stderr] if p.is_table
                        else float(e.stderr))
            p.status = "estimated"
            p.source = "calibration (calib.calibrate)"
        else:
            p.status = e.status
            p.stderr = None
        if p.is_table:
            p.entry_status = list(e.entry_status) if e.entry_status else [p.status] * len(p.value)
