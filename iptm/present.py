"""What the command line, the HTML report and the dashboard say about a run, decided once here so the three
agree: how many parameters the logs estimated, which subsystems kept their priors and why, which replayed
channels were scored, whether a grid is the converged default or a coarser preview, and what an ordering
that does not hold suggests. No physics: counts, labels and differences of figures computed elsewhere.
"""
from __future__ import annotations

import math

from optimize import PAPER_CONDITION  # noqa: F401 - the paper's figures' label, for the pages


# ---------------------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------------------
def parameter_counts(params) -> dict:
    """Statuses of a calibrated parameter set, counted once for every display.

    ``estimated``: parameters whose status is ``estimated`` (a table counts when any of its entries is);
    ``partly``: of those, tables with only some entries estimated; ``weak``, ``prior``, ``fixed``: the others.
    """
    out = {"estimated": 0, "partly": 0, "weak": 0, "prior": 0, "fixed": 0}
    for name in params:
        p = params.param(name)
        status = p.status or "prior"
        if status in out:
            out[status] += 1
        n = p.n_entries_estimated() if status == "estimated" else None
        if n and n[0] < n[1]:
            out["partly"] += 1
    return out


def counts_text(counts: dict) -> str:
    """``17 parameters estimated (4 of them tables with only some entries determined), 1 weakly informed``."""
    part = f" ({counts['partly']} of them tables with only some entries determined)" if counts.get("partly") else ""
    return (f"{counts['estimated']} parameters estimated{part}, {counts['weak']} weakly informed (posterior "
            "mostly the prior)")


def _calibration_section(cal) -> dict:
    """The ``[calibration]`` section from a CalibrationResult, its ``to_dict()`` or the section itself."""
    if hasattr(cal, "calibration_section"):
        return cal.calibration_section()
    cal = dict(cal or {})
    return cal.get("calibration", cal)


def subsystems_at_prior(cal) -> list[dict]:
    """Every subsystem the calibration could not fit (no log carried what it needs): ``{"subsystem",
    "reason"}`` in fitting order. ``cal``: a :class:`calib.fit.driver.CalibrationResult`, its ``to_dict()``
    (the pipeline's ``calibration.json``) or its ``[calibration]`` section."""
    subs = _calibration_section(cal).get("subsystems") or {}
    out = []
    for name, d in subs.items():
        if d.get("logs"):
            continue
        reason = d.get("message") or "; ".join(f"{lg}: {why}" for lg, why in (d.get("skipped") or {}).items())
        out.append({"subsystem": name, "reason": reason or "no log was usable for it"})
    return out


def prior_banner(cal) -> list[str]:
    """One line per subsystem left at its priors, naming the parameters and why (empty when all were fitted)."""
    from calib.fit import SUBSYSTEM_PARAMS

    return [f"{s['subsystem']} parameters ({', '.join(SUBSYSTEM_PARAMS.get(s['subsystem'], []))}) left at their "
            f"priors: {s['reason']}" for s in subsystems_at_prior(cal)]


def channel_scores(metrics: dict, log) -> list[dict]:
    """The replay metrics of one log (:meth:`calib.fit.validate.Replay.metrics`, or the validation metrics of
    a calibration) as rows ``{"channel", "scored", "rmse", "max_abs", "bias", "unit", "why"}``. A channel the
    log does not carry is "not scored": the replay takes the measured fuel rate as zero where the engine is
    stopped, so a log without fuel rate would otherwise show RMSE 0 over the engine-off seconds. ``log``: the
    DriveLog (None: every channel with a metric counts as scored)."""
    from calib.fit import CHANNEL_METRICS

    rows = []
    for key, (canonical, unit) in CHANNEL_METRICS.items():
        m = (metrics or {}).get(key)
        carried = log is None or log.has(canonical)
        if isinstance(m, dict) and "rmse" in m and carried:
            rows.append({"channel": key, "scored": True, "rmse": m["rmse"], "max_abs": m.get("max_abs"),
                         "bias": m.get("bias"), "unit": m.get("unit", unit), "why": ""})
        elif m is not None or not carried:
            rows.append({"channel": key, "scored": False, "rmse": None, "max_abs": None, "bias": None, "unit": unit,
                         "why": f"not scored: the log has no {canonical}" if not carried else "not scored"})
    return rows


def scores_text(metrics: dict, log) -> str:
    """``soc RMSE 0.0015 -, ..., fuel_rate not scored (the log has no fuel_rate_g_per_s)``."""
    parts = []
    for r in channel_scores(metrics, log):
        if r["scored"]:
            parts.append(f"{r['channel']} RMSE {r['rmse']:.3g} {r['unit']}")
        elif r["why"].startswith("not scored: "):
            parts.append(f"{r['channel']} not scored ({r['why'][len('not scored: '):]})")
        else:
            parts.append(f"{r['channel']} not scored")
    return ", ".join(parts) or "no channel to compare"


# ---------------------------------------------------------------------------------------------------
# optimisation
# ---------------------------------------------------------------------------------------------------
def converged_grids():
    """The grids ``iptm optimize`` and ``iptm run`` solve on by default (each formulation's converged grid)."""
    from optimize.formulations import DEFAULT_GRIDS

    return DEFAULT_GRIDS


def preview_grids():
    """The dashboard's preview: every step of each formulation's converged grid doubled (about 4-32x less
    work; its error against the converged result is measured, not assumed: :func:`preview_difference`)."""
    from dataclasses import asdict

    from optimize.formulations import FORMULATIONS, DPGrids, FormulationGrids

    g = converged_grids()
    return FormulationGrids(*(DPGrids(**{k: 2 * v for k, v in asdict(g.of(f)).items()}) for f in FORMULATIONS))


def coarser_than_converged(grids) -> list[str]:
    """The formulations whose grid has a step coarser than its converged default."""
    from dataclasses import asdict

    from optimize.formulations import FORMULATIONS, GRID_AXES, FormulationGrids

    g, ref = FormulationGrids.coerce(grids), converged_grids()
    return [f for f in FORMULATIONS
            if any(asdict(g.of(f))[a] > asdict(ref.of(f))[a] * (1 + 1e-9) for a in GRID_AXES[f])]


def preview_difference(preview_cs, converged_cs) -> dict:
    """Per DP formulation solved in both: the preview's corrected fuel minus the converged one's, in % of the
    converged (``{key: {"preview_g", "converged_g", "diff_pct"}}``), measured on the same scenario."""
    out = {}
    for k in ("baseline", "thermal", "thermal_cabin"):
        if k in preview_cs.sims and k in converged_cs.sims:
            p = preview_cs.sims[k].summary()["fuel_corrected_g"]
            c = converged_cs.sims[k].summary()["fuel_corrected_g"]
            out[k] = {"preview_g": p, "converged_g": c,
                      "diff_pct": 100.0 * (p - c) / c if c else float("nan")}
    return out


def difference_text(diff: dict) -> str:
    """``Thermal-DP +0.41 %, Thermal-Cabin-DP -0.12 %`` (corrected fuel, preview minus converged)."""
    from optimize import LABELS

    return ", ".join(f"{LABELS[k].split(' on ')[0]} {v['diff_pct']:+.2f} %" for k, v in diff.items()
                     if math.isfinite(v["diff_pct"]))


def ordering_advice(cs, settable=("grids", "terminal")) -> str:
    """What to try when the paper's ordering does not hold, naming only settings not already in use that the
    caller can set (``settable``): converged grids when a grid is coarser, the valued terminal condition when
    another is used; otherwise that the ordering fails on the settings that judge it."""
    from optimize.formulations import DPScenario

    tips = []
    coarse = coarser_than_converged(cs.grids)
    if coarse and "grids" in settable:
        tips.append("solve on the converged grids (coarser here: " + ", ".join(coarse) + ")")
    valued = DPScenario().terminal
    if cs.scenario.terminal != valued and "terminal" in settable:
        tips.append(f"compare with the {valued} terminal condition (in use: {cs.scenario.terminal}; the DP then "
                    "minimises the corrected fuel it is judged on)")
    if tips:
        return "Try: " + "; ".join(tips) + "."
    if coarse:
        return "The grids are coarser than the converged ones: their error may decide the order."
    return ("This is on the converged grids" + (f" with the {valued} terminal condition" if cs.scenario.terminal
            == valued else "") + ": the order is a result of this car and drive, not of a setting.")
