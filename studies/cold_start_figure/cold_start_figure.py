"""The default car's cold start on the cold FTP's bag 1 (20 degF, heater and defroster on), as the sources
describe it (docs/cold_start.md): engine speed and mode, coolant and cabin, SOC, heater.

    python studies/cold_start_figure/cold_start_figure.py [OUT.png]     # default reports/figures/cold_start_bag1.png
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "reports" / "figures" / "cold_start_bag1.png"


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calib.model import CAT, IDLE, ON, RuleParams, default_parameters, ftp
    from calib import RPM

    out = Path((argv or sys.argv[1:] or [str(OUT)])[0])
    r = ftp.run_ftp(default_parameters(), ftp.COLD_FTP)
    run, n = r.runs[0], ftp.BAG1_S
    t, f, rp = run.t[:n], run.flows, RuleParams()
    fig, ax = plt.subplots(4, 1, figsize=(10, 11), sharex=True)
    a = ax[0]
    standstill = run.v[:n] < 0.1
    on = run.e_mode[:n] == ON
    shades = [(run.e_mode[:n] == CAT, "tab:red", "catalyst heating (plant, whatever the controller asks)"),
              (run.e_mode[:n] == IDLE, "tab:orange", "idle, held on by the thermal rules"),
              (on & standstill, "tab:purple", "on, charging at a standstill"),
              (on & ~standstill, "tab:green", "on, driving")]
    for m, c, lab in shades:
        a.fill_between(t, 0, 4000, where=m, color=c, alpha=0.18, step="post", lw=0, label=lab)
    a.step(t, f["omega_e"][:n] / RPM, where="post", color="k", lw=1.0, label="engine speed (left axis)")
    a.set_ylabel("engine speed (rpm)")
    a.set_ylim(0, 4000)
    b = a.twinx()
    b.plot(t, run.v[:n] * 3.6, color="tab:blue", lw=1.2, label="vehicle speed (right axis)")
    b.set_ylabel("vehicle speed (km/h)", color="tab:blue")
    b.tick_params(axis="y", colors="tab:blue")
    b.set_ylim(0, 100)
    h1, l1 = a.get_legend_handles_labels()
    h2, l2 = b.get_legend_handles_labels()
    a.legend(h1 + h2, l1 + l2, loc="lower center", bbox_to_anchor=(0.5, 1.0), fontsize=8, ncol=3, frameon=False)
    fig.suptitle(f"Cold FTP bag 1 ({ftp.COLD_FTP.T_soak_degC:g} degC soak, heater and defroster on): "
                 f"default car, rule-based controller")
    a = ax[1]
    a.plot(t, run.T_cl[:n], color="tab:red", label="coolant")
    a.plot(t, run.T_cab[:n], color="tab:purple", label="cabin")
    for y, lab in ((rp.T_idle_degC, "engine may stop (no heat requested)"),
                   (rp.T_heat_on_degC, "engine may stop (heat requested)"), (rp.T_warm_degC, "warm-up charge ends"),
                   (ftp.T_SET_DEGC, "cabin set point")):
        a.axhline(y, color="grey", ls=":", lw=0.8)
        a.text(t[-1], y, lab, ha="right", va="bottom", fontsize=7, color="grey")
    a.set_ylabel("temperature (degC)")
    a.legend(loc="upper left", fontsize=8)
    a = ax[2]
    a.plot(t, run.soc[:n], color="tab:green")
    a.axhline(rp.soc_target, color="grey", ls=":", lw=0.8)
    a.axhline(rp.soc_warmup, color="grey", ls="--", lw=0.8)
    a.text(t[-1], rp.soc_warmup, "warm-up SOC target (coolant below 70 degC)", ha="right", va="bottom", fontsize=7,
           color="grey")
    a.text(t[-1], rp.soc_target, "SOC target when warm", ha="right", va="bottom", fontsize=7, color="grey")
    a.set_ylabel("SOC")
    a = ax[3]
    a.step(t, f["W_f"][:n], where="post", color="k", lw=0.8, label="fuel rate (left axis)")
    a.set_ylabel("fuel rate (g/s)")
    b = a.twinx()
    b.plot(t, f["Q_heat"][:n] / 1e3, color="tab:orange", lw=1.5, label="heater delivered (right axis)")
    b.set_ylabel("heater delivered (kW)", color="tab:orange")
    b.tick_params(axis="y", colors="tab:orange")
    b.set_ylim(bottom=0)
    h1, l1 = a.get_legend_handles_labels()
    h2, l2 = b.get_legend_handles_labels()
    a.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    a.set_xlabel("time (s)")
    a.set_xlim(0, t[-1])
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
