"""Calibration on test cars that are not our model, with the targets beside every figure.

Sections (``iptm bench calib``; ``--quick``: one perturbed seed, no repeated timing):

1. **FASTSim 3 Sonata** (:mod:`calib.synth_fastsim`, needs the ``fastsim`` extra): calibrate on the two
   cold-soaked -7 degC drives, validate on the held-out warm restart and the 22 degC drive: cumulative
   fuel error, cabin and SOC RMSE, coolant RMSE per coolant-temperature regime; then the calibrated
   model's cold (-7 degC soak) over warm (22 degC) UDDS fuel per km (simulated with the rule-based
   controller and a 22 degC climate control) against FASTSim's own ratio.
2. **Perturbed-structure synthesiser** (:mod:`calib.synth_perturbed`, seeds 1-3): calibrate on the two
   cold-start drives, validate on the held-out warm restart; ``f_cl`` at -10 and 0 degC against the
   truth; coverage of the truth by the reported 95 % intervals (value +- 1.96 sd) over the fitter's
   parameters that have a counterpart in the plant.
3. **Missing channels**: the perturbed seed-1 drives without engine speed/torque, and without heater
   data (vent temperature, blower flow): does calibration run, what each subsystem used, what the
   validation reports.
4. **OBD-style logs** of the perturbed seed-1 car (:func:`calib.synth_perturbed.synthesise_perturbed_obd`):
   the two calibration drives and a parked cold start at idle as an OBD-II tool logs them (PIDs polled in
   turn, each every 5-15 s; fuel from the MAF as a labelled estimate; battery current, voltage and SOC from
   CAN at 10 Hz; no heater, cabin, engine torque or power channel), calibrated with the heater heat
   estimated, and the warm-up alone with the heater declared off: engine-thermal parameters against the
   plant's, and the held-out coolant RMSE and cumulative fuel beside the same car's full-channel
   calibration on the same held-out log; the time each calibration took.
5. **Wall time** of calibrating 1 hour of logs (the two perturbed calibration drives cut to 30 min each;
   median of 3 runs, with the load average: the machine is shared).

Every log is SYNTHETIC. Figures are printed, never asserted.
"""
from __future__ import annotations

import os
import time

import numpy as np

TARGETS = {
    "fastsim_fuel_pct": 5.0, "fastsim_cabin_rmse": 1.0, "fastsim_soc_rmse": 0.02, "fastsim_udds_ratio_pct": 10.0,
    "pert_fuel_pct": 3.0, "pert_coolant_rmse": 1.5, "pert_soc_rmse": 0.01, "pert_fcl_pct": 10.0,
    "coverage": 0.90, "wall_1h_s": 10.0, "obd_warmup_C_eng_pct": 20.0,
}
#: Coolant regimes (measured coolant temperature, degC) for the FASTSim error breakdown.
REGIMES = [("below 40", -100.0, 40.0), ("40-80 warm-up", 40.0, 80.0), ("80-95 thermostat", 80.0, 95.0),
           ("above 95 (FASTSim: radiator off while moving)", 95.0, 1e9)]


def _mark(ok) -> str:
    return "n/a" if ok is None else ("MEETS" if ok else "MISSES")


def _replay(log, params):
    """The validation replay, or the message of its refusal."""
    from calib.errors import IptmError
    from calib.fit.validate import replay

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


# ---------------------------------------------------------------------------------------- FASTSim
def fastsim_section() -> dict:
    from calib.fit.driver import calibrate
    from calib.ingest import to_drivelog
    from calib.synth_fastsim import (SONATA, fastsim_available, pack_energy_J, synthesise_fastsim,
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
    t0 = time.perf_counter()
    try:
        res = calibrate(cal, progress=False)
    except Exception as exc:  # noqa: BLE001 - the benchmark reports any failure as a figure
        print(f"   calibration FAILED: {type(exc).__name__}: {exc}")
        return {"calibration_error": str(exc)}
    wall = time.perf_counter() - t0
    print(f"   calibration of {sum(lg.duration_s for lg in cal) / 60:.0f} min of logs: {wall:.1f} s")
    for line in _fit_summary(res):
        print(line)
    fig = {"calibration_wall_s": wall, "validation": {}}
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
          "Evidence: scripts/fastsim_structure.py, docs/test_cars.md.")
    return fig


def model_udds_ratio(params) -> dict:
    """Fuel per km of ``params`` on a cold-soaked -7 degC UDDS over a 22 degC one (rule-based controller,
    climate control at 22 degC without base heat)."""
    from calib.errors import IptmError
    from calib.model.rulebased import RuleParams
    from calib.model.simulate import simulate
    from calib.synth import HvacController

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
    from calib.fit.driver import calibrate
    from calib.synth_perturbed import CALIBRATION, perturbed_logs, score

    print(f"-- perturbed-structure synthesiser (SYNTHETIC), seeds {', '.join(map(str, seeds))}: calibrate on "
          f"{len(CALIBRATION)} cold-start drives, validate on a held-out warm restart")
    runs, pairs = [], []
    for seed in seeds:
        logs, plant = perturbed_logs(seed)
        cal, val = logs[:len(CALIBRATION)], logs[len(CALIBRATION):]
        t0 = time.perf_counter()
        res = calibrate(cal, validate=val, progress=False)
        wall = time.perf_counter() - t0
        print(f"   seed {seed}: calibration {wall:.1f} s on {sum(lg.duration_s for lg in cal) / 60:.0f} min of logs")
        run = {"seed": seed, "wall_s": wall, "validation": res.validation, "params": {}}
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
    from calib.fit.driver import calibrate
    from calib.synth_perturbed import CALIBRATION, ENGINE_CHANNELS, HEATER_CHANNELS, perturbed_logs

    print("-- logs without engine data / without heater data (perturbed seed 1)")
    out = {}
    for label, drop in (("no engine speed/torque", ENGINE_CHANNELS), ("no heater data", HEATER_CHANNELS)):
        logs, _ = perturbed_logs(1, drop_channels=drop)
        cal, val = logs[:len(CALIBRATION)], logs[len(CALIBRATION):]
        print(f"   {label} (dropped: {', '.join(drop)})")
        try:
            res = calibrate(cal, progress=False)
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
    from calib.fit.driver import calibrate
    from calib.ingest import to_drivelog
    from calib.synth_perturbed import (CALIBRATION, PARKED_WARMUP, comparable_truth, perturbed_logs,
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
        t0 = time.perf_counter()
        try:
            res = calibrate(cal, validate=val, progress=False, heater=heater, diagnose=False)
        except Exception as exc:  # noqa: BLE001 - the benchmark reports any failure as a figure
            print(f"   {label}: calibration FAILED: {type(exc).__name__}: {exc}")
            out[label] = {"calibration_error": str(exc)}
            continue
        wall = time.perf_counter() - t0
        print(f"   {label}: calibration of {minutes:.0f} min of logs (validation included) {wall:.1f} s "
              f"({wall / max(minutes, 1e-9) * 60:.1f} s per hour of logs)")
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
    from calib.drivelog import DriveLog
    from calib.fit.driver import calibrate
    from calib.synth_perturbed import CALIBRATION, perturbed_logs

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


def run(quick: bool = False) -> dict:
    seeds = [1] if quick else [1, 2, 3]
    figures = {"targets": TARGETS}
    figures["fastsim"] = fastsim_section()
    figures["perturbed"] = perturbed_section(seeds)
    figures["missing_channels"] = missing_section()
    figures["obd"] = obd_section(1)
    figures["timing"] = timing_section(1 if quick else 3)
    return figures
