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

from calib import __version__
from calib.fileio import write_json, write_text

from .report import Section, render

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


def build_report(*, reports_dir: Path, run_id: str, ingested, fit_logs, val_logs, params, calib_info, calib_text,
                 val_pngs, artifact, case_study, scenario, grids, base_params, command_line, wall_s) -> Path:
    reports_dir.mkdir(parents=True, exist_ok=True)
    final = reports_dir / run_id
    if final.exists():
        raise FileExistsError(f"{final} exists: a run never overwrites an earlier report")
    tmp = reports_dir / f".partial-{run_id}"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "figures").mkdir(parents=True)
    try:
        _build(tmp, run_id, ingested, fit_logs, val_logs, params, calib_info, calib_text, val_pngs, artifact,
               case_study, scenario, grids, base_params, command_line, wall_s)
        tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def _build(out, run_id, ingested, fit_logs, val_logs, params, calib_info, calib_text, val_pngs, artifact, cs,
           scenario, grids, base_params, command_line, wall_s):
    synthetic = any(lg.meta.synthetic for _, lg, _ in ingested)
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

    # --- data
    logs_info, reports = [], {}
    data = Section("data", "Data used")
    rows = []
    for path, lg, rep in ingested:
        role = "validation (held out)" if any(lg is v for v in val_logs) else "calibration"
        info = {"file": str(path), "name": lg.name, "format": lg.meta.format, "sha256": lg.meta.sha256,
                "synthetic": bool(lg.meta.synthetic), "duration_s": lg.duration_s, "role": role,
                "channels": lg.channels()}
        logs_info.append(info)
        rows.append({"log": lg.label(), "format": lg.meta.format, "duration s": round(lg.duration_s),
                     "role": role, "sha256": lg.meta.sha256[:16] + "...", "channels": len(lg.channels())})
        rep = rep.reset_index() if rep.index.name else rep
        reports[lg.name] = rep
        rep.to_csv(out / f"channels_{Path(lg.name).stem}.csv", index=False)
    data.table(pd.DataFrame(rows))
    for name, rep in reports.items():
        data.table(rep, f"channel report: {name}")

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
        ptab.append({"parameter": n, "value": val, "unit": p.unit, "stderr": se, "status": p.status,
                     "note": p.note})
    cal.table(pd.DataFrame(ptab))
    val = (calib_info.get("validation") or {}).get("metrics", {})
    vrows = []
    for lname, chans in val.items():
        for ch, m in (chans or {}).items():
            if isinstance(m, dict):
                vrows.append({"log": lname, "channel": ch, **{k: v for k, v in m.items()
                                                               if isinstance(v, (int, float, str))}})
    if vrows:
        cal.table(pd.DataFrame(vrows), "validation on held-out logs: the calibrated model replayed from the "
                                       "logged inputs")
    for i, png in enumerate(val_pngs):
        dst = out / "figures" / Path(png).name
        shutil.copyfile(png, dst)
        cal.figure(dst, "measured vs simulated (paper Fig. 3 style)")
    cal.pre(calib_text)

    # --- optimisation
    opt = Section("optimisation", "Optimisation: rule-based vs the three DP formulations")
    tab = cs.table().reset_index(drop=True)
    keep = [c for c in ("strategy", "fuel_g", "fuel_corrected_g", "soc_final", "T_cl_final_degC", "T_cl_mean_degC",
                        "T_cab_final_degC", "T_cab_mean_degC", "engine_starts", "idle_s", "charge_sustaining",
                        "saving_vs_rule_pct", "paper_vs_rule_pct", "saving_vs_baseline_pct",
                        "paper_vs_baseline_pct") if c in tab.columns]
    opt.p(f"Scenario: cycle {scenario.cycle}, ambient {scenario.T_amb:g} degC, SOC0 {scenario.soc0:g}, "
          f"coolant {scenario.T_cl0:g} degC, cabin {scenario.T_cab0:g} degC, heater {scenario.Q_heat:g} W "
          f"(Thermal-Cabin: {scenario.Q_heat_min:g}-{scenario.Q_heat_max:g} W). Grids: "
          + ", ".join(f"{k} {v:g}" for k, v in grids.to_dict().items()) + ".")
    opt.table(tab[keep], "fuel and final states of each strategy; savings next to the paper's. Corrected fuel "
                         "accounts for differences in final stored electric and thermal energy.")
    ok = cs.ordering_ok() if hasattr(cs, "ordering_ok") else None
    opt.p(f"Ordering rule-based > Baseline-DP on the thermal model > Thermal-DP > Thermal-Cabin-DP in fuel: "
          f"{'holds' if ok else 'does NOT hold (see the README for the physical explanation)'}.")
    if cs.rule:
        opt.p("Tuned rule-based thresholds: " + ", ".join(f"{k} = {v:g}" for k, v in cs.rule["thresholds"].items()))
    for png in cs.plot_figures(out / "figures"):
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
        strat[r["key"]] = {k: r.get(k) for k in ("fuel_g", "fuel_corrected_g", "soc_final", "T_cl_final_degC",
                                                  "T_cab_final_degC", "T_cab_mean_degC", "saving_vs_rule_pct",
                                                  "saving_vs_baseline_pct", "charge_sustaining")}
    statuses = [params.param(n).status for n in params]
    summary = {"run_id": run_id, "synthetic_data": synthetic, "strategies": strat, "ordering_ok": ok,
               "n_estimated": statuses.count("estimated"), "n_weak": statuses.count("weak"),
               "wall_s": wall_s}
    lines = [f"{k}: {v['fuel_g']:.1f} g" + (f" ({v['saving_vs_rule_pct']:.2f} % below rule-based)"
                                              if v.get("saving_vs_rule_pct") not in (None, 0.0) else "")
             for k, v in strat.items()]
    summ.p("Fuel over the scenario: " + "; ".join(lines) + ".")
    summ.p(f"Calibration: {summary['n_estimated']} parameters estimated, {summary['n_weak']} weakly informed "
           f"(posterior mostly the prior).")

    banner = ("SYNTHETIC DATA: the logs in this report were simulated by the workbench from known truth "
              "parameters; they are not measurements.") if synthetic else ""
    html = render(f"iptm report {run_id}", [summ, data, cal, opt, pr], banner=banner)
    write_text(out / "index.html", html)
    write_json(out / "report.json", _clean({
        "summary": summary, "provenance": prov, "channel_reports": {k: v.to_dict(orient="records")
                                                                    for k, v in reports.items()},
        "calibration": calib_info, "case_study": cs.to_dict(),
        "figures": sorted(p.name for p in (out / "figures").glob("*.png")),
        "time_series": {k: _series(s) for k, s in cs.sims.items()}}))
