"""Calibration: identify the model of docs/model.md from drive logs, with uncertainty and validation.

:func:`calibrate` runs one fitter per subsystem over all logs that carry what it needs (one residual
vector across logs), merges the estimates into a :class:`calib.model.params.ParameterSet`, replays the
fitted and the held-out logs (:mod:`calib.fit.validate`) and says which drives would inform what the logs
did not (:mod:`calib.fit.advice`):

========================  ==========================================================================
:mod:`calib.fit.battery`  ``U_oc_V``, ``R_int_ohm`` tables and ``U_hyst_V`` (linear least squares on
                          the table values, hat-function basis, and the step at zero current),
                          ``C_bat_Ah`` (Coulomb counting against logged SOC), ``R_int_tc_per_K``
                          (profile, when the battery temperature spans >= 10 K); from battery power and
                          SOC alone: ``C_bat_Ah``, the level of ``R_int_ohm``, ``R_int_tc_per_K`` and
                          ``U_hyst_V`` (MAP fit of the SOC balance; ``U_oc_V`` stays the prior)
:mod:`calib.fit.fuel`     ``eta_ool`` (the warm fuel rate along the operating line), ``W_idle_g_per_s``,
                          ``f_cl`` (monotone, smooth), on stable 1 s bins, a noise sd per regime
                          (engine mode x coolant interval)
:mod:`calib.fit.thermal`  ``kappa`` (bay temperature, linear), ``C_eng_J_per_K``, ``gamma_exh``,
                          ``hA_eng_W_per_K``, ``T_open_degC``, ``k_rad_W_per_K`` (output error)
:mod:`calib.fit.cabin`    ``C_cab_J_per_K``, ``UA_cab_W_per_K``, ``Q_sun_W`` (output error),
                          ``eps_hc`` (vent temperature where the heater-core limit binds)
========================  ==========================================================================

What a log has
--------------
Inputs come in several forms (:func:`calib.fit.replay.log_arrays`): the engine operating point from
speed x torque, or the logged engine power, or inferred from the power balance (traction demand minus the
motor's share of the battery power); the battery power logged or as voltage x current; the heater heat
logged, from vent temperature and blower flow, or inferred from the cabin balance. Each fit states in
``SubsystemFit.used`` what it used per log, and what it inferred.

Sparse channels and unknown inputs
----------------------------------
A channel polled every few seconds is used where it has samples: the fitters bridge an input across its
short gaps only (:func:`calib.fit.replay.fill_short`: up to 2.5 times its own sampling interval, at least
5 s) and leave a bin whose input is unknown out of the fit (the output-error replays restart after it); the
engine mode comes from every cue a log has, engine speed, fuel rate (measured or from the MAF) and engine
power (:func:`calib.fit.replay.running_cue`), so a bin is never "engine off" for want of a sample. The
heater heat of a log without a heater channel is declared off or estimated (``heater=``; the engine-thermal
fit's ``used`` says which), so a parked warm-up at idle logged by an OBD tool is a calibration drive.

Estimation: maximum a posteriori
--------------------------------
Every parameter has a prior value and a prior sd (``Parameter.prior_sd``, defaults in
:data:`calib.model.params.PRIOR_SD`). Each fit minimises the data misfit plus the prior penalty,
``sum (r / s)^2 + sum ((p - p_prior) / sd_prior)^2`` (in lmfit, the prior as extra residuals;
:func:`calib.fit.toolkit.map_fit`), where ``s`` is the data's noise sd re-estimated from the residuals and
inflated by ``sqrt(n / n_eff)`` for their autocorrelation, so the data count as ``n_eff`` independent
samples. Closed-form fits (tables, capacity, ``kappa``, ``eps_hc``) combine their regression estimate
with the prior by precision weighting. Every parameter then moves as far as its data justify, and its
value *is the posterior*, whatever the data say about it:

- the posterior sd (Gauss-Newton, plus the calibration uncertainty of the logged inputs, 1 % of fuel,
  engine and heater power and 0.5 K of temperature sensors, propagated linearly) is the ``stderr``;
- ``informed = 1 - posterior sd / prior sd`` says how much the data narrowed the prior; below
  :data:`calib.fit.toolkit.WEAK_INFORMED` the status is ``weak`` (the value is mostly the prior), else
  ``estimated``; a parameter no data reaches returns its prior with the prior sd;
- pairs with posterior ``|r| >`` :data:`calib.fit.toolkit.CONFOUNDED` are reported as confounded (the
  logs determine a combination), and :func:`calib.fit.advice.advise` names a drive that would separate them.

Statuses: ``estimated``, ``weak`` (posterior, mostly the prior), ``prior`` (the fit could not run: its
channels are missing; value and sd are the prior's), ``fixed`` (``fix=``).

``hA_eng_W_per_K`` and ``kappa`` enter the coolant equation only as ``hA_eng (1 - kappa)`` unless a log
carries the engine-bay temperature. Without it, ``kappa`` is its prior and ``hA_eng`` is reported as the
value that, *with that kappa*, reproduces the identified product; its note says so.
"""
from __future__ import annotations


import dataclasses
import datetime as _dt
from dataclasses import dataclass

import numpy as np

from calib.fit import battery as _battery, cabin as _cabin, fuel as _fuel, thermal as _thermal
from calib.fit.toolkit import CONFOUNDED, WEAK_INFORMED, SubsystemFit

#: The parameters each subsystem fitter estimates (each fitter's own ``PARAMS``).
SUBSYSTEM_PARAMS = {name: list(mod.PARAMS) for name, mod in (("battery", _battery), ("fuel", _fuel),
                                                              ("thermal", _thermal), ("cabin", _cabin))}


@dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    Attributes
    ----------
    params : ParameterSet
        Calibrated set: posterior values with ``stderr`` (posterior sd), ``prior_value``, ``prior_sd``,
        ``informed``, ``status``, ``note`` and ``logs`` filled.
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
    advice: list = None
    diagnostics: dict = None  # {"fitted": {log: ...}, "held_out": {log: ...}} (see calib.fit.validate.diagnostics)
    data_warnings: list = None  # each subsystem that used a channel which lost samples or is an estimate
    timings: dict = None  # wall seconds per step: each subsystem fit, "validation", "diagnostics"

    def plot(self, path=None, title=None):
        """How much the data informed each fitted parameter (``1 - posterior sd / prior sd``), by subsystem
        and status (:func:`calib.plotting.plot_calibration`). Returns the Figure."""
        from calib.plotting import plot_calibration

        return plot_calibration(self, path, title)

    def calibration_section(self) -> dict:
        """The ``[calibration]`` section of the artifact: logs, date, software, per-subsystem metrics."""
        sec = {"software": f"iptm/calib {self.version}", "date_utc": self.date, "wall_s": round(self.wall_s, 3),
               "method": "maximum a posteriori (data misfit in noise sd + Gaussian prior penalty)",
               "criteria": {"weak_informed": WEAK_INFORMED, "confounded_abs_r": CONFOUNDED},
               "logs": self.logs, "subsystems": {}, "advice": list(self.advice or []),
               "data_warnings": list(self.data_warnings or [])}
        for name, f in self.fits.items():
            d = {"logs": list(f.logs), "metrics": _clean(f.metrics), "message": f.message}
            if f.skipped:
                d["skipped"] = dict(f.skipped)
            if f.used:
                d["used"] = _clean(f.used)
            if f.confounded:
                d["confounded"] = [{"a": a, "b": b, "r": round(r, 4)} for a, b, r in f.confounded]
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
        if self.diagnostics:
            d["validation"]["diagnostics"] = _clean(self.diagnostics)
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

    # --- saving -----------------------------------------------------------------------------------
    def to_pandas(self):
        """One row per parameter: posterior value and sd, status, prior value and sd, how informed, source."""
        import pandas as pd

        rows = [{"name": p.name, "value": p.value, "unit": p.unit, "stderr": p.stderr, "status": p.status,
                 "prior_value": p.prior_value, "prior_sd": p.prior_sd, "informed": p.informed, "source": p.source,
                 "note": p.note} for p in (self.params.param(n) for n in self.params.names())]
        return pd.DataFrame(rows).set_index("name")

    def save(self, path):
        """Save as a result folder of kind ``calibration`` (docs/results.md), atomically; returns its path. Its
        ``parameters.toml`` is the calibrated parameter set, readable by ``ParameterSet.load``."""
        from calib.results import save_result

        return save_result(path, self._write_into)

    def _write_into(self, folder) -> None:
        import tomli_w

        from calib.model.params import _strip_none
        from calib.results import write_parts

        meta = {"params_meta": dict(self.params.meta), "validation": _clean(self.validation), "logs": _clean(self.logs),
                "validation_logs": _clean(self.validation_logs), "wall_s": self.wall_s, "date": self.date,
                "software_version": self.version, "advice": _clean(self.advice), "diagnostics": _clean(self.diagnostics),
                "data_warnings": _clean(self.data_warnings), "timings": _clean(self.timings),
                "fits": {k: _clean(dataclasses.asdict(f)) for k, f in self.fits.items()}}
        write_parts(folder, "calibration", meta,
                    texts={"parameters.toml": tomli_w.dumps(_strip_none(_clean(self.params.to_dict())))})

    @classmethod
    def load(cls, path) -> "CalibrationResult":
        """Read a folder written by :meth:`save` (a ResultFileError where it is not one)."""
        from calib.errors import IptmError, ResultFileError
        from calib.fit.toolkit import ParamEstimate
        from calib.model.params import ParameterSet
        from calib.results import need, read_parts

        doc, _, path = read_parts(path, "calibration")
        try:
            params = ParameterSet.load(path / "parameters.toml")
        except IptmError as exc:
            raise ResultFileError(f"{path}: parameters.toml: {exc}") from None
        params.meta = dict(need(doc, "params_meta", path))
        fits = {}
        for name, d in need(doc, "fits", path).items():
            try:
                d = dict(d, needs=tuple(d["needs"]), confounded=[tuple(c) for c in d.get("confounded", [])],
                         estimates={k: ParamEstimate(**e) for k, e in d.get("estimates", {}).items()})
                fits[name] = SubsystemFit(**d)
            except (KeyError, TypeError) as exc:
                raise ResultFileError(f"{path}: fit {name!r} is damaged ({exc})") from None
        return cls(params=params, fits=fits, version=need(doc, "software_version", path), **{k: need(doc, k, path) for k in (
            "validation", "logs", "validation_logs", "wall_s", "date")},
            **{k: doc.get(k) for k in ("advice", "diagnostics", "data_warnings", "timings")})

    def report(self) -> str:
        """Text fit report: per parameter posterior value and sd, prior and prior sd, how much the data
        informed it; what each fit used; confounded pairs; advice; validation and residual diagnostics."""
        L = [f"Calibration ({self.date}, calib {self.version}) from {len(self.logs)} log(s) in {self.wall_s:.1f} s",
             "Maximum a posteriori: value +- posterior sd; prior +- prior sd; informed = 1 - posterior sd / prior sd"]
        for w in self.data_warnings or []:
            L.append(f"WARNING {w}")
        for lg in self.logs:
            L.append(f"  log {lg['name']}{' [SYNTHETIC]' if lg['synthetic'] else ''}: {lg['duration_s']:.0f} s, "
                     f"sha256 {lg['sha256'][:12] or '-'}")
        fmt = lambda v: f"{v:.4g}" if isinstance(v, (int, float)) and np.isfinite(v) else "-"  # noqa: E731
        for name, f in self.fits.items():
            L.append("")
            L.append(f"[{name}] logs used: {', '.join(f.logs) or 'none'}")
            if f.message:
                L.append(f"  {f.message}")
            for lg, why in f.skipped.items():
                L.append(f"  skipped {lg}: {why}")
            for lg, used in f.used.items():
                L.append(f"  used from {lg}: " + "; ".join(f"{k}: {v}" for k, v in used.items() if v))
            for k, v in f.metrics.items():
                if isinstance(v, (int, float)):
                    L.append(f"  {k}: {v:.4g}")
            for e in f.estimates.values():
                p = self.params.param(e.name)
                if p.is_table:
                    L.append(f"  {e.name:18s} [{e.status}] {p.unit}")
                    se = e.stderr if isinstance(e.stderr, list) else [None] * len(p.value)
                    pr = e.prior if isinstance(e.prior, list) else [None] * len(p.value)
                    psd = e.prior_sd if isinstance(e.prior_sd, list) else [None] * len(p.value)
                    inf = e.informed if isinstance(e.informed, list) else [None] * len(p.value)
                    for x, v, s_, st, p0, s0, i0 in zip(p.x, p.value, se, e.entry_status or [e.status] * len(p.value),
                                                        pr, psd, inf):
                        L.append(f"      {p.x_name}={x:<8g} {v:12.6g} +- {fmt(s_):9s} prior {fmt(p0):>9s} +- "
                                 f"{fmt(s0):9s} informed {fmt(100 * i0) if i0 is not None else '-':>4s} %  {st}")
                else:
                    inf = f"{100 * e.informed:.0f} %" if isinstance(e.informed, (int, float)) else "-"
                    L.append(f"  {e.name:18s} {p.value:12.6g} +- {fmt(e.stderr):9s} {p.unit:10s} prior "
                             f"{fmt(e.prior):>9s} +- {fmt(e.prior_sd):9s} informed {inf:>5s} [{e.status}]")
                if e.note and e.status != "estimated" or (e.note and "only as" in e.note):
                    L.append(f"      note: {e.note}")
            for a, b, r in f.confounded:
                L.append(f"  confounded: {a} and {b} (posterior correlation {r:+.3f})")
        if self.advice:
            L.append("")
            L.append("Advice (what drive would inform what these logs did not):")
            for a in self.advice:
                L.append(f"  - {a}")
        if self.validation:
            L.append("")
            L.append("Validation (simulated - measured):")
            for lg, m in self.validation.items():
                L.append(f"  {lg}")
                for ch, v in m.items():
                    if ch == "cumulative_fuel":
                        L.append(f"    cumulative fuel: measured {v['measured_g']:.1f} g, simulated "
                                 f"{v['simulated_g']:.1f} g, error {v['error_pct']:+.2f} %")
                    elif ch == "refused":
                        for k, why in v.items():
                            L.append(f"    {k:13s} NOT CHECKED: {why}")
                    elif ch == "inferred":
                        for k, how in v.items():
                            L.append(f"    input {k} inferred: {how}")
                    else:
                        L.append(f"    {ch:13s} RMSE {v['rmse']:.4g} max {v['max_abs']:.4g} bias {v['bias']:+.4g} "
                                 f"{v['unit']}")
        if self.diagnostics:
            L.append("")
            L.append("Residual diagnostics (RMSE / bias by regime; lag-1 and lag-60 s residual autocorrelation):")
            for kind, per in self.diagnostics.items():
                for lg, chans in per.items():
                    L.append(f"  [{kind}] {lg}")
                    for ch, d in chans.items():
                        ac = d["autocorrelation"]
                        L.append(f"    {ch:13s} RMSE {d['rmse']:.4g} bias {d['bias']:+.4g} {d['unit']}; acf(1s) "
                                 f"{ac.get('1s', float('nan')):.2f} acf(60s) {ac.get('60s', float('nan')):.2f}; "
                                 f"n_eff {d['n_eff']:.0f} of {d['n']}")
                        for rg, v in d["by_regime"].items():
                            L.append(f"      {rg:26s} RMSE {v['rmse']:.4g} bias {v['bias']:+.4g} (n {v['n']})")
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


def calibrate(logs, *, base=None, fit=None, fix=None, validate=None, progress=True, diagnose=True,
              heater=None) -> CalibrationResult:
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
    diagnose : bool
        Replay the fitted and the held-out logs and compute residual diagnostics
        (:func:`calib.fit.validate.diagnostics`).
    heater : None, "off" or "estimate"
        The heater heat of logs without a heater channel (``heater_power_W``, or vent temperature and blower
        flow): ``"off"`` declares it zero (the heater did not run; the cabin fit and the replays then use
        zero too); ``"estimate"`` estimates it in the engine-thermal fit as an unknown draw with a wide prior
        (never inferred from the cabin balance); None (default) infers it from the cabin balance where the
        cabin temperature is logged and estimates it where not. Each fit's ``used`` says which.

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
    from calib.fit.advice import advise
    from calib.fit.validate import diagnostics, replay
    from calib.fit.validate import validate as run_validation

    from calib.fit.replay import HEATER_CHOICES

    t0 = time.perf_counter()
    logs = list(logs)
    if not logs:
        raise IptmError("calibrate: no logs given")
    if heater not in HEATER_CHOICES:
        raise IptmError(f"calibrate: heater={heater!r}; give 'off' (the heater did not run in logs without a heater "
                        "channel), 'estimate' (estimate its heat) or None (infer it from the cabin where logged, else "
                        "estimate it)")
    base = (base or default_parameters()).copy()
    known = set(base.names())
    sel = set(fit) if fit is not None else None
    fixed = set(fix or ())
    for n in (sel or set()) | fixed:
        if n not in known:
            raise ParameterError(f"unknown parameter {n!r} in fit/fix - {base.closest_hint(n)}")
    allowed = {n for names in SUBSYSTEM_PARAMS.values() for n in names}
    if sel is not None:
        allowed &= sel
    allowed -= fixed

    steps = [("battery", fit_battery), ("fuel", fit_fuel), ("thermal", fit_thermal), ("cabin", fit_cabin)]
    work = base.copy()
    fits = {}
    bar = tqdm(total=len(steps) + (1 if validate else 0), desc="calibrate", disable=not progress, leave=False)
    timings = {}
    for name, fn in steps:
        bar.set_postfix_str(name)
        t_step = time.perf_counter()
        f = fn(logs, work, allowed=allowed, **({"heater": heater} if name in ("thermal", "cabin") else {}))
        fits[name] = f
        _merge(work, f, allowed, fixed)
        timings[name] = time.perf_counter() - t_step
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
    diag = {"fitted": {}, "held_out": {}}
    if validate:
        bar.set_postfix_str("validation")
        t_step = time.perf_counter()
        val = run_validation(validate, work, heater=heater)
        timings["validation"] = time.perf_counter() - t_step
        bar.update(1)
    if diagnose:
        t_step = time.perf_counter()
        for kind, group in (("fitted", logs), ("held_out", validate or [])):
            for lg in group:
                rep = replay(lg, work, heater=heater)
                diag[kind][rep.name] = diagnostics(rep)
        timings["diagnostics"] = time.perf_counter() - t_step
    bar.close()
    return CalibrationResult(params=work, fits=fits, validation=val, logs=[_log_info(lg) for lg in logs],
                             validation_logs=[_log_info(lg) for lg in (validate or [])],
                             wall_s=time.perf_counter() - t0, date=stamp, version=__version__,
                             advice=advise(fits), diagnostics=diag if diagnose else None,
                             data_warnings=data_warnings(fits, logs), timings=timings)


def data_warnings(fits: dict, logs) -> list[str]:
    """One line per subsystem and log where the fit used a channel that lost more than 1 % of its samples
    (non-finite or impossible values) or that is an estimate (fuel from MAF): the reader of a calibration
    sees which estimates rest on such data."""
    from calib.drivelog import CHANNELS
    from calib.ingest.channels import channel_losses

    by_label = {lg.label(): lg for lg in logs}
    out = []
    for name, f in fits.items():
        for label in f.logs:
            lg = by_label.get(label)
            if lg is None:
                continue
            said = " ".join(str(v) for v in (f.used.get(label) or {}).values())
            chans = set(f.needs) | {ch for ch in CHANNELS if ch in said}
            losses = channel_losses(lg.meta)
            for ch in sorted(chans & set(lg.meta.lossy_channels())):
                d = losses[ch]
                out.append(f"[{name}] used {ch} of {label}, which lost {d['lost']} of {d['read']} samples "
                           f"({100 * d['fraction']:.1f} %: {d['why']})")
            for ch in sorted(chans & set(lg.meta.estimated or {})):
                out.append(f"[{name}] used {ch} of {label}, which is an {lg.meta.estimated[ch]}")
    return out


def _merge(ps, fit: SubsystemFit, allowed, fixed):
    """Write a subsystem's posterior estimates into the parameter set (value, posterior sd, prior, informed)."""
    from calib.model.params import prior_sd_of

    for n, e in fit.estimates.items():
        if n in fixed or n not in allowed:
            continue
        p = ps.param(n)
        p.logs = list(fit.logs)
        p.note = e.note
        p.prior_value = e.prior if e.prior is not None else p.value
        p.prior_sd = e.prior_sd if e.prior_sd is not None else prior_sd_of(p)
        p.informed = e.informed
        p.status = e.status
        if e.status in ("estimated", "weak"):
            p.value = [float(v) for v in e.value] if p.is_table else float(e.value)
            p.source = "calibration (calib.fit.driver, maximum a posteriori)"
        if e.stderr is not None:
            p.stderr = ([float(s) if s is not None else float("nan") for s in e.stderr] if p.is_table
                        else float(e.stderr))
        else:
            p.stderr = None
        if p.is_table:
            p.entry_status = list(e.entry_status) if e.entry_status else [p.status] * len(p.value)
