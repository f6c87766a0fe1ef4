"""Check the default parameter set against EPA's warm laboratory fuel economy (data/prius_facts.md).

The rule-based controller drives the model over UDDS, HWFET and US06 warm (24 degC ambient, coolant at
90 degC, heater off, start SOC 0.6). Economy is corrected for the SOC difference (the electric-energy
conversion of :meth:`calib.model.simulate.SimResult.fuel_equivalents`) and compared with:

- UDDS: FTP bags 3-4 (hot start; bag 3 3.59 mi at 62.72 mpg, bag 4 3.91 mi at 114.35 mpg -> 82.0 mpg);
- HWFET: 71.2 mpg (HWFE); US06: 48.6 mpg.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

#: EPA unadjusted laboratory results, 2017-2022 Prius FWD (mpg). UDDS = hot FTP bags 3-4.
EPA_MPG = {"udds": (3.59 + 3.91) / (3.59 / 62.72 + 3.91 / 114.35), "hwfet": 71.2, "us06": 48.6}
WARM = dict(T_amb=24.0, soc0=0.6, T_cl0=90.0, T_cab0=22.0, Q_heat=0.0)


def epa_comparison(params) -> pd.DataFrame:
    """Model (rule-based, warm, SOC-corrected) vs EPA mpg per cycle, with the relative error."""
    from calib.model.rulebased import RuleParams
    from calib.model.simulate import simulate

    rows = []
    for cyc, target in EPA_MPG.items():
        s = simulate(params, cyc, rule_params=RuleParams(Q_heat_W=0.0), **WARM).summary()
        rows.append({"cycle": cyc.upper(), "epa_mpg": round(target, 1), "model_mpg": round(s["mpg"], 1),
                     "model_mpg_soc_corrected": round(s["mpg_soc_corrected"], 1),
                     "soc_final": round(s["soc_final"], 3),
                     "error_pct": round(100 * (s["mpg_soc_corrected"] / target - 1), 1)})
    return pd.DataFrame(rows)


def tune_fuel_scale(params) -> float:
    """The fuel-map scale that makes the mean log error over the three cycles zero (fuel ~ scale)."""
    base = params.with_values(fuel_scale=1.0)
    df = epa_comparison(base)
    return float(np.exp(np.mean(np.log(df["model_mpg_soc_corrected"] / df["epa_mpg"]))))
