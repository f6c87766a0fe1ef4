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
    out = {"epa_warm_cycles": warm.to_dict(orient="records"), "ftp": ftp.to_dict(orient="records"),
           "cold_warm_ratio": ratio}
    if not quick:
        out["causes"] = _causes(ps).to_dict(orient="records")
    return out


def _causes(ps):
    """The cold FTP with one cause at a time switched back or varied (docs/cold_start.md)."""
    import pandas as pd

    from calib.model import ftp
    from calib.model.rulebased import RuleParams

    no_rule = RuleParams(T_heat_on_degC=-273.0)
    f_steep = ps.copy()
    fp = f_steep.param("f_cl")
    fp.x, fp.value, fp.prior_sd = [-10.0, 20.0, 50.0, 70.0], [2.0, 1.6, 1.2, 1.0], None
    f_steep.validate()
    cases = [
        ("previous default: gamma_exh 0.5, Q_rad_max 30 kW, engine may stop at 40 degC with heat on",
         ps.with_values(gamma_exh=0.5, Q_rad_max_W=30e3), no_rule, None),
        ("gamma_exh 0.5 with the engine-on rule", ps.with_values(gamma_exh=0.5), None, None),
        ("gamma_exh 0.35 with the engine-on rule", ps.with_values(gamma_exh=0.35), None, None),
        ("default without the engine-on rule", ps, no_rule, None),
        ("default", ps, None, None),
        ("default, blower at full flow from the start (no warm-up control)", ps, None, (-274.0, -273.0)),
        ("default with a steeper f_cl (2.0/1.6/1.2/1.0 at -10/20/50/70 degC)", f_steep, None, None),
        ("default with the engine-on rule at 45 degC", ps, RuleParams(T_heat_on_degC=45.0), None),
        ("default with the engine-on rule at 65 degC", ps, RuleParams(T_heat_on_degC=65.0), None),
    ]
    rows = []
    ramp = ftp.BLOWER_RAMP_DEGC
    try:
        for name, p, rp, r in cases:
            ftp.BLOWER_RAMP_DEGC = r or ramp
            w, c = (ftp.run_ftp(p, cond, rule_params=rp) for cond in (ftp.WARM_FTP, ftp.COLD_FTP))
            rows.append({"case": name, "warm_mpg": round(w.composite_mpg, 1), "warm_err_pct": round(w.error_pct, 1),
                         "warm_bag1/bag3": round(w.bag_mpg[0] / w.bag_mpg[2], 2),
                         "cold_mpg": round(c.composite_mpg, 1), "cold_err_pct": round(c.error_pct, 1),
                         "cold_idle_s": c.runs[0].summary()["idle_s"] + c.runs[1].summary()["idle_s"],
                         "T_cl_end_bag1": round(c.T_cl_bounds[1], 1)})
    finally:
        ftp.BLOWER_RAMP_DEGC = ramp
    df = pd.DataFrame(rows)
    print("\nCauses (one change at a time; EPA: warm 78.0, cold 56.3 mpg, warm bag1/bag3 0.81):")
    with pd.option_context("display.width", 250, "display.max_colwidth", 80):
        print(df.to_string(index=False))
    return df
