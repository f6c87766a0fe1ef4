"""Held-out cumulative fuel and SOC of the FASTSim Sonata calibration over several sensor-noise seeds.

The scenarios of ``iptm bench calib`` (calibrate on the two cold drives, validate on the warm restart and
the 22 degC drive) with the logs' noise, phase and dropout seeds ``S, S+1, S+2, S+3`` for every ``S`` given
(the bench uses 7). Prints the two held-out fuel errors and SOC RMSEs, the fitted ``f_cl`` above 80 degC and
the battery hysteresis. Needs the
``fastsim`` extra. Every log is SYNTHETIC. ``.venv/bin/python scripts/fastsim_fuel_seeds.py 7 17 27 37``
"""
from __future__ import annotations

import sys


def main(seeds) -> None:
    from calib.fit.driver import calibrate
    from calib.fit.validate import replay
    from calib.ingest import to_drivelog
    from calib.synth_fastsim import SONATA, synthesise_fastsim

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


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [7])
