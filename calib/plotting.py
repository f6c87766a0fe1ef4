"""The figures of the physics layer, one function per figure (matplotlib; the Agg backend is selected when
a figure is written to a file, so nothing here needs a display). The result types delegate here:
:meth:`calib.model.simulate.SimResult.plot`, :meth:`calib.fit.validate.Replay.plot` and
:meth:`calib.fit.driver.CalibrationResult.plot`."""
from __future__ import annotations

import numpy as np

from calib.fit.replay import CHANNEL_METRICS

__all__ = ["plot_simulation", "plot_validation", "plot_residuals", "plot_residual_comparison", "plot_calibration",
           "finish_figure"]


def finish_figure(fig, path=None, suptitle=None, fontsize=9, rect=None):
    """Every figure of the project ends here: an optional suptitle, a tight layout (``rect`` leaves room for
    a footnote) and, when ``path`` is given, an atomic save that also closes the figure. Returns ``fig``."""
    if suptitle is not None:
        fig.suptitle(suptitle, fontsize=fontsize)
    if rect is None:
        fig.tight_layout()
    else:
        fig.tight_layout(rect=rect)
    if path is not None:
        from calib.fileio import save_figure

        save_figure(fig, path)
    return fig


def plot_simulation(sim, path=None, title=None):
    """States, powers and fuel over time; saves to ``path`` when given. Returns the Figure."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    f = sim.flows
    tt = sim.t[:-1]
    fig, ax = plt.subplots(6, 1, figsize=(9, 12), sharex=True)
    ax[0].plot(sim.t, sim.v * 3.6, "k", lw=0.8)
    ax[0].set_ylabel("speed [km/h]")
    ax[1].plot(sim.t, sim.soc, "C0")
    ax[1].set_ylabel("SOC [-]")
    ax[2].plot(sim.t, sim.T_cl, "C3", label="coolant")
    ax[2].plot(sim.t, sim.T_cab, "C2", label="cabin")
    ax[2].set_ylabel("temperature [degC]")
    ax[2].legend(loc="best", fontsize=8)
    ax[3].plot(tt, f["P_e"] / 1e3, "C1", lw=0.8, label="engine")
    ax[3].plot(tt, f["P_bat"] / 1e3, "C0", lw=0.8, label="battery")
    ax[3].set_ylabel("power [kW]")
    ax[3].legend(loc="best", fontsize=8)
    ax[4].step(tt, sim.e_mode, "C4", where="post")
    ax[4].set_yticks([1, 2, 3, 4], ["off", "idle", "on", "catalyst"])
    ax[4].set_ylabel("engine mode")
    ax[5].plot(sim.t, np.concatenate([[0], np.cumsum(f["W_f"]) * sim.Ts]), "C5")
    ax[5].set_ylabel("cumulative fuel [g]")
    ax[5].set_xlabel("time [s]")
    import textwrap

    text = title or (f"{sim.info.get('cycle', '')} at {sim.info.get('T_amb_degC', '')} degC\n"
                     f"{sim.info.get('controller', '')}")
    text = "\n".join(textwrap.fill(line, 110) for line in str(text).splitlines())
    return finish_figure(fig, path, text)


def plot_residuals(rep, path=None, title=None):
    """Per simulated channel: measured vs simulated, residual over time, residual autocorrelation.
    Written atomically when ``path`` is given. Returns the Figure."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    keys = [k for k in CHANNEL_METRICS if k in rep.measured and k in rep.simulated]
    fig, ax = plt.subplots(max(len(keys), 1), 3, figsize=(12, 2.6 * max(len(keys), 1)), squeeze=False)
    t = rep.t / 60.0
    for i, k in enumerate(keys):
        m, s = rep.measured[k], rep.simulated[k]
        ok = np.isfinite(m) & np.isfinite(s)
        unit = CHANNEL_METRICS[k][1]
        a = ax[i, 0]
        a.plot(m[ok], s[ok], ".", ms=1.5, alpha=0.5)
        lo, hi = float(np.nanmin(m[ok])), float(np.nanmax(m[ok]))
        a.plot([lo, hi], [lo, hi], "k-", lw=0.8)
        a.set_xlabel(f"measured {k} [{unit}]")
        a.set_ylabel("simulated")
        a = ax[i, 1]
        a.plot(t[ok], (s - m)[ok], "-", lw=0.6)
        a.axhline(0, color="k", lw=0.6)
        a.set_ylabel(f"residual [{unit}]")
        a.set_xlabel("time [min]")
        a = ax[i, 2]
        r = (s - m)[ok]
        r = r - r.mean()
        nl = min(300, max(r.size // 3, 2))
        den = float(r @ r) or 1.0
        acf = [1.0] + [float(r[j:] @ r[:-j] / den) for j in range(1, nl)]
        a.plot(np.arange(nl), acf, "-")
        a.axhline(0, color="k", lw=0.6)
        a.set_xlabel("lag [samples]")
        a.set_ylabel("residual ACF")
    if rep.refused:
        fig.text(0.01, 0.005, "not checked: " + "; ".join(f"{k} ({v})" for k, v in rep.refused.items())[:220],
                 fontsize=7)
    return finish_figure(fig, path, title or f"Residual diagnostics: {rep.name}", rect=(0, 0.03, 1, 1))


def plot_validation(rep, path=None, title=None):
    """Measured vs simulated (paper Fig. 3 style): SOC, coolant, cabin, fuel rate and cumulative fuel.

    Written atomically when ``path`` is given (Agg backend). Returns the Figure.
    """
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    t = rep.t / 60.0
    fig, ax = plt.subplots(5, 1, figsize=(8, 11), sharex=True)
    panels = [("soc", "SOC [-]"), ("coolant_temp", "coolant temp. [degC]"), ("cabin_temp", "cabin temp. [degC]"),
              ("fuel_rate", "fuel rate [g/s]")]
    for a, (k, lab) in zip(ax, panels):
        if k in rep.measured:
            a.plot(t, rep.measured[k], "k-", lw=0.8, label="measured")
        if k in rep.simulated:
            a.plot(t, rep.simulated[k], "r--", lw=1.0, label="simulated")
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
    ax[0].legend(loc="best", fontsize=8)
    cum = rep.cumulative_fuel() if hasattr(rep, "cumulative_fuel") else None
    if cum is not None:  # both over the same seconds: a second neither knows adds to neither
        ax[4].plot(t, cum[0], "k-", lw=0.8, label="measured")
        ax[4].plot(t, cum[1], "r--", lw=1.0, label="simulated")
    for a, (k, _lab) in zip(ax, panels + [("fuel_rate", "")]):
        if k in rep.refused:
            a.text(0.5, 0.5, f"not simulated: {rep.refused[k]}"[:110], transform=a.transAxes, ha="center",
                   fontsize=7, color="r")
    ax[4].set_ylabel("cumulative fuel [g]")
    ax[4].set_xlabel("time [min]")
    ax[4].grid(alpha=0.3)
    m = rep.metrics()
    sub = ", ".join(f"{k} RMSE {v['rmse']:.3g}" for k, v in m.items() if "rmse" in v)
    return finish_figure(fig, path, (title or f"Validation: {rep.name}") + "\n" + sub)


def plot_residual_comparison(reps, path=None, title=None):
    """Residuals (simulated - measured) of SOC, coolant, cabin temperature and fuel rate, one line per log.

    ``reps`` is a list of ``(label, Replay)``; fitted and held-out logs side by side show whether the fit
    only follows the logs it was fitted on. Written atomically when ``path`` is given. Returns the Figure.
    """
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = [("soc", "SOC [-]"), ("coolant_temp", "coolant [degC]"), ("cabin_temp", "cabin [degC]"),
              ("fuel_rate", "fuel rate [g/s]")]
    fig, ax = plt.subplots(len(panels), 1, figsize=(8, 8.5), sharex=True)
    for i, (label, rep) in enumerate(reps):
        for a, (k, _) in zip(ax, panels):
            m, s = rep.measured.get(k), rep.simulated.get(k)
            if m is None or s is None:
                continue
            a.plot(rep.t / 60.0, s - m, lw=0.7, color=f"C{i}", label=label)
    for a, (_, lab) in zip(ax, panels):
        a.axhline(0.0, color="k", lw=0.6)
        a.set_ylabel("residual " + lab, fontsize=8)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 1.45), ncol=2, frameon=False)
    ax[-1].set_xlabel("time [min]")
    return finish_figure(fig, path, title or "residuals: simulated - measured")


def plot_calibration(res, path=None, title=None):
    """One bar per fitted parameter (a table: the mean over its entries): the fraction of the prior
    uncertainty the data removed, ``1 - posterior sd / prior sd``, coloured by status (estimated, weak).
    Parameters held at their prior or fixed are listed in the title, not drawn. Returns the Figure."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    rows, skipped = [], []
    for sub, fit in res.fits.items():
        for name, e in fit.estimates.items():
            inf = e.informed
            if e.status not in ("estimated", "weak") or inf is None:
                skipped.append(name)
                continue
            val = float(np.mean(inf)) if isinstance(inf, (list, tuple, np.ndarray)) else float(inf)
            rows.append((f"{name} ({sub})" + (" [weak]" if e.status == "weak" else ""), val, e.status))
    fig, ax = plt.subplots(figsize=(8, 0.32 * max(len(rows), 1) + 1.6))
    colours = {"estimated": "C0", "weak": "C1"}
    y = np.arange(len(rows))[::-1]
    ax.barh(y, [r[1] for r in rows], color=[colours[r[2]] for r in rows])
    ax.set_yticks(y, [r[0] for r in rows], fontsize=8)
    ax.set_xlim(0.0, 1.0)
    ax.set_xlabel("informed by the data: 1 - posterior sd / prior sd")
    from matplotlib.patches import Patch

    ax.legend(handles=[Patch(color=c, label=st) for st, c in colours.items()], fontsize=8, loc="lower right")
    ax.grid(axis="x", alpha=0.3)
    text = title or "calibration: what the logs determined"
    if skipped:
        text += "\nat the prior or fixed: " + ", ".join(skipped)
    ax.set_title(text, fontsize=9)
    return finish_figure(fig, path)
