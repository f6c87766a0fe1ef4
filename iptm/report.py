"""Assemble a run's report folder: index.html (self-contained), report.json, the calibration artifact,
channel reports, figures and the time series behind them.

The folder is built as ``reports/.partial-<run-id>`` and renamed to ``reports/<run-id>`` when complete.
"""
from __future__ import annotations

import datetime as _dt
import json
import platform
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from calib import __version__, write_json, write_text

from html import escape as html_escape

from iptm.html import Section, render
from iptm.present import counts_text, parameter_counts, prior_banner
from optimize.formulations import FORMULATIONS
from optimize import PAPER_CONDITION

FIG_SERIES = {  # what the paper-style figures plot, per strategy
    "soc": "soc", "T_cl_degC": "T_cl", "T_cab_degC": "T_cab",
}


def _series(sim) -> dict:
    f = sim.flows
    return {"time_s": sim.t.tolist(), "speed_mps": sim.v.tolist(), "soc": sim.soc.tolist(),
            "T_cl_degC": sim.T_cl.tolist(), "T_cab_degC": sim.T_cab.tolist(),
            "e_mode": sim.e_mode.tolist(), "P_e_W": f["P_e"].tolist(), "P_bat_W": f["P_bat"].tolist(),
            "Q_heat_W": f["Q_heat"].tolist(),
            "fuel_cum_g": np.concatenate([[0.0], np.cumsum(f["W_f"]) * sim.Ts]).tolist()}


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, float) and not np.isfinite(o):
        return None
    if isinstance(o, (np.floating,)):
        return _clean(float(o))
    if isinstance(o, (np.integer,)):
        return int(o)
    return o


#: The comparison table's columns: (source column, header with unit, decimals). Corrected fuel (final SOC,
#: coolant and cabin heat valued) is the headline and comes first; raw fuel (as burnt) is labelled raw.
PAPER_HEADER = f"paper [%] ({PAPER_CONDITION})"
COMPARISON = [
    ("strategy", "strategy", None), ("fuel_corrected_g", "corrected fuel [g]", 1),
    ("L_per_100km_corrected", "corrected L/100 km", 2), ("mpg_corrected", "corrected mpg", 1),
    ("fuel_g", "raw fuel [g]", 1), ("L_per_100km", "raw L/100 km", 2), ("mpg", "raw mpg", 1),
    ("soc_final", "final SOC [-]", 3),
    ("T_cl_final_degC", "final coolant [degC]", 1), ("T_cl_mean_degC", "mean coolant [degC]", 1),
    ("T_cab_final_degC", "final cabin [degC]", 1), ("T_cab_mean_degC", "mean cabin [degC]", 1),
    ("engine_starts", "engine starts", 0), ("idle_s", "idle [s]", 0), ("charge_sustaining", "charge-sustaining", None),
    ("saving_vs_rule_pct", "saving vs rule-based, corrected [%]", 2),
    ("raw_saving_vs_rule_pct", "saving vs rule-based, raw [%]", 2), ("paper_vs_rule_pct", PAPER_HEADER, 2),
    ("saving_vs_baseline_pct", "saving vs Baseline-DP, corrected [%]", 2),
    ("raw_saving_vs_baseline_pct", "saving vs Baseline-DP, raw [%]", 2),
    ("paper_vs_baseline_pct", PAPER_HEADER.replace("[%]", "[%] vs Baseline-DP"), 2),
]
#: The headline per strategy (the Report page and the report's summary).
SUMMARY = [c for c in COMPARISON if c[0] in (
    "strategy", "fuel_corrected_g", "L_per_100km_corrected", "mpg_corrected", "fuel_g", "L_per_100km", "mpg",
    "saving_vs_rule_pct", "raw_saving_vs_rule_pct")]


def _cell(v, dec):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "NO"
    if dec is None:
        return str(v)
    return f"{float(v):.{dec}f}"


def comparison_table(tab: pd.DataFrame) -> pd.DataFrame:
    """The case-study table as the report shows it: a labelled row per strategy, units in the headers,
    numbers rounded to what they mean (strings, so the HTML shows them as given)."""
    cols = [(c, h, d) for c, h, d in COMPARISON if c in tab.columns]
    return pd.DataFrame([{h: _cell(r[c], d) for c, h, d in cols} for _, r in tab.iterrows()])


def summary_table(tab: pd.DataFrame) -> pd.DataFrame:
    """Headline per strategy: corrected fuel with its L/100 km and mpg, the raw ones beside them, and the
    savings against rule-based (corrected, then raw)."""
    keep = [k for k in SUMMARY if k[0] in tab.columns]
    return pd.DataFrame([{h: _cell(r[c], d) for c, h, d in keep} for _, r in tab.iterrows()])


def validation_rows(metrics: dict, logs_by_label: dict) -> list[dict]:
    """The validation metrics of held-out logs as table rows; a channel the log does not carry is "not
    scored" (:func:`iptm.present.channel_scores`), never RMSE 0."""
    from iptm.present import channel_scores

    rows = []
    for lname, chans in (metrics or {}).items():
        for r in channel_scores(chans, logs_by_label.get(lname)):
            rows.append({"log": lname, "channel": r["channel"],
                         "RMSE": "not scored" if not r["scored"] else f"{r['rmse']:.4g}",
                         "max abs": "" if not r["scored"] else f"{r['max_abs']:.4g}",
                         "bias": "" if not r["scored"] else f"{r['bias']:+.4g}", "unit": r["unit"],
                         "note": r["why"]})
        cum = (chans or {}).get("cumulative_fuel")
        lg = logs_by_label.get(lname)
        if isinstance(cum, dict) and "error_pct" in cum and (lg is None or lg.has("fuel_rate_g_per_s")):
            rows.append({"log": lname, "channel": "cumulative fuel", "RMSE": "", "max abs": "", "bias": "",
                         "unit": "g", "note": f"measured {cum['measured_g']:.1f} g, simulated {cum['simulated_g']:.1f} g, "
                                              f"error {cum['error_pct']:+.2f} %"})
    return rows


def build_report(*, reports_dir: Path, run_id: str, ingested, fit_logs, val_logs, params, calib_info, calib_text,
                 val_pngs, artifact, case_study, scenario, grids, base_params, command_line, wall_s,
                 drive_warnings=(), truth=None) -> Path:
    reports_dir.mkdir(parents=True, exist_ok=True)
    final = reports_dir / run_id
    if final.exists():
        raise FileExistsError(f"{final} exists: a run never overwrites an earlier report")
    tmp = reports_dir / f".partial-{run_id}"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "figures").mkdir(parents=True)
    try:
        _build(tmp, run_id, ingested, fit_logs, val_logs, params, calib_info, calib_text, val_pngs, artifact,
               case_study, scenario, grids, base_params, command_line, wall_s, list(drive_warnings), truth)
        tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def _build(out, run_id, ingested, fit_logs, val_logs, params, calib_info, calib_text, val_pngs, artifact, cs,
           scenario, grids, base_params, command_line, wall_s, drive_warnings=(), truth=None):
    synthetic = any(lg.meta.synthetic for _, lg, _ in ingested)
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

    # --- data
    logs_info, reports = [], {}
    data = Section("data", "Data used")
    rows = []
    from calib.ingest import same_drive
    from calib import format_economy, log_fuel_distance
    from calib.ingest import display_report

    for path, lg, rep in ingested:
        if any(lg is v for v in val_logs):
            role = "validation (held out)"
        elif any(lg is f for f in fit_logs):
            role = "calibration"
        else:
            twin = next((f for f in fit_logs + val_logs if same_drive(f, lg)), None)
            role = f"not used: same drive as {twin.label()}" if twin is not None else "not used"
        fuel_g, dist_km = log_fuel_distance(lg)
        info = {"file": str(path), "name": lg.name, "format": lg.meta.format, "sha256": lg.meta.sha256,
                "synthetic": bool(lg.meta.synthetic), "duration_s": lg.duration_s, "role": role,
                "channels": lg.channels()}
        logs_info.append(info)
        rows.append({"log": lg.label(), "format": lg.meta.format, "duration s": round(lg.duration_s),
                     "distance km": round(dist_km, 2) if dist_km == dist_km else None,
                     "fuel g": round(fuel_g, 1) if fuel_g == fuel_g else None,
                     "economy": format_economy(fuel_g, dist_km) if fuel_g == fuel_g else "-",
                     "role": role, "sha256": lg.meta.sha256[:16] + "...", "channels": len(lg.channels())})
        rep = rep.reset_index() if rep.index.name else rep
        reports[lg.name] = rep
        rep.to_csv(out / f"channels_{Path(lg.name).stem}.csv", index=False)
    data.table(pd.DataFrame(rows), "fuel and distance as logged (fuel-rate and speed channels integrated)")
    from calib.ingest import log_warnings

    for _path, lg, _rep in ingested:
        for t in log_warnings(lg):
            data.raw(f"<p class='warn'>Warning: {html_escape(lg.label())}: {html_escape(t)}</p>")
    for w in drive_warnings:
        data.raw(f"<p class='warn'>Warning: {html_escape(w)}</p>")
    for name, rep in reports.items():
        data.table(display_report(rep.set_index("channel") if "channel" in rep.columns else rep),
                   f"channel report: {name}")

    # --- calibration
    shutil.copyfile(artifact, out / "calibration.toml")
    cal = Section("calibration", "Calibration")
    cal.p("Values are maximum a posteriori estimates (data misfit plus a prior penalty) with their posterior "
          "standard deviation. 'estimated': the logs narrowed the prior by at least 30 %; 'weak': they narrowed "
          "it less, the value is mostly the prior; 'prior': not fitted (see the note). The artifact "
          "calibration.toml loads as a parameter set.")
    ptab = []
    for n in params:
        p = params.param(n)
        if not p.vary and p.status == "prior":
            continue
        val = p.value if not p.is_table else "[" + ", ".join(f"{v:.4g}" for v in p.value) + "]"
        se = p.stderr if not isinstance(p.stderr, list) else "[" + ", ".join(
            "-" if v is None else f"{v:.2g}" for v in p.stderr) + "]"
        ptab.append({"parameter": n, "value": val, "unit": p.unit, "stderr": se, "status": p.status_text(),
                     "note": p.note})
    cal.table(pd.DataFrame(ptab))
    counts = parameter_counts(params)
    priors = prior_banner(calib_info)
    cal.p(f"Calibration: {counts_text(counts)}.")
    for w in priors:
        cal.raw(f"<p class='warn'>{html_escape(w)}</p>")
    val = (calib_info.get("validation") or {}).get("metrics", {})
    vrows = validation_rows(val, {lg.label(): lg for _, lg, _ in ingested})
    if vrows:
        cal.table(pd.DataFrame(vrows), "validation on held-out logs: the calibrated model replayed from the "
                                       "logged inputs")
    if truth is not None:
        from calib.fit import truth_comparison

        tfile, tps = truth
        trows = truth_comparison(params, tps)
        if trows:
            cal.table(pd.DataFrame(trows), f"SYNTHETIC logs: estimates next to the truth they were simulated from "
                                           f"({Path(tfile).name}); 'error / stderr' within +-2 means the stated "
                                           "uncertainty covers the error")
    for png in val_pngs:
        dst = out / "figures" / Path(png).name
        shutil.copyfile(png, dst)
        stem = Path(png).stem
        cap = ("residuals (simulated - measured) on every log" if stem == "residuals" else
               "measured vs simulated on a held-out log (paper Fig. 3 style)" if stem.startswith("validation_")
               else "measured vs simulated on a fitted log")
        cal.figure(dst, cap)
    cal.pre(calib_text)

    # --- optimisation
    opt = Section("optimisation", "Optimisation: rule-based vs the three DP formulations")
    tab = cs.table().reset_index()
    opt.p(f"Scenario: cycle {scenario.cycle}, ambient {scenario.T_amb:g} degC, SOC0 {scenario.soc0:g}, "
          f"coolant {scenario.T_cl0:g} degC, cabin {scenario.T_cab0:g} degC, heater {scenario.Q_heat:g} W "
          f"(Thermal-Cabin: {scenario.Q_heat_min:g}-{scenario.Q_heat_max:g} W). Grid steps: "
          + grids.describe([f for f in FORMULATIONS if f in cs.outcomes]) + ".")
    opt.table(comparison_table(tab), "one row per strategy: corrected fuel (final SOC, coolant and cabin heat "
                                     "valued: the headline) with its L/100 km and mpg, raw fuel (as burnt) beside "
                                     "it, final states, and savings next to the paper's (Gong et al., CCTA 2019; "
                                     f"{PAPER_CONDITION}).")
    if "baseline_warm" in set(tab["key"]):
        opt.p("Baseline-DP is solved on a model without the engine thermal dynamics (coolant factor f_cl = 1): "
              "the row 'Baseline-DP (own optimum, f_cl = 1)' is the fuel that model predicts for its own "
              "optimum; 'Baseline-DP on thermal model' replays the same controls on the full thermal model and is "
              "the one compared with the other strategies.")
    ok = cs.ordering_ok() if hasattr(cs, "ordering_ok") else None
    ordering = cs.ordering_statement() if hasattr(cs, "ordering_statement") else None
    opt.p(f"Terminal condition on coolant and cabin: {scenario.terminal}. Savings are on corrected fuel (equal "
          "final stored energy); the raw savings (fuel as burnt) are shown beside them.")
    if ordering:
        opt.p("Paper's ordering (rule-based, Baseline-DP on the thermal model, Thermal-DP, Thermal-Cabin-DP), "
              + ordering + ".")
    if hasattr(cs, "format_value_check") and cs.outcomes:
        opt.pre(cs.format_value_check())
    if getattr(cs, "convergence", None) is not None:
        from optimize import CABIN_TOL_K, FUEL_TOL_PCT, format_case_study_convergence

        opt.p(f"Grid convergence: each DP solved again with every grid step halved; converged when the corrected "
              f"fuel changes by less than {FUEL_TOL_PCT:g} % and the mean cabin by less than {CABIN_TOL_K:g} K.")
        opt.pre(format_case_study_convergence(cs))
    if cs.rule:
        opt.p("Tuned rule-based thresholds: " + ", ".join(f"{k} = {v:g}" for k, v in cs.rule["thresholds"].items()))
    for png in cs.plot(out / "figures"):
        opt.figure(png, Path(png).stem.replace("_", " "))

    # --- provenance
    prov = {"run_id": run_id, "date_utc": now, "software": f"iptm {__version__}", "python": platform.python_version(),
            "command_line": command_line, "base_parameters": base_params or "default 2017 Prius",
            "logs": logs_info, "scenario": scenario.to_dict(), "grids": grids.to_dict(), "wall_s": wall_s}
    pr = Section("provenance", "Provenance")
    pr.table(pd.DataFrame([{"item": k, "value": json.dumps(v) if isinstance(v, (dict, list)) else str(v)}
                           for k, v in prov.items() if k != "logs"]))
    pr.table(pd.DataFrame([{"log": i["name"], "sha256": i["sha256"], "synthetic": i["synthetic"]}
                           for i in logs_info]))

    # --- summary first
    summ = Section("summary", "Summary")
    strat = {}
    for r in cs.to_dict()["table"]:
        strat[r["key"]] = {k: r.get(k) for k in ("fuel_corrected_g", "L_per_100km_corrected", "mpg_corrected",
                                                  "fuel_g", "L_per_100km", "mpg", "soc_final",
                                                  "T_cl_final_degC",
                                                  "T_cab_final_degC", "T_cab_mean_degC", "saving_vs_rule_pct",
                                                  "raw_saving_vs_rule_pct", "saving_vs_baseline_pct",
                                                  "charge_sustaining")}
    summary = {"run_id": run_id, "synthetic_data": synthetic, "strategies": strat, "ordering_ok": ok,
               "ordering": ordering, "terminal": scenario.terminal,
               "n_estimated": counts["estimated"], "n_partly": counts["partly"], "n_weak": counts["weak"],
               "calibration_text": counts_text(counts), "at_prior": priors,
               "convergence": None if getattr(cs, "convergence", None) is None else [
                   {k: r[k] for k in ("formulation", "rel_change_corrected_pct", "T_cab_mean_change_K", "converged")}
                   for r in cs.convergence],
               "wall_s": wall_s}
    summ.p(f"Fuel over the scenario. Terminal condition on coolant and cabin: {scenario.terminal}; corrected fuel "
           "values each strategy's final SOC, coolant and cabin heat in grams of fuel, so strategies that end in "
           "different states compare on equal terms." + (f" {ordering[:1].upper()}{ordering[1:]}." if ordering else ""))
    summ.table(summary_table(tab), "fuel over the scenario, per strategy (corrected: valued at equal final stored "
                                   "energy; raw: as burnt)")
    partial = [f"{n}: {params.param(n).n_entries_estimated()[0]} of {params.param(n).n_entries_estimated()[1]} "
               "entries estimated" for n in params
               if params.param(n).status == "estimated" and params.param(n).n_entries_estimated()
               and params.param(n).n_entries_estimated()[0] < params.param(n).n_entries_estimated()[1]]
    summ.p(f"Calibration: {counts_text(counts)}" + (f"; tables only partly determined: {'; '.join(partial)}"
                                                     if partial else "") + ".")
    for w in drive_warnings:
        summ.raw(f"<p class='warn'>Warning: {html_escape(w)}</p>")

    banner = ("SYNTHETIC DATA: the logs in this report were simulated by the workbench from known truth "
              "parameters; they are not measurements.") if synthetic else ""
    html = render(f"iptm report {run_id}", [summ, data, cal, opt, pr], banner=banner,
                  warnings=[f"Not fitted: {w}" for w in priors])
    write_text(out / "index.html", html)
    write_json(out / "report.json", _clean({
        "summary": summary, "provenance": prov, "channel_reports": {k: v.to_dict(orient="records")
                                                                    for k, v in reports.items()},
        "calibration": calib_info, "case_study": cs.to_dict(),
        "figures": sorted(p.name for p in (out / "figures").glob("*.png")),
        "time_series": {k: _series(s) for k, s in cs.sims.items()}}))
