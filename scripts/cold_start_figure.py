"""The default car's cold start on the cold FTP's bag 1 (20 degF, heater and defroster on), as the sources
describe it (docs/cold_start.md): engine speed and mode, coolant and cabin, SOC, heater.

    python scripts/cold_start_figure.py [OUT.png]     # default reports/figures/cold_start_bag1.png
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "reports" / "figures" / "cold_start_bag1.png"


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calib.model import ftp
    from calib.model.equations import CAT, IDLE, ON
    from calib.model.params import default_parameters
    from calib.model.rulebased import RuleParams
    from calib.units import RPM

    out = Path((argv or sys.argv[1:] or [str(OUT)])[0])
    r = ftp.run_ftp(default_parameters(), ftp.COLD_FTP)
    run, n = r.runs[0], ftp.BAG1_S
    t, f, rp = run.t[:n], run.flows, RuleParams()
    fig, ax = plt.subplots(4, 1, figsize=(10, 10), sharex=True)
    a = ax[0]
    a.plot(t, f["omega_e"][:n] / RPM, color="k", lw=1.0, label="engine speed")
    colours = {CAT: ("tab:red", "catalyst heating"), IDLE: ("tab:orange", "idle (held on)"),
               ON: ("tab:green", "on")}
    for mode, (c, lab) in colours.items():
        m = run.e_mode[:n] == mode
        a.fill_between(t, 0, 4000, where=m, color=c, alpha=0.15, step="post", label=lab)
    a.set_ylabel("engine speed (rpm)")
    a.set_ylim(0, 4000)
    b = a.twinx()
    b.plot(t, run.v[:n] * 3.6, color="tab:blue", lw=0.8, alpha=0.7)
    b.set_ylabel("vehicle speed (km/h)", color="tab:blue")
    a.legend(loc="upper left", fontsize=8, ncol=4)
    a.set_title(f"Cold FTP bag 1 ({ftp.COLD_FTP.T_soak_degC:g} degC soak, heater and defroster on): "
                f"default car, rule-based controller")
    a = ax[1]
    a.plot(t, run.T_cl[:n], color="tab:red", label="coolant")
    a.plot(t, run.T_cab[:n], color="tab:purple", label="cabin")
    for y, lab in ((rp.T_idle_degC, "engine may stop (no heat)"), (rp.T_heat_on_degC, "engine may stop (heat on)"),
                   (rp.T_warm_degC, "warm-up charge ends")):
        a.axhline(y, color="grey", ls=":", lw=0.8)
        a.text(t[-1], y, lab, ha="right", va="bottom", fontsize=7, color="grey")
    a.set_ylabel("temperature (degC)")
    a.legend(loc="upper left", fontsize=8)
    a = ax[2]
    a.plot(t, run.soc[:n], color="tab:green")
    a.axhline(rp.soc_target, color="grey", ls=":", lw=0.8)
    a.axhline(rp.soc_warmup, color="grey", ls="--", lw=0.8)
    a.text(t[-1], rp.soc_warmup, "warm-up SOC target", ha="right", va="bottom", fontsize=7, color="grey")
    a.text(t[-1], rp.soc_target, "SOC target", ha="right", va="bottom", fontsize=7, color="grey")
    a.set_ylabel("SOC")
    a = ax[3]
    a.plot(t, f["Q_heat"][:n] / 1e3, color="tab:orange", label="heater delivered")
    a.plot(t, f["W_f"][:n], color="k", lw=0.8, label="fuel rate (g/s)")
    a.set_ylabel("heater (kW), fuel (g/s)")
    a.set_xlabel("time (s)")
    a.legend(loc="upper left", fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
