"""Held-out cumulative fuel and SOC of the FASTSim Sonata calibration over several sensor-noise seeds, and
over the drive selections of docs/calibration_robustness.md with the fuel model's own share of the error.

``fastsim_fuel_seeds.py S...``: the scenarios of ``iptm bench calib`` (calibrate on the two cold drives,
validate on the warm restart and the 22 degC drive) with the logs' noise, phase and dropout seeds
``S, S+1, S+2, S+3`` for every ``S`` given (the bench uses 7). Prints the two held-out fuel errors and SOC
RMSEs, the fitted ``f_cl`` above 80 degC and the battery hysteresis.

``fastsim_fuel_seeds.py --selections``: every 2-of-6 selection of the drive-selection study (same drives and
seeds); for each held-out drive the cumulative fuel error of the validation replay (the coolant simulated by
the calibrated engine-thermal model) and of the fuel model replayed on the logged coolant (the fuel fit's
share), with the calibrated radiator gain.

Needs the ``fastsim`` extra. Every log is SYNTHETIC. ``.venv/bin/python studies/fastsim_fuel_seeds/fastsim_fuel_seeds.py 7 17 27 37``
"""
from __future__ import annotations

import sys


def main(seeds) -> None:
    from calib.fit import calibrate, replay
    from calib.ingest import to_drivelog
    from testcars.synth_fastsim import SONATA, synthesise_fastsim

    for s0 in seeds:
        logs = []
        for i, sc in enumerate(SONATA):
            _, streams, meta = synthesise_fastsim(sc, seed=s0 + i)
            logs.append(to_drivelog(streams, meta))
        res = calibrate(logs[:2], progress=False, diagnose=False)
        f = res.params.param("f_cl")
        ms = [replay(lg, res.params).metrics() for lg in logs[2:]]
        errs = [m["cumulative_fuel"]["error_pct"] for m in ms]
        soc = [m["soc"]["rmse"] for m in ms]
        h = res.params.param("U_hyst_V")
        hot = ", ".join(f"{x:g} degC {v:.3f}" for x, v in zip(f.x, f.value) if x > 80)
        print(f"seeds {s0}-{s0 + 3}: held-out cumulative fuel {errs[0]:+.2f} % (warm restart), {errs[1]:+.2f} % "
              f"(22 degC drive); SOC RMSE {soc[0]:.4f} and {soc[1]:.4f}; U_hyst {h.value:.2f} +- {h.stderr:.2f} V; "
              f"f_cl {hot}", flush=True)


def _fill(a, default):
    """Linear interpolation over NaN (held flat at the ends); ``default`` when all NaN (as the replay fills
    a logged channel)."""
    import numpy as np

    a = np.asarray(a, dtype=float)
    ok = np.isfinite(a)
    if not ok.any():
        return np.full(a.shape, default)
    idx = np.arange(a.size)
    return np.interp(idx, idx[ok], a[ok])


def fuel_on_logged_coolant(log, params) -> float:
    """Cumulative fuel error (%) of the fuel model alone: engine on/off, power and coolant as logged."""
    import numpy as np

    from calib.fit import fuel_replay, log_arrays, replay
    from calib.model import IDLE, ON

    mp = params.model_params()
    la = log_arrays(log, mp)
    Wm = replay(log, params).measured["fuel_rate"]
    T = _fill(la.ch["coolant_temp_degC"], 20.0)
    n = la.t.size
    Wt = (la.f_on * fuel_replay(mp, np.full(n, ON, np.int64), la.P_on, T)
          + la.f_idle * fuel_replay(mp, np.full(n, IDLE, np.int64), np.zeros(n), T))
    ok = np.isfinite(Wm) & np.isfinite(Wt)
    return float(100.0 * (Wt[ok].sum() / Wm[ok].sum() - 1.0))


def selections() -> None:
    from itertools import combinations

    from calib.fit import calibrate, replay
    from calib.ingest import to_drivelog
    from testcars.synth_fastsim import synthesise_fastsim
    from iptm.benchmarks.calib import SELECTION_SEED, selection_pool

    pool = selection_pool()
    logs = {i: to_drivelog(*synthesise_fastsim(sc, seed=SELECTION_SEED + i)[1:]) for i, (_, sc) in enumerate(pool, 1)}
    print("selection: held-out drive fuel error, validation replay (simulated coolant) / fuel model on the logged "
          "coolant; calibrated k_rad")
    for pair in combinations(logs, 2):
        res = calibrate([logs[i] for i in pair], progress=False, diagnose=False)
        cells = []
        for i in logs:
            if i in pair:
                continue
            e = replay(logs[i], res.params).metrics()["cumulative_fuel"]["error_pct"]
            cells.append(f"{i}: {e:+.1f} / {fuel_on_logged_coolant(logs[i], res.params):+.1f} %")
        k = res.params.param("k_rad_W_per_K")
        print(f"  {pair[0]}+{pair[1]}: " + "; ".join(cells) + f"; k_rad {k.value:.0f} W/K ({k.status})", flush=True)


if __name__ == "__main__":
    if sys.argv[1:] == ["--selections"]:
        selections()
    else:
        main([int(a) for a in sys.argv[1:]] or [7])
