"""Drive plans in closed loop on cars that are not our model (``python -m iptm.benchmarks.plan``).

For each foreign car (FASTSim 3's thermal Sonata, :mod:`testcars.synth_fastsim`; the perturbed-structure
plant, :mod:`testcars.synth_perturbed`): calibrate on its usual calibration drives, let :func:`calib.design.make_plan`
design a drive for the parameters the logs left weakest (a cold start at the first calibration drive's
ambient; the heater schedule is left to the car's own climate control: neither car takes a heater command),
drive the plan with the foreign car, and calibrate again with it. The same is done with an equally long
UDDS and HWFET (repeated and cut to the plan's length, same start); each added drive's sd is also predicted
on the log the car wrote (the same linearisation fed with the car's own trajectory). The perturbed plant is held out on its
own warm restart plus a highway drive of this benchmark that reaches the thermostat. Printed per car: each target's posterior
sd now, predicted (our model's linearisation) and achieved (the re-calibration), the estimates against the
car's own value where it has a counterpart, and the held-out coolant error by coolant regime and cabin error.
Every log is SYNTHETIC.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: Coolant regimes (measured coolant, degC) of the held-out error.
REGIMES = [("below 40", -100.0, 40.0), ("40-80", 40.0, 80.0), ("80 and above", 80.0, 1e9)]


def _calibrate(logs):
    from calib import calibrate

    t0 = time.perf_counter()
    res = calibrate(logs, progress=False, diagnose=False)
    return res, time.perf_counter() - t0


def _prior(res, tmp):
    from calib.design import ArtifactPrior

    path = Path(tmp) / f"artifact_{id(res)}.json"
    res.to_artifact(path)
    return ArtifactPrior.load(path)


def held_out_errors(params, logs) -> dict:
    """Coolant RMSE per :data:`REGIMES` and cabin RMSE (degC) of the validation replay over ``logs`` pooled."""
    from calib import IptmError
    from calib import replay

    err = {label: [] for label, _, _ in REGIMES}
    err["cabin"] = []
    for lg in logs:
        try:
            rep = replay(lg, params)
        except IptmError:
            continue
        m, s = rep.measured.get("coolant_temp"), rep.simulated.get("coolant_temp")
        if m is not None and s is not None:
            for label, lo, hi in REGIMES:
                sel = np.isfinite(m) & np.isfinite(s) & (m >= lo) & (m < hi)
                err[label].append(s[sel] - m[sel])
        m, s = rep.measured.get("cabin_temp"), rep.simulated.get("cabin_temp")
        if m is not None and s is not None:
            sel = np.isfinite(m) & np.isfinite(s)
            err["cabin"].append(s[sel] - m[sel])
    out = {}
    for k, parts in err.items():
        e = np.concatenate(parts) if parts else np.zeros(0)
        out[k] = {"rmse": float(np.sqrt(np.mean(e * e))) if e.size >= 10 else math.nan, "n": int(e.size)}
    return out


def drive_vs_model(log, sim) -> dict:
    """How the foreign car drove a trace against what the plan's model predicted: coolant and cabin RMS
    difference and each one's maximum (degC)."""
    out = {}
    t = log.data.index.to_numpy(float)
    for ch, pred in (("coolant_temp_degC", sim.T_cl), ("cabin_temp_degC", sim.T_cab)):
        if ch not in log.data:
            continue
        m = log.data[ch].to_numpy(float)
        p = np.interp(t, sim.t, pred)
        ok = np.isfinite(m)
        out[ch] = {"rms_diff": float(np.sqrt(np.mean((m[ok] - p[ok]) ** 2))), "max_logged": float(np.max(m[ok])),
                   "max_model": float(np.max(pred))}
    return out


def standard_cut(name: str, seconds: int):
    """A standard cycle repeated back to back and cut to ``seconds`` (1 s steps)."""
    from calib import Cycle, load_cycle

    v = load_cycle(name).v
    reps = int(math.ceil((seconds + 1) / v.size))
    vv = np.concatenate([v] * reps)[: seconds + 1]
    return Cycle(f"{name} cut to {seconds} s", np.arange(seconds + 1, dtype=float), vv)


class FastsimCar:
    name = "FASTSim 3 Sonata (SYNTHETIC)"

    def __init__(self):
        from calib.ingest import to_drivelog
        from testcars.synth_fastsim import SONATA, synthesise_fastsim

        logs = [to_drivelog(*synthesise_fastsim(sc, seed=7 + i)[1:]) for i, sc in enumerate(SONATA)]
        self.cal, self.held = logs[:2], logs[2:]
        self.T_amb = SONATA[0].T_amb

    def drive(self, cycle, T_amb, T_cl0, seed, label):
        from calib.ingest import to_drivelog
        from testcars.synth_fastsim import FastsimScenario, synthesise_fastsim

        sc = FastsimScenario(f"plan_{label}", cycle, T_amb, T_cl0, T_amb, T_amb, f"{label} ({cycle.name})")
        return to_drivelog(*synthesise_fastsim(sc, seed=seed)[1:])

    def truth(self, name):
        return None  # FASTSim's thermal model has no parameter that is one of ours


def _highway_held_out():
    """A held-out drive of this benchmark that takes the coolant above the thermostat (the perturbed plant's
    own held-out warm restart stays below 80 degC)."""
    from testcars.synth_perturbed import Drive

    return Drive("perturbed_held_out_highway", "hwfet+us06", -5.0, 20.0, 5.0, 0.0, 0.58,
                 description="held out: restart at -5 degC (coolant 20 degC, cabin 5 degC), HWFET + US06 (23 min)")


class PerturbedCar:
    def __init__(self, seed: int):
        from testcars.synth_perturbed import CALIBRATION, HELD_OUT, comparable_truth, perturbed_logs

        self.seed = seed
        self.name = f"perturbed plant, seed {seed} (SYNTHETIC)"
        logs, self.plant = perturbed_logs(seed, CALIBRATION + HELD_OUT + [_highway_held_out()])
        self.cal, self.held = logs[:len(CALIBRATION)], logs[len(CALIBRATION):]
        self.T_amb = CALIBRATION[0].T_amb
        self.comp = comparable_truth(self.plant)

    def drive(self, cycle, T_amb, T_cl0, seed, label):
        from calib.ingest import to_drivelog
        from testcars.synth_perturbed import Drive, synthesise_perturbed

        d = Drive(f"perturbed_plan_{label}", cycle, T_amb, T_cl0, T_amb, T_amb, 0.58,
                  description=f"{label} ({cycle.name})")
        return to_drivelog(*synthesise_perturbed(d, self.plant, seed=seed)[1:])

    def truth(self, name):
        v = self.comp["values"].get(name)
        return float(v) if isinstance(v, (int, float)) else None


def closed_loop(car, minutes: float = 20.0, tmp=None, log=print) -> dict:
    """The closed loop on one car (module docstring); returns the figures."""
    from calib.design import make_plan
    from calib.design import Planner, log_inputs, simulate_cycle

    tmp = tmp or tempfile.mkdtemp(prefix="iptm-plan-")
    res0, w0 = _calibrate(car.cal)
    prior = _prior(res0, tmp)
    targets = prior.weakest()
    log(f"-- {car.name}: calibrated on {len(car.cal)} drives ({w0:.0f} s); targets: "
        + ", ".join(f"{t} (sd {100 * prior.ratio(t):.0f} % of prior)" for t in targets))
    t0 = time.perf_counter()
    plan = make_plan(prior, targets, minutes=minutes, ambient=car.T_amb, heater=False)
    log(f"   plan ({time.perf_counter() - t0:.0f} s): {plan.design.describe()}")
    planner = Planner(prior, targets)
    n = int(round(plan.sim.t[-1]))
    drives = {"plan": plan_cycle(plan), "UDDS": standard_cut("udds", n), "HWFET": standard_cut("hwfet", n)}
    out = {"car": car.name, "targets": targets, "design": plan.design.describe(), "arms": {}}
    from calib.design import subsystem_of

    subs = sorted({subsystem_of(t) for t in targets})

    def noise(res):
        return {s: res.fits[s].metrics.get("noise_sd_degC", math.nan) if s in res.fits else math.nan for s in subs}

    base_err = held_out_errors(res0.params, car.held)
    out["arms"]["calibration drives only"] = {"sd": {t: prior.sd[t] for t in targets},
                                              "value": {t: float(res0.params[t]) for t in targets},
                                              "held_out": base_err, "noise_degC": noise(res0)}
    for i, (label, cyc) in enumerate(drives.items()):
        sim = plan.sim if label == "plan" else simulate_cycle(prior.params, cyc, car.T_amb, plan.design.T_cl0)
        pred = planner.predict(sim)["sd"]
        lg = car.drive(cyc, car.T_amb, plan.design.T_cl0, 500 + i, label)
        on_log = planner.predict(inputs=log_inputs(lg, prior.params))["sd"]
        res, w = _calibrate(car.cal + [lg])
        out["arms"][f"+ {label}"] = {"predicted_sd": pred, "predicted_on_log_sd": on_log,
                                     "sd": {t: float(res.params.param(t).stderr) for t in targets},
                                     "value": {t: float(res.params[t]) for t in targets},
                                     "held_out": held_out_errors(res.params, car.held), "wall_s": w,
                                     "noise_degC": noise(res), "drive_vs_model": drive_vs_model(lg, sim)}
        log(f"   + {label}: re-calibrated ({w:.0f} s)")
    out["truth"] = {t: car.truth(t) for t in targets}
    return out


def plan_cycle(plan):
    """The plan's speed trace as a cycle (what the driver follows)."""
    from calib import Cycle

    return Cycle("drive plan", plan.sim.t.copy(), plan.sim.v.copy())


def table(fig: dict) -> str:
    """The closed-loop figures of one car as text tables."""
    arms = list(fig["arms"])
    lines = [f"{fig['car']}: plan = {fig['design']}"]
    for t in fig["targets"]:
        tv = fig["truth"].get(t)
        lines.append(f"  {t} (car's value: {'no counterpart' if tv is None else f'{tv:.4g}'})")
        lines.append(f"    {'logs':26s} {'sd predicted':>12s} {'on its log':>11s} {'sd achieved':>12s} {'estimate':>11s}")
        for a in arms:
            d = fig["arms"][a]
            p, q = d.get("predicted_sd", {}).get(t), d.get("predicted_on_log_sd", {}).get(t)
            lines.append(f"    {a:26s} {'' if p is None else f'{p:12.4g}':>12s} {'' if q is None else f'{q:11.4g}':>11s} "
                         f"{d['sd'][t]:12.4g} {d['value'][t]:11.5g}")
    subs = list(fig["arms"][arms[0]]["noise_degC"])
    lines.append("  fitted noise sd of the replay (degC): " + ", ".join(subs))
    for a in arms:
        lines.append(f"    {a:26s} " + " ".join(f"{fig['arms'][a]['noise_degC'][s]:8.3f}" for s in subs))
    lines.append("  the car on each added drive against the model's prediction (degC): coolant rms diff, max "
                 "logged / model; cabin rms diff, max logged / model")
    for a in arms[1:]:
        dv = fig["arms"][a]["drive_vs_model"]
        parts = [f"{dv[c]['rms_diff']:6.1f} {dv[c]['max_logged']:6.1f} / {dv[c]['max_model']:5.1f}"
                 for c in ("coolant_temp_degC", "cabin_temp_degC") if c in dv]
        lines.append(f"    {a:26s} " + " | ".join(parts))
    keys = [label for label, _, _ in REGIMES] + ["cabin"]
    lines.append("  held-out RMSE (degC): " + " | ".join(f"coolant {k}" if k != "cabin" else "cabin" for k in keys))
    for a in arms:
        h = fig["arms"][a]["held_out"]
        lines.append(f"    {a:26s} " + " ".join(f"{h[k]['rmse']:8.2f}" for k in keys))
    return "\n".join(lines)


def run(quick: bool = False, seeds=(1, 2, 3), minutes: float = 20.0, cars=None) -> dict:
    """The closed loop on each car (the perturbed plant once per seed; ``quick``: the perturbed plant, first
    seed, only), tables printed; a car whose loop raises is reported in ``failures`` and the others still
    run."""
    from testcars.synth_fastsim import fastsim_available

    cars = list(cars or (["perturbed"] if quick else ["perturbed", "fastsim"]))
    seeds = list(seeds)[:1] if quick else list(seeds)
    todo = [(c, s) for c in cars for s in (seeds if c == "perturbed" else [None])]
    out = {"cars": [], "failures": []}
    with tempfile.TemporaryDirectory(prefix="iptm-plan-") as tmp:
        for c, seed in todo:
            if c == "fastsim" and not fastsim_available():
                print("-- FASTSim: skipped, the optional package fastsim is not installed (pip install 'iptm[fastsim]')")
                out["skipped"] = "fastsim not installed"
                continue
            try:
                car = PerturbedCar(seed) if c == "perturbed" else FastsimCar()
                fig = closed_loop(car, minutes, tmp)
            except Exception as exc:  # noqa: BLE001 - a failed car is a failed case; the others still run
                msg = f"{c}{'' if seed is None else f' seed {seed}'}: {type(exc).__name__}: " \
                      f"{(str(exc).strip().splitlines() or [''])[0]}"
                print(f"FAILED: {msg}", flush=True)
                out["failures"].append(msg)
                continue
            print(table(fig), flush=True)
            out["cars"].append(fig)
    return out


BLOCK = "plan-bench"


def render_doc(doc_path, text: str) -> None:
    """Rewrite the ``<!-- figures:plan-bench -->`` block of ``doc_path`` with ``text`` (a code block)."""
    import re

    from calib import IptmError
    from calib import write_text

    p = Path(doc_path)
    old = p.read_text(encoding="utf-8")
    pat = re.compile(rf"(<!-- figures:{BLOCK} -->)(.*?)(<!-- /figures:{BLOCK} -->)", re.S)
    if not pat.search(old):
        raise IptmError(f"{doc_path}: no <!-- figures:{BLOCK} --> ... <!-- /figures:{BLOCK} --> block to rewrite; "
                        "add one where the table belongs")
    write_text(p, pat.sub(lambda m: m.group(1) + "\n```text\n" + text + "\n```\n" + m.group(3), old))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m iptm.benchmarks.plan", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cars", nargs="+", default=["perturbed", "fastsim"], choices=("perturbed", "fastsim"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="perturbed plant seeds (default 1 2 3)")
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    ap.add_argument("--doc", metavar="MD", help="rewrite the figures block of this page (docs/drive_plans.md)")
    args = ap.parse_args(argv)
    res = run(seeds=args.seeds, minutes=args.minutes, cars=args.cars)
    figs = res["cars"]
    if args.json:
        from calib import write_json

        write_json(args.json, figs)
    if args.doc and not res["failures"]:
        cmd = "python -m iptm.benchmarks.plan " + " ".join(argv if argv is not None else sys.argv[1:])
        render_doc(args.doc, f"$ {cmd}\n" + "\n\n".join(table(f) for f in figs))
    return 1 if res["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
