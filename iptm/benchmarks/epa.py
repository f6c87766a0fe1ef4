"""Benchmark: the default car against EPA's laboratory results (warm cycles, warm and cold FTP).

Prints the warm UDDS/HWFET/US06 table (:func:`calib.model.epa.epa_comparison`) and the FTP composite
at 75 degF and at 20 degF (:func:`calib.model.ftp.ftp_comparison`) against the 2022 Prius of the EPA
Test Car List. ``--params FILE`` is not taken: this checks the default parameter set.
"""
from __future__ import annotations


def run(quick: bool = False) -> dict:
    import pandas as pd

    from calib.model.epa import epa_comparison
    from calib.model.ftp import COLD_FTP, WARM_FTP, run_ftp
    from calib.model.params import default_parameters

    ps = default_parameters()
    warm = epa_comparison(ps)
    print("EPA warm cycles (rule-based, 24 degC, coolant 90 degC, SOC-corrected):")
    print(warm.to_string(index=False))
    rows = []
    for c in (WARM_FTP, COLD_FTP):
        r = run_ftp(ps, c)
        row = r.row()
        cold = r.runs[0].summary()
        row.update(idle_s_bags_1_2=cold["idle_s"], heater_MJ=round(cold["heater_delivered_J"] / 1e6, 2))
        rows.append(row)
    ftp = pd.DataFrame(rows)
    print("\nFTP composite (rule-based, everything soaked at the test temperature, bags SOC-corrected; "
          "EPA Test Car List 2022 Prius):")
    with pd.option_context("display.width", 200):
        print(ftp.to_string(index=False))
    print("EPA bags of the 75 degF FTP: 50.71 / 126.29 / 62.72 / 114.35 mpg (bag 1 / bag 3 = 0.81; "
          f"model {ftp['bag1_mpg'].iloc[0] / ftp['bag3_mpg'].iloc[0]:.2f})")
    ratio = ftp["model_mpg"].iloc[0] / ftp["model_mpg"].iloc[1]
    print(f"\ncold/warm fuel per mile: model {ratio:.3f}, EPA {WARM_FTP.epa_mpg / COLD_FTP.epa_mpg:.3f}")
    return {"epa_warm_cycles": warm.to_dict(orient="records"), "ftp": ftp.to_dict(orient="records"),
            "cold_warm_ratio": ratio}
