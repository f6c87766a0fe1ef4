"""Calibration: identify the model of docs/model.md from drive logs, with uncertainty and validation.

:func:`calibrate` runs one fitter per subsystem over all logs that carry the channels it declares in
``NEEDS`` (one residual vector across logs), merges the estimates into a
:class:`calib.model.params.ParameterSet` and validates the result on held-out logs (:mod:`calib.fit.validate`):

========================  ==========================================================================
:mod:`calib.fit.battery`  ``U_oc_V``, ``R_int_ohm`` tables (direct linear least squares on the table
                          values, hat-function basis), ``C_bat_Ah`` (Coulomb counting against logged
                          SOC), ``R_int_tc_per_K`` (profile over the coefficient, when the battery
                          temperature spans >= 10 K)
:mod:`calib.fit.fuel`     ``fuel_scale``, ``W_idle_g_per_s``, ``f_cl`` (lmfit on stable 1 s bins)
:mod:`calib.fit.thermal`  ``kappa`` (bay temperature, linear), ``C_eng_J_per_K``, ``gamma_exh``,
                          ``hA_eng_W_per_K``, ``T_open_degC``, ``k_rad_W_per_K`` (output error)
:mod:`calib.fit.cabin`    ``C_cab_J_per_K``, ``UA_cab_W_per_K``, ``Q_sun_W`` (output error),
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
from dataclasses import dataclass

import numpy as np

from calib.fit import battery as _battery, cabin as _cabin, fuel as _fuel, thermal as _thermal
from calib.fit.toolkit import CORR_MAX, REL_SE_MAX, U_OC_SE_MAX_V, SubsystemFit

#: The parameters each subsystem fitter estimates (each fitter's own ``PARAMS``).
SUBSYSTEM_PARAMS = {name: list(mod.PARAMS) for name, mod in (("battery", _battery), ("fuel", _fuel),
                                                              ("thermal", _thermal), ("cabin", _cabin))}


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
        """The ``[calibration]`` section of the artifact: logs, date, software, per-subsystem metrics."""
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
        """Everything in JSON-able form (estimates, fits, validation metrics)."""
        d = self.params.to_dict()
        d["calibration"] = self.calibration_section()
        d["validation"] = {"logs": self.validation_logs, "metrics": _clean(self.validation)}
        return d

    def to_artifact(self, path) -> None:
        """Write the artifact (TOML or JSON): the parameter set plus [calibration] and [validation].

        ``ParameterSet.load(path)`` reads it back as a parameter set.
        """
        from pathlib import Path

        from calib.errors import ParameterError
        from calib.fileio import write_json, write_text
        from calib.model.params import _strip_none

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
        Priors and fixed values (default :func:`calib.model.params.default_parameters`). Bounds of the fits are
        the parameters' bounds.
    fit : iterable of str, optional
        Only these parameters are estimated (others stay at ``base``, status unchanged).
    fix : iterable of str, optional
        Parameters held at their ``base`` value (status ``fixed``).
    validate : list of DriveLog, optional
        Held-out logs: replayed with the calibrated parameters (:func:`calib.fit.validate.validate`).
    progress : bool
        Show a tqdm progress bar (on stderr).

    Returns
    -------
    CalibrationResult
    """
    import time

    from tqdm.auto import tqdm

    from calib._version import __version__
    from calib.errors import IptmError, ParameterError
    from calib.fit.battery import fit_battery
    from calib.fit.cabin import fit_cabin
    from calib.fit.fuel import fit_fuel
    from calib.fit.thermal import fit_thermal
    from calib.model.params import default_parameters
    from calib.fit.validate import validate as run_validation

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
    work.meta.update(name=f"calibrated from {len(logs)} log(s)", origin="calib.fit.driver", date_utc=stamp,
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
            p.source = "calibration (calib.fit.driver)"
        else:
            p.status = e.status
            p.stderr = None
        if p.is_table:
            p.entry_status = list(e.entry_status) if e.entry_status else [p.status] * len(p.value)
