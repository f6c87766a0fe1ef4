"""Calibration on test cars that are not our model, with the targets beside every figure.

Sections (``iptm bench calib``; ``--quick``: one perturbed seed, no repeated timing):

1. **FASTSim 3 Sonata** (:mod:`testcars.synth_fastsim`, needs the ``fastsim`` extra): calibrate on the two
   cold-soaked -7 degC drives, validate on the held-out warm restart and the 22 degC drive: cumulative
   fuel error, cabin and SOC RMSE, coolant RMSE per coolant-temperature regime; then the calibrated
   model's cold (-7 degC soak) over warm (22 degC) UDDS fuel per km (simulated with the rule-based
   controller and a 22 degC climate control) against FASTSim's own ratio.
2. **Perturbed-structure synthesiser** (:mod:`testcars.synth_perturbed`, seeds 1-3): calibrate on the two
   cold-start drives, validate on the held-out warm restart; ``f_cl`` at -10 and 0 degC against the
   truth; coverage of the truth by the reported 95 % intervals (value +- 1.96 sd) over the fitter's
   parameters that have a counterpart in the plant.
3. **Missing channels**: the perturbed seed-1 drives without engine speed/torque, and without heater
   data (vent temperature, blower flow): does calibration run, what each subsystem used, what the
   validation reports.
4. **OBD-style logs** of the perturbed seed-1 car (:func:`testcars.synth_perturbed.synthesise_perturbed_obd`):
   the two calibration drives and a parked cold start at idle as an OBD-II tool logs them (PIDs polled in
   turn, each every 5-15 s; fuel from the MAF as a labelled estimate; battery current, voltage and SOC from
   CAN at 10 Hz; no heater, cabin, engine torque or power channel), calibrated with the heater heat
   estimated, and the warm-up alone with the heater declared off: engine-thermal parameters against the
   plant's, and the held-out coolant RMSE and cumulative fuel beside the same car's full-channel
   calibration on the same held-out log; the time each calibration took.
5. **Wall time** of calibrating 1 hour of logs (the two perturbed calibration drives cut to 30 min each;
   median of 3 runs, with the load average: the machine is shared).
6. **Drive selections** (not with ``--quick``; alone: ``python -m iptm.benchmarks.calib --selections``): the
   FASTSim car calibrated on every 2-of-6 split of a pool of cold and warm starts at -7 and 22 degC, each
   scored on its 4 held-out drives (the rule and the table: docs/calibration_robustness.md).

Every calibration is timed (:func:`timed_calibrate`): its wall time per hour of calibration logs against the
target of 10 s per hour (a case over it is flagged) and the time of each step (subsystem fits, validation,
diagnostics); the run ends with the table of every case. The numba kernels are compiled first
(:func:`warm_up`), so no case's time includes the one-off compilation.

Every log is SYNTHETIC. Figures are printed, never asserted.
"""
from __future__ import annotations

import os
import time

import numpy as np

TARGETS = {
    "fastsim_fuel_pct": 5.0, "fastsim_cabin_rmse": 1.0, "fastsim_soc_rmse": 0.02, "fastsim_udds_ratio_pct": 10.0,
    "pert_fuel_pct": 3.0, "pert_coolant_rmse": 1.5, "pert_soc_rmse": 0.01, "pert_fcl_pct": 10.0,
    "coverage": 0.90, "wall_1h_s": 10.0, "obd_warmup_C_eng_pct": 20.0, "s_per_hour": 10.0,
}
#: Coolant regimes (measured coolant temperature, degC) for the FASTSim error breakdown.
REGIMES = [("below 40", -100.0, 40.0), ("40-80 warm-up", 40.0, 80.0), ("80-95 thermostat", 80.0, 95.0),
           ("above 95 (FASTSim: radiator off while moving)", 95.0, 1e9)]


def _mark(ok) -> str:
    return "n/a" if ok is None else ("MEETS" if ok else "MISSES")


def _replay(log, params):
    """The validation replay, or the message of its refusal."""
    from calib import IptmError
    from calib.fit import replay

    try:
        return replay(log, params), None
    except IptmError as exc:
        return None, str(exc)


def _val_line(m: dict) -> str:
    parts = []
    cf = m.get("cumulative_fuel")
    if cf:
        parts.append(f"cumulative fuel {cf['error_pct']:+.2f} % ({cf['simulated_g']:.0f} vs {cf['measured_g']:.0f} g)")
    for k in ("soc", "coolant_temp", "cabin_temp"):
        if k in m:
            parts.append(f"{k} RMSE {m[k]['rmse']:.3g}")
    return "; ".join(parts) or "no metrics"


def _fit_summary(res) -> list[str]:
    out = []
    for name, f in res.fits.items():
        est = [n for n, e in f.estimates.items() if e.status == "estimated"]
        line = f"    [{name}] logs used: {len(f.logs)}; estimated: {', '.join(est) or 'none'}"
        if f.message:
            line += f"; {f.message}"
        out.append(line)
        for lg, why in f.skipped.items():
            out.append(f"      skipped {lg}: {why}")
    return out


# ---------------------------------------------------------------------------------------- timing per case
#: Every timed calibration of a run: case, hours of calibration logs, wall time, per-step times.
CASES: list = []


def timed_calibrate(case: str, cal, **kw):
    """``calibrate(cal, progress=False, **kw)``, timed: prints the wall time per hour of logs (flagged
    above the target) and the time of each step (subsystem fits, validation, diagnostics), and records the
    case in :data:`CASES`. Returns the result; an exception propagates."""
    from calib.fit import calibrate

    hours = sum(lg.duration_s for lg in cal) / 3600.0
    t0 = time.perf_counter()
    res = calibrate(cal, progress=False, **kw)
    wall = time.perf_counter() - t0
    rate = wall / max(hours, 1e-9)
    steps = dict(res.timings or {})
    CASES.append({"case": case, "hours": hours, "wall_s": wall, "s_per_hour": rate, "steps_s": steps,
                  "load_average": _load()})
    flag = "" if rate <= TARGETS["s_per_hour"] else "  OVER TARGET"
    print(f"   time: {wall:.2f} s for {hours:.2f} h of logs = {rate:.2f} s per hour "
          f"[target <= {TARGETS['s_per_hour']:g}: {_mark(rate <= TARGETS['s_per_hour'])}]{flag}; "
          + ", ".join(f"{k} {v:.2f} s" for k, v in steps.items()))
    return res


def _load() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def warm_up() -> float:
    """Compile (or load) the numba kernels once, on 5 minutes of a perturbed drive, so that no case's time
    includes the one-off compilation (its cache is keyed by the sources: any edit compiles afresh)."""
    from calib import DriveLog
    from calib.fit import calibrate
    from testcars.synth_perturbed import CALIBRATION, perturbed_logs

    logs, _ = perturbed_logs(1, drives=CALIBRATION[:1])
    t0 = time.perf_counter()
    calibrate([DriveLog(lg.data.loc[:300.0].copy(), lg.meta) for lg in logs], progress=False)
    wall = time.perf_counter() - t0
    print(f"-- kernels compiled or loaded from the cache: {wall:.1f} s (once per process; not in any case's time)")
    return wall


def cases_summary() -> dict:
    """The table of every timed case; cases over the target flagged."""
    print(f"-- time per case (calibration wall time, validation and diagnostics included where the case runs them; "
          f"load average now {_load():.1f} on {os.cpu_count()} cores: the machine is shared)")
    print(f"   {'case':70s} {'h of logs':>9s} {'wall s':>7s} {'s per h':>8s}  slowest step")
    over = []
    for c in CASES:
        slow = max(c["steps_s"].items(), key=lambda kv: kv[1]) if c["steps_s"] else ("-", 0.0)
        bad = c["s_per_hour"] > TARGETS["s_per_hour"]
        if bad:
            over.append(c["case"])
        print(f"   {c['case'][:70]:70s} {c['hours']:9.2f} {c['wall_s']:7.2f} {c['s_per_hour']:8.2f}  "
              f"{slow[0]} {slow[1]:.2f} s{'  OVER TARGET' if bad else ''}")
    worst = max((c["s_per_hour"] for c in CASES), default=float("nan"))
    print(f"   slowest case {worst:.2f} s per hour of logs  [target every case <= {TARGETS['s_per_hour']:g} s/h: "
          f"{_mark(not over) if CASES else 'n/a'}]" + (f"; over: {', '.join(over)}" if over else ""))
    return {"cases": list(CASES), "max_s_per_hour": worst, "over_target": over}


# ---------------------------------------------------------------------------------------- FASTSim
def fastsim_section() -> dict:
    from calib.ingest import to_drivelog
    from testcars.synth_fastsim import (SONATA, fastsim_available, pack_energy_J, synthesise_fastsim,
                                     udds_cold_warm_ratio)

    print("-- FASTSim 3 Sonata thermal HEV (SYNTHETIC): calibrate on 2 cold drives, validate on a warm restart "
          "and a 22 degC drive")
    if not fastsim_available():
        print("   skipped: the optional package fastsim is not installed (pip install 'iptm[fastsim]')")
        return {"skipped": "fastsim not installed"}
    logs = {}
    for i, sc in enumerate(SONATA):
        _, streams, meta = synthesise_fastsim(sc, seed=7 + i)
        logs[sc.name] = to_drivelog(streams, meta)
    names = list(logs)
    cal, val = [logs[n] for n in names[:2]], [logs[n] for n in names[2:]]
    try:
        res = timed_calibrate("FASTSim Sonata: 2 cold drives", cal)
    except Exception as exc:  # noqa: BLE001 - the benchmark reports any failure as a figure
        print(f"   calibration FAILED: {type(exc).__name__}: {exc}")
        return {"calibration_error": str(exc)}
    for line in _fit_summary(res):
        print(line)
    fig = {"calibration_wall_s": CASES[-1]["wall_s"], "steps_s": CASES[-1]["steps_s"], "validation": {}}
    bat = res.fits.get("battery")
    if bat is not None and "energy_capacity_kWh_at_soc_0_6" in bat.metrics:
        e_fit, e_true = bat.metrics["energy_capacity_kWh_at_soc_0_6"], pack_energy_J() / 3.6e6
        fig["battery_energy_kWh"] = {"fitted": e_fit, "fastsim": e_true}
        print(f"   battery energy from power and SOC: {e_fit:.2f} kWh (C_bat_Ah at the prior OCV; "
              f"{bat.estimates['C_bat_Ah'].status}) against FASTSim's {e_true:.2f} kWh ({100 * (e_fit / e_true - 1):+.1f} %)")
    for lg in val:
        rep, refused = _replay(lg, res.params)
        if rep is None:
            print(f"   held out {lg.name}: validation refused: {refused}")
            fig["validation"][lg.name] = {"refused": refused}
            continue
        m = rep.metrics()
        cf = m.get("cumulative_fuel", {}).get("error_pct")
        cab = m.get("cabin_temp", {}).get("rmse")
        soc = m.get("soc", {}).get("rmse")
        print(f"   held out {lg.name} (inputs: {getattr(rep, 'inputs', '?')})")
        print(f"     cumulative fuel error {cf:+.2f} %  [target |err| <= {TARGETS['fastsim_fuel_pct']:g} %: "
              f"{_mark(None if cf is None else abs(cf) <= TARGETS['fastsim_fuel_pct'])}]" if cf is not None
              else "     cumulative fuel: not computed")
        print(f"     cabin RMSE {cab:.2f} degC  [target <= {TARGETS['fastsim_cabin_rmse']:g}: "
              f"{_mark(cab <= TARGETS['fastsim_cabin_rmse'])}]" if cab is not None else "     cabin: not computed")
        print(f"     SOC RMSE {soc:.4f}  [target <= {TARGETS['fastsim_soc_rmse']:g}: "
              f"{_mark(soc <= TARGETS['fastsim_soc_rmse'])}]" if soc is not None else "     SOC: not computed")
        reg = {}
        meas, sim = rep.measured.get("coolant_temp"), rep.simulated.get("coolant_temp")
        if meas is not None and sim is not None:
            for label, lo, hi in REGIMES:
                sel = np.isfinite(meas) & np.isfinite(sim) & (meas >= lo) & (meas < hi)
                if sel.sum() >= 10:
                    e = sim[sel] - meas[sel]
                    reg[label] = {"rmse": float(np.sqrt(np.mean(e * e))), "bias": float(np.mean(e)), "n": int(sel.sum())}
                    print(f"     coolant {label:46s} RMSE {reg[label]['rmse']:6.2f} degC, bias "
                          f"{reg[label]['bias']:+6.2f}, {reg[label]['n']} s")
        fig["validation"][lg.name] = {"metrics": m, "coolant_by_regime": reg, "inputs": getattr(rep, "inputs", "")}
    # cold/warm UDDS ratio: FASTSim vs the calibrated model
    fr = udds_cold_warm_ratio()
    mr = model_udds_ratio(res.params)
    # what the fuel and thermal fits took from the logs (anything else in the ratio is a prior)
    est = [n for sub in ("fuel", "thermal") if sub in res.fits
           for n, e in res.fits[sub].estimates.items() if e.status in ("estimated", "weak")]
    fig["udds"] = {"estimated_fuel_thermal": est}
    fig["udds"].update(fastsim=fr, model=mr)
    print(f"   UDDS fuel per km, cold-soaked -7 degC / 22 degC: FASTSim {fr['ratio']:.3f} "
          f"({fr['cold_g_per_km']:.1f} / {fr['warm_g_per_km']:.1f} g/km)")
    if "error" in mr:
        print(f"   calibrated model: simulation failed: {mr['error']}")
    else:
        dev = 100 * (mr["ratio"] / fr["ratio"] - 1)
        fig["udds"]["deviation_pct"] = dev
        print(f"   calibrated model {mr['ratio']:.3f} ({mr['cold_g_per_km']:.1f} / {mr['warm_g_per_km']:.1f} g/km, "
              f"Prius road load and controller): {dev:+.1f} %  [target within {TARGETS['fastsim_udds_ratio_pct']:g} %: "
              f"{_mark(abs(dev) <= TARGETS['fastsim_udds_ratio_pct'])}]")
        print(f"     fuel and engine-thermal parameters estimated from the FASTSim logs: "
              f"{', '.join(est) or 'none, so this is the prior model ratio, not a calibrated one'}")
    print("   structure mismatch: FASTSim's radiator acts only while the car is stopped, so its engine runs to "
          "120-160 degC on a highway where our thermostat model holds ~90 degC; its engine runs at one power "
          "(~14.8 kW), so the warm fuel map is seen at one point; its heater passes up to 15 kW from a cold engine; "
          "its engine efficiency keeps rising above the thermostat, its fuel per unit work 21 % lower above 120 degC "
          "than at 80-85 degC (our f_cl may fall "
          "below 1 above 80 degC, with a prior sd of 1.5 % per 10 K, and is flat beyond 120 degC); its battery "
          "loses a fixed fraction of the power at each C-rate, independent of temperature below 23 degC (ours: "
          "U_hyst |I| + R I^2, R falling with temperature; the hysteresis takes the proportional loss). "
          "Evidence: studies/fastsim_structure/fastsim_structure.py, docs/test_cars.md.")
    return fig


def model_udds_ratio(params) -> dict:
    """Fuel per km of ``params`` on a cold-soaked -7 degC UDDS over a 22 degC one (rule-based controller,
    climate control at 22 degC without base heat)."""
    from calib import IptmError
    from calib.model import RuleParams, simulate
    from calib import HvacController

    out = {}
    try:
        for key, T in (("cold", -7.0), ("warm", 22.0)):
            ctrl = HvacController(params.model_params(), RuleParams(), T_set=22.0, Q_base_W=0.0)
            r = simulate(params, "udds", ctrl, T_amb=T, soc0=0.6, T_cl0=T, T_cab0=T, T_bat=T)
            out[f"{key}_g_per_km"] = r.fuel_g / r.distance_km
    except IptmError as exc:
        return {"error": str(exc)}
    out["ratio"] = out["cold_g_per_km"] / out["warm_g_per_km"]
    return out


# ---------------------------------------------------------------------------------------- perturbed
def perturbed_section(seeds) -> dict:
    from testcars.synth_perturbed import CALIBRATION, perturbed_logs, score

    print(f"-- perturbed-structure synthesiser (SYNTHETIC), seeds {', '.join(map(str, seeds))}: calibrate on "
          f"{len(CALIBRATION)} cold-start drives, validate on a held-out warm restart")
    runs, pairs = [], []
    for seed in seeds:
        logs, plant = perturbed_logs(seed)
        cal, val = logs[:len(CALIBRATION)], logs[len(CALIBRATION):]
        print(f"   seed {seed}: calibration on {sum(lg.duration_s for lg in cal) / 60:.0f} min of logs")
        res = timed_calibrate(f"perturbed seed {seed}: 2 cold drives (validation included)", cal, validate=val)
        run = {"seed": seed, "wall_s": CASES[-1]["wall_s"], "validation": res.validation, "params": {}}
        for lg, m in res.validation.items():
            cf = m.get("cumulative_fuel", {}).get("error_pct")
            cool = m.get("coolant_temp", {}).get("rmse")
            soc = m.get("soc", {}).get("rmse")
            print(f"     held out {lg}")
            if cf is not None:
                print(f"       cumulative fuel error {cf:+.2f} %  [target |err| <= {TARGETS['pert_fuel_pct']:g} %: "
                      f"{_mark(abs(cf) <= TARGETS['pert_fuel_pct'])}]")
            if cool is not None:
                print(f"       coolant RMSE {cool:.2f} degC  [target <= {TARGETS['pert_coolant_rmse']:g}: "
                      f"{_mark(cool <= TARGETS['pert_coolant_rmse'])}]")
            if soc is not None:
                print(f"       SOC RMSE {soc:.4f}  [target <= {TARGETS['pert_soc_rmse']:g}: "
                      f"{_mark(soc <= TARGETS['pert_soc_rmse'])}]")
        print(f"     {'parameter':16s} {'truth':>11s} {'estimate':>11s} {'sd':>9s} {'status':>13s}  95 % interval")
        for r in score(res.params, plant):
            name, tv, v, sd, covered = r["name"], r["truth"], r["estimate"], r["sd"], r["covered"]
            pairs.append(covered)
            run["params"][name] = r
            extra = ""
            if name.startswith("f_cl@"):
                dev = 100 * (v / tv - 1)
                extra = f"  {dev:+.1f} % [target within {TARGETS['pert_fcl_pct']:g} %: {_mark(abs(dev) <= TARGETS['pert_fcl_pct'])}]"
            sds = f"{sd:9.3g}" if sd is not None else "        -"
            cov = "no interval" if covered is None else ("contains truth" if covered else "MISSES truth")
            print(f"     {name:16s} {tv:11.5g} {v:11.5g} {sds} {r['status']:>13s}  {cov}{extra}")
        runs.append(run)
    n_all = len(pairs)
    n_int = sum(c is not None for c in pairs)
    n_cov = sum(bool(c) for c in pairs)
    print(f"   95 % interval coverage: {n_cov}/{n_all} parameter-seed pairs contain the truth ({n_int} have an "
          f"interval; {n_all - n_int} report none)  [target >= {100 * TARGETS['coverage']:.0f} % of pairs: "
          f"{_mark(n_all and n_cov / n_all >= TARGETS['coverage'])}]")
    return {"runs": runs, "coverage": {"pairs": n_all, "with_interval": n_int, "covered": n_cov}}


# ---------------------------------------------------------------------------------------- missing data
def missing_section() -> dict:
    from testcars.synth_perturbed import CALIBRATION, ENGINE_CHANNELS, HEATER_CHANNELS, perturbed_logs

    print("-- logs without engine data / without heater data (perturbed seed 1)")
    out = {}
    for label, drop in (("no engine speed/torque", ENGINE_CHANNELS), ("no heater data", HEATER_CHANNELS)):
        logs, _ = perturbed_logs(1, drop_channels=drop)
        cal, val = logs[:len(CALIBRATION)], logs[len(CALIBRATION):]
        print(f"   {label} (dropped: {', '.join(drop)})")
        try:
            res = timed_calibrate(f"perturbed seed 1, {label}", cal)
        except Exception as exc:  # noqa: BLE001 - reported as the figure
            print(f"     calibration FAILED: {type(exc).__name__}: {exc}")
            out[label] = {"calibration_error": str(exc)}
            continue
        print("     calibration ran")
        for line in _fit_summary(res):
            print("  " + line)
        rep, refused = _replay(val[0], res.params)
        if rep is None:
            print(f"     validation refused: {refused}")
            out[label] = {"validation_refused": refused}
        else:
            m = rep.metrics()
            print(f"     validation (inputs: {getattr(rep, 'inputs', '?')}): {_val_line(m)}")
            out[label] = {"validation": m, "inputs": getattr(rep, "inputs", "")}
    return out


# ---------------------------------------------------------------------------------------- OBD-style logs
OBD_THERMAL = ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K")


def obd_section(seed: int = 1) -> dict:
    from calib.ingest import to_drivelog
    from testcars.synth_perturbed import (CALIBRATION, PARKED_WARMUP, comparable_truth, perturbed_logs,
                                       synthesise_perturbed_obd)

    print(f"-- OBD-style logs of the perturbed car (seed {seed}, SYNTHETIC): PIDs polled in turn, each every 5-15 s "
          "(coolant, engine speed, speed, MAF -> fuel as a labelled estimate, ambient); battery current, voltage and "
          "SOC from CAN at 10 Hz; no heater, cabin, engine torque or power channel")
    logs, plant = perturbed_logs(seed)
    cal_full, val = logs[:len(CALIBRATION)], logs[len(CALIBRATION):]
    drives = CALIBRATION + [PARKED_WARMUP]
    obd = [to_drivelog(*synthesise_perturbed_obd(d, plant, seed=100 * seed + i)[1:]) for i, d in enumerate(drives)]
    truth = comparable_truth(plant)["values"]
    cases = [("full channels: 2 cold-start drives", cal_full, None),
             ("OBD: the same 2 drives + a parked warm-up, heater estimated", obd, None),
             ("OBD: parked warm-up alone (7 min at idle, -1 degC), heater declared off", obd[-1:], "off")]
    out = {}
    for label, cal, heater in cases:
        minutes = sum(lg.duration_s for lg in cal) / 60
        print(f"   {label}: calibration of {minutes:.0f} min of logs (validation included)")
        try:
            res = timed_calibrate(f"OBD seed {seed}, {label}", cal, validate=val, heater=heater, diagnose=False)
        except Exception as exc:  # noqa: BLE001 - the benchmark reports any failure as a figure
            print(f"   {label}: calibration FAILED: {type(exc).__name__}: {exc}")
            out[label] = {"calibration_error": str(exc)}
            continue
        wall = CASES[-1]["wall_s"]
        th = res.fits["thermal"]
        for lg, used in th.used.items():
            if "heater heat" in used:
                print(f"     heater heat of {lg}: {used['heater heat']}")
        fig = {"minutes": minutes, "wall_s": wall, "params": {}}
        for n in OBD_THERMAL:
            p = res.params.param(n)
            tv = float(truth[n])
            dev = 100 * (float(p.value) / tv - 1)
            sd = f"{p.stderr:.3g}" if isinstance(p.stderr, (int, float)) and np.isfinite(p.stderr) else "-"
            extra = ""
            if n == "C_eng_J_per_K" and heater == "off":
                ok = p.status == "estimated" and abs(dev) <= TARGETS["obd_warmup_C_eng_pct"]
                extra = f"  [target: estimated, within {TARGETS['obd_warmup_C_eng_pct']:g} %: {_mark(ok)}]"
            print(f"     {n:16s} {float(p.value):11.5g} +- {sd:9s} [{p.status}]  plant {tv:11.5g}  {dev:+.1f} %{extra}")
            fig["params"][n] = {"value": float(p.value), "sd": p.stderr, "status": p.status, "truth": tv,
                                "error_pct": dev}
        for lg, m in res.validation.items():
            cf = m.get("cumulative_fuel", {}).get("error_pct")
            cool = m.get("coolant_temp", {}).get("rmse")
            parts = []
            if cool is not None:
                parts.append(f"coolant RMSE {cool:.2f} degC [target <= {TARGETS['pert_coolant_rmse']:g}: "
                             f"{_mark(cool <= TARGETS['pert_coolant_rmse'])}]")
            if cf is not None:
                parts.append(f"cumulative fuel {cf:+.2f} % [target |err| <= {TARGETS['pert_fuel_pct']:g} %: "
                             f"{_mark(abs(cf) <= TARGETS['pert_fuel_pct'])}]")
            for k, why in m.get("refused", {}).items():
                parts.append(f"{k} not checked: {why}")
            print(f"     held out {lg} (full channels): " + ("; ".join(parts) or "no metrics"))
            fig["validation"] = {"log": lg, "coolant_rmse": cool, "fuel_pct": cf}
        out[label] = fig
    return out


# ---------------------------------------------------------------------------------------- timing
def timing_section(repeats: int) -> dict:
    from calib import DriveLog
    from calib.fit import calibrate
    from testcars.synth_perturbed import CALIBRATION, perturbed_logs

    logs, _ = perturbed_logs(1, drives=CALIBRATION)
    cut = [DriveLog(lg.data.loc[:1800.0].copy(), lg.meta) for lg in logs]
    minutes = sum(lg.duration_s for lg in cut) / 60
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        calibrate(cut, progress=False)
        walls.append(time.perf_counter() - t0)
    med = float(np.median(walls))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"-- wall time: calibration of {minutes:.0f} min of logs: median {med:.2f} s over {repeats} run(s) "
          f"(all: {', '.join(f'{w:.2f}' for w in walls)}); load average {load:.1f} on {os.cpu_count()} cores  "
          f"[target <= {TARGETS['wall_1h_s']:g} s on 2 cores: {_mark(med <= TARGETS['wall_1h_s'])}"
          f"{'; measured under load' if load > 1.5 else ''}]")
    return {"minutes": minutes, "walls_s": walls, "median_s": med, "load_average": load}


# ---------------------------------------------------------------------------------------- drive selections
#: The FASTSim drive pool of docs/calibration_robustness.md (the rule is written there; drive i, 1-based,
#: is synthesised with seed SELECTION_SEED + i).
SELECTION_SEED = 100
SELECTION_CAL = 2  # calibration drives per selection: every 2-of-6 split


def selection_pool():
    from testcars.synth_fastsim import SONATA, FastsimScenario

    by = {sc.name: sc for sc in SONATA}
    return [
        ("cold_udds_hwfet", by["sonata_cold_udds_hwfet"]),
        ("cold_nycc_us06_udds", by["sonata_cold_nycc_us06_udds"]),
        ("cold_wltc", FastsimScenario("sonata_cold_wltc", "wltc_city_3b+wltc_high_3b+wltc_extrahigh_3",
                                      -7.0, -7.0, -7.0, -7.0, "cold soak at -7 degC, WLTC class 3b")),
        ("warm_restart", by["sonata_warm_restart"]),
        ("mild_udds_hwfet", by["sonata_mild_udds_hwfet"]),
        ("mild_restart_us06_wltc", FastsimScenario("sonata_mild_restart_us06_wltc", "us06+wltc_city_3b+wltc_high_3b",
                                                   22.0, 80.0, 22.0, 22.0,
                                                   "warm restart at 22 degC: engine 80 degC; US06 + WLTC city + high")),
    ]


#: Estimates recorded per selection (the causes of its misses are read from them).
SELECTION_ESTIMATES = ("C_bat_Ah", "R_int_ohm", "R_int_tc_per_K", "U_hyst_V", "f_cl")


def _est_text(e: dict) -> str:
    if e["x"] is None:
        return f"{e['value']:.4g} ({e['status']})"
    return "[" + ", ".join(f"{x:g}: {v:.3g}" for x, v in zip(e["x"], e["value"])) + f"] ({e['status']})"


def selections_section() -> dict:
    """Every 2-of-6 split of the FASTSim pool into calibration and held-out drives (the rule of
    docs/calibration_robustness.md): held-out cumulative fuel error and SOC RMSE of every selection."""
    from itertools import combinations

    from calib.ingest import to_drivelog
    from testcars.synth_fastsim import fastsim_available, synthesise_fastsim

    print("-- FASTSim drive selections (SYNTHETIC): every 2-of-6 split into calibration and held-out drives "
          "(rule: docs/calibration_robustness.md)")
    if not fastsim_available():
        print("   skipped: the optional package fastsim is not installed (pip install 'iptm[fastsim]')")
        return {"skipped": "fastsim not installed"}
    pool = selection_pool()
    logs = {}
    for i, (key, sc) in enumerate(pool, start=1):
        _, streams, meta = synthesise_fastsim(sc, seed=SELECTION_SEED + i)
        logs[key] = to_drivelog(streams, meta)
    drives = [{"n": i, "key": k, "name": sc.name, "cycle": sc.cycle, "T_amb": sc.T_amb, "T_eng0": sc.T_eng0,
               "minutes": logs[k].duration_s / 60} for i, (k, sc) in enumerate(pool, start=1)]
    rows = []
    for pair in combinations(range(1, len(pool) + 1), SELECTION_CAL):
        cal_keys = [pool[i - 1][0] for i in pair]
        held = [(i, k) for i, (k, _) in enumerate(pool, start=1) if i not in pair]
        label = "+".join(map(str, pair))
        print(f"   selection {label}: calibrate on {', '.join(cal_keys)}")
        row = {"selection": label, "calibration": list(pair), "held_out": {}, "misses": []}
        try:
            res = timed_calibrate(f"FASTSim selection {label}", [logs[k] for k in cal_keys], diagnose=False)
        except Exception as exc:  # noqa: BLE001 - the benchmark reports any failure as a figure
            print(f"     calibration FAILED: {type(exc).__name__}: {exc}")
            row["calibration_error"] = str(exc)
            row["misses"].append("calibration failed")
            rows.append(row)
            continue
        row.update(wall_s=CASES[-1]["wall_s"], s_per_hour=CASES[-1]["s_per_hour"])
        # what the causes of a miss are read from: the battery's loss terms and the coolant fuel factor
        est = {}
        for n in SELECTION_ESTIMATES:
            p = res.params.param(n)
            est[n] = {"value": [float(x) for x in p.value] if p.is_table else float(p.value), "status": p.status,
                      "x": [float(x) for x in p.x] if p.is_table else None}
        row["estimates"] = est
        print("     " + "; ".join(f"{n} {_est_text(e)}" for n, e in est.items()))
        for i, k in held:
            rep, refused = _replay(logs[k], res.params)
            if rep is None:
                row["held_out"][str(i)] = {"refused": refused}
                row["misses"].append(f"{i} not validated")
                continue
            m = rep.metrics()
            fuel = m.get("cumulative_fuel", {}).get("error_pct")
            soc = m.get("soc", {}).get("rmse")
            row["held_out"][str(i)] = {"fuel_pct": fuel, "soc_rmse": soc}
            if fuel is None or abs(fuel) > TARGETS["fastsim_fuel_pct"]:
                row["misses"].append(f"{i} fuel {fuel:+.1f} %" if fuel is not None else f"{i} fuel not computed")
            if soc is None or soc > TARGETS["fastsim_soc_rmse"]:
                row["misses"].append(f"{i} SOC {soc:.3f}" if soc is not None else f"{i} SOC not computed")
        row["meets"] = not row["misses"]
        f = [v["fuel_pct"] for v in row["held_out"].values() if v.get("fuel_pct") is not None]
        so = [v["soc_rmse"] for v in row["held_out"].values() if v.get("soc_rmse") is not None]
        print(f"     held out {', '.join(str(i) for i, _ in held)}: fuel error "
              + ", ".join(f"{x:+.2f} %" for x in f) + "; SOC RMSE " + ", ".join(f"{x:.4f}" for x in so)
              + f"  [targets |fuel| <= {TARGETS['fastsim_fuel_pct']:g} %, SOC <= {TARGETS['fastsim_soc_rmse']:g}: "
              + (_mark(True) if row["meets"] else f"MISSES: {'; '.join(row['misses'])}") + "]")
        rows.append(row)
    n_ok = sum(bool(r.get("meets")) for r in rows)
    print(f"   {n_ok}/{len(rows)} selections meet both targets on every held-out drive")
    out = {"rule": "docs/calibration_robustness.md", "seed_base": SELECTION_SEED, "drives": drives,
           "selections": rows, "meet": n_ok, "targets": {k: TARGETS[k] for k in ("fastsim_fuel_pct",
                                                                               "fastsim_soc_rmse", "s_per_hour")},
           "load_average": _load(), "cpus": os.cpu_count()}
    print(selections_table(out))
    return out


def selections_table(d: dict) -> str:
    """Markdown table of a :func:`selections_section` result (the block of docs/calibration_robustness.md)."""
    n = [dr["n"] for dr in d["drives"]]
    head = ("| calibration drives | " + " | ".join(f"held out {i}: fuel, SOC RMSE" for i in n)
            + " | s per hour of logs | targets |")
    rows = [head, "|" + "---|" * (len(n) + 3)]
    for r in d["selections"]:
        cells = []
        for i in n:
            if i in r["calibration"]:
                cells.append("(calibration)")
                continue
            h = r["held_out"].get(str(i), {})
            if "refused" in h:
                cells.append("not validated")
            else:
                fuel, soc = h.get("fuel_pct"), h.get("soc_rmse")
                cells.append(("-" if fuel is None else f"{fuel:+.1f} %") + ", " + ("-" if soc is None else f"{soc:.4f}"))
        rate = f"{r['s_per_hour']:.1f}" if "s_per_hour" in r else "-"
        verdict = "meets" if r.get("meets") else "misses: " + "; ".join(r["misses"])
        rows.append(f"| {' + '.join(map(str, r['calibration']))} | " + " | ".join(cells) + f" | {rate} | {verdict} |")
    t = d["targets"]
    rows.append("")
    rows.append(f"{d['meet']} of {len(d['selections'])} selections meet |fuel error| <= {t['fastsim_fuel_pct']:g} % "
                f"and SOC RMSE <= {t['fastsim_soc_rmse']:g} on every held-out drive; calibration times measured "
                f"at load average {d['load_average']:.1f} on {d['cpus']} cores (a shared machine).")
    return "\n".join(rows)


BLOCK = "calib-selections"


def render_doc(doc_path, data: dict) -> None:
    """Rewrite the ``<!-- figures:calib-selections -->`` block of ``doc_path`` from ``data``."""
    import re
    from pathlib import Path

    from calib import IptmError

    p = Path(doc_path)
    text = p.read_text(encoding="utf-8")
    pat = re.compile(rf"(<!-- figures:{BLOCK} -->)(.*?)(<!-- /figures:{BLOCK} -->)", re.S)
    if not pat.search(text):
        raise IptmError(f"{doc_path}: no <!-- figures:{BLOCK} --> ... <!-- /figures:{BLOCK} --> block to rewrite; "
                        "add one where the table belongs")
    p.write_text(pat.sub(lambda m: m.group(1) + "\n" + selections_table(data) + "\n" + m.group(3), text),
                 encoding="utf-8")


def run(quick: bool = False, selections: bool | None = None) -> dict:
    """All sections; ``selections`` (default: not ``quick``) adds the FASTSim drive selections."""
    seeds = [1] if quick else [1, 2, 3]
    CASES.clear()
    figures = {"targets": TARGETS}
    figures["warm_up_s"] = warm_up()
    figures["fastsim"] = fastsim_section()
    figures["perturbed"] = perturbed_section(seeds)
    figures["missing_channels"] = missing_section()
    figures["obd"] = obd_section(1)
    figures["timing"] = timing_section(1 if quick else 3)
    if selections if selections is not None else not quick:
        figures["selections"] = selections_section()
    figures["per_case"] = cases_summary()
    return figures


def main(argv=None) -> int:
    """``python -m iptm.benchmarks.calib --selections [--json FILE] [--docs PAGE] [--render-only]``."""
    import argparse
    import json

    from calib import IptmError, write_json

    ap = argparse.ArgumentParser(prog="python -m iptm.benchmarks.calib",
                                 description="the FASTSim drive selections of docs/calibration_robustness.md")
    ap.add_argument("--selections", action="store_true", help="run the drive selections (the only section here)")
    ap.add_argument("--json", metavar="FILE", help="write the selections' figures as JSON")
    ap.add_argument("--docs", metavar="PAGE", help="rewrite the page's calib-selections block from the figures")
    ap.add_argument("--render-only", action="store_true", help="read --json instead of running, then --docs")
    a = ap.parse_args(argv)
    try:
        if a.render_only:
            if not (a.json and a.docs):
                raise IptmError("--render-only needs --json FILE (the figures to read) and --docs PAGE")
            try:
                d = json.loads(open(a.json, encoding="utf-8").read())
                # this module's own JSON, or that of `iptm bench calib --json`
                data = d["selections"] if "selections" in d else d["calib"]["selections"]
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise IptmError(f"--json {a.json}: cannot read selection figures from it ({exc}); write it with "
                                "--selections --json FILE") from None
        else:
            if not a.selections:
                raise IptmError("nothing to do: give --selections (or --render-only with --json and --docs)")
            CASES.clear()
            warm_up()
            data = selections_section()
            cases_summary()
            if "skipped" in data:
                raise IptmError("the drive selections need the optional package fastsim: pip install 'iptm[fastsim]'")
            if a.json:
                write_json(a.json, {"selections": data})
        if a.docs:
            render_doc(a.docs, data)
    except IptmError as exc:
        print(f"error: {exc}")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
