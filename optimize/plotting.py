"""The figures of the optimisation layer, one function per figure (matplotlib; the Agg backend is selected
when a figure is written to a file). The result types delegate here: :meth:`optimize.casestudy.CaseStudy.plot`,
:meth:`optimize.causal.sdp.SDPPolicy.plot`; :func:`plot_study` draws a sweep's results table."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from calib.plotting import finish_figure
from optimize.labels import LABELS, NAMES, PAPER_CONDITION, PAPER_SAVINGS

__all__ = ["plot_case_study", "plot_study", "plot_policy", "plot_dp_result"]


def plot_case_study(cs, outdir) -> list:
    """The paper's figures as PNGs in ``outdir``; returns their paths. The cabin and heater figures are
    drawn only when Thermal-DP or Thermal-Cabin-DP was solved (the other strategies do not decide the heat)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    outdir = Path(outdir)
    keys = [k for k in ("rule", "baseline", "thermal", "thermal_cabin") if k in cs.sims]
    colors = {"rule": "k", "baseline": "C0", "thermal": "C3", "thermal_cabin": "C2"}
    paths = []

    def save(fig, name):
        p = outdir / f"{name}.png"
        finish_figure(fig, p)
        paths.append(str(p))

    series = [
        ("soc", "SOC [-]", lambda s: (s.t, s.soc), "plot"),
        ("coolant", "coolant temperature [degC]", lambda s: (s.t, s.T_cl), "plot"),
        ("engine_power", "engine power [kW]", lambda s: (s.t[:-1], s.flows["P_e"] / 1e3), "plot"),
        ("battery_power", "battery power [kW]", lambda s: (s.t[:-1], s.flows["P_bat"] / 1e3), "plot"),
        ("engine_mode", "engine mode (1 off, 2 idle, 3 on, 4 catalyst heating)", lambda s: (s.t[:-1], s.e_mode), "step"),
        ("cumulative_fuel", "cumulative fuel [g]",
         lambda s: (s.t, np.concatenate([[0], np.cumsum(s.flows["W_f"]) * s.Ts])), "plot"),
        ("cabin", "cabin temperature [degC]", lambda s: (s.t, s.T_cab), "plot"),
        ("heater_power", "heater power delivered [W]", lambda s: (s.t[:-1], s.flows["Q_heat"]), "plot"),
    ]
    title = f"{cs.sims[keys[0]].info.get('cycle', '')}, {cs.scenario.T_amb:g} degC"
    for name, ylabel, get, _kind in series:
        use = keys if name not in ("cabin", "heater_power") else [k for k in keys if k in ("thermal",
                                                                                           "thermal_cabin")]
        if not use:  # no strategy of this figure was solved: no empty axes
            continue
        if name == "engine_mode":
            fig, axs = plt.subplots(len(use), 1, figsize=(9, 1.6 * len(use) + 0.6), sharex=True,
                                    squeeze=False)
            for ax, k in zip(axs[:, 0], use):
                t, y = get(cs.sims[k])
                ax.step(t, y, where="post", color=colors[k], lw=0.8)
                ax.set_yticks([1, 2, 3, 4], ["off", "idle", "on", "catalyst"])
                ax.set_ylabel(LABELS[k].split(" on ")[0], fontsize=8)
            axs[-1, 0].set_xlabel("time [s]")
            fig.suptitle(f"engine mode - {title}", fontsize=10)
        else:
            fig, ax = plt.subplots(figsize=(9, 3.6))
            for k in use:
                t, y = get(cs.sims[k])
                ax.plot(t, y, color=colors[k], lw=0.9, label=LABELS[k])
            if name == "cabin" and "thermal_cabin" in cs.outcomes:
                ex = cs.outcomes["thermal_cabin"].extra
                # the scenario's bound, which the DP enforces (the cabin grid's top lies above it)
                ax.axhline(cs.scenario.T_cab_ub, color="0.5", ls=":", lw=0.8,
                           label=f"upper bound {cs.scenario.T_cab_ub:g} degC")
                lb = getattr(cs.outcomes["thermal_cabin"], "T_cab_lb", None)
                if lb is not None:  # the comfort bound at steps 1..N, which Thermal-Cabin-DP may ride
                    tt = cs.sims["thermal_cabin"].t
                    ax.plot(tt[1:1 + len(lb)], lb, color="0.5", ls="--", lw=0.8, label="comfort bound")
                if cs.scenario.terminal == "free":
                    ax.axhline(ex.get("T_cab_terminal_min", np.nan), color="0.5", ls="--", lw=0.8,
                               label="terminal minimum")
            ax.set_xlabel("time [s]")
            ax.set_ylabel(ylabel)
            ax.legend(fontsize=8, loc="best")
            ax.set_title(title, fontsize=10)
        save(fig, name)
    # fuel bars: the saving of each strategy against the reference (rule-based when present). Corrected fuel
    # (final SOC, coolant and cabin heat valued) is the headline: the solid bar on top; raw fuel (as burnt)
    # beside it, lighter. Savings rather than grams from 0 keep differences of a few percent visible.
    ref = "rule" if "rule" in keys else keys[0]
    fuel = {k: cs.sims[k].fuel_g for k in keys}
    corr = {k: cs.sims[k].summary()["fuel_corrected_g"] for k in keys}
    sav = [100 * (1 - fuel[k] / fuel[ref]) for k in keys]
    sav_c = [100 * (1 - corr[k] / corr[ref]) for k in keys]
    fig, ax = plt.subplots(figsize=(8, 0.75 * len(keys) + 2.5))
    y = np.arange(len(keys))[::-1]
    h = 0.38
    ax.barh(y + h / 2, sav_c, h, color=[colors[k] for k in keys], label="corrected fuel (final SOC, coolant and "
            "cabin heat valued)")
    ax.barh(y - h / 2, sav, h, color=[colors[k] for k in keys], alpha=0.3, label="raw fuel (as burnt)")
    papers = [PAPER_SAVINGS.get(k, {}).get("vs_rule") for k in keys] if ref == "rule" else []
    span = max([abs(v) for v in sav + sav_c] + [p for p in papers if p is not None] + [0.5])
    for yi, k, v, vc in zip(y, keys, sav, sav_c):
        paper = PAPER_SAVINGS.get(k, {}).get("vs_rule") if ref == "rule" else None
        if paper is not None:  # the paper's figure is raw fuel: drawn on the raw bar
            ax.plot([paper], [yi - h / 2], marker="D", color="k", ms=5, ls="none",
                    label=f"paper ({PAPER_CONDITION})" if k == "thermal" else None)
        for yy, val, g, what, c, mark in ((yi + h / 2, vc, corr[k], "corrected", "k", None),
                                          (yi - h / 2, v, fuel[k], "raw", "0.35", paper)):
            txt = f"{what} {g:.1f} g" + (" (reference)" if k == ref else f", {val:+.2f} %")
            ax.text(max(val, 0, mark or 0) + 0.03 * span, yy, txt, va="center", ha="left", fontsize=8, color=c)
    ax.axvline(0, color="0.3", lw=0.8)
    ax.set_yticks(y, [LABELS[k].replace(" on thermal model", "\non thermal model") for k in keys], fontsize=8)
    ax.set_xlim(min(0.0, min(sav + sav_c)) - 0.1 * span, 1.6 * span)
    ax.set_xlabel(f"saving vs {LABELS[ref]} [%]")
    handles, names = ax.get_legend_handles_labels()
    # the headline first, raw beside it, the paper's figures last
    first = sorted(range(len(names)), key=lambda i: (not names[i].startswith("corrected"), not names[i].startswith("raw")))
    ax.legend([handles[i] for i in first], [names[i] for i in first], fontsize=8, loc="upper center",
              bbox_to_anchor=(0.5, -0.16), ncol=1, frameon=False)
    ax.set_title(f"fuel saving - {title} (terminal condition: {cs.scenario.terminal})", fontsize=10)
    save(fig, "fuel_bars")
    return paths


def plot_study(df: pd.DataFrame, outdir, metric="both") -> list[str]:
    """``saving_vs_ambient.png`` (saving of each non-reference strategy vs ambient, one line per cycle;
    median and 5-95 % band over Monte-Carlo draws) when the ambient varies, and ``saving_spread.png``
    (boxplot over draws for each cycle and ambient) when there are Monte-Carlo draws. ``metric``:
    ``saving_pct`` (fuel), ``saving_corrected_pct`` (fuel corrected for the final SOC, coolant and cabin
    energy) or ``both`` (one panel each). Returns the paths."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    outdir = Path(outdir)
    paths = []
    ok = df[(df["status"] == "ok") & (df["strategy"] != df["reference"])]
    if ok.empty:
        return paths
    # corrected first (the headline), raw beside it
    metrics = ["saving_corrected_pct", "saving_pct"] if metric == "both" else [metric]
    labels = {"saving_pct": "raw fuel saving vs {ref} [%]",
              "saving_corrected_pct": "corrected-fuel saving vs {ref} [%]"}
    ref = NAMES.get(df["reference"].iloc[0], df["reference"].iloc[0])
    name = df["study"].iloc[0] if "study" in df else ""

    def save(fig, fname):
        p = outdir / fname
        finish_figure(fig, p)
        paths.append(str(p))

    if ok["T_amb"].nunique() > 1:
        fig, axs = plt.subplots(1, len(metrics), figsize=(6.2 * len(metrics), 4.2), squeeze=False)
        groups = list(ok.groupby(["cycle", "strategy", "params"], sort=True))
        for ax, m in zip(axs[0], metrics):
            for i, ((cyc, strat, plabel), g) in enumerate(groups):
                st = g.groupby("T_amb")[m]
                med = st.median()
                lab = f"{cyc}, {NAMES.get(strat, strat)}" + (f" ({plabel})" if ok["params"].nunique() > 1 else "")
                line, = ax.plot(med.index, med.values, marker="o", lw=1.4, label=lab, color=f"C{i % 10}")
                if g["draw"].notna().any() and st.size().max() > 1:
                    ax.fill_between(med.index, st.quantile(0.05).values, st.quantile(0.95).values,
                                    color=line.get_color(), alpha=0.2, lw=0)
            ax.axhline(0, color="0.6", lw=0.7)
            ax.set_xlabel("ambient temperature [degC]")
            ax.set_ylabel(labels[m].format(ref=ref))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        plabels = sorted(ok["params"].unique())
        fig.suptitle(f"{name}: saving vs ambient (parameters: {', '.join(plabels[:3])}"
                     f"{', ...' if len(plabels) > 3 else ''})", fontsize=10)
        save(fig, "saving_vs_ambient.png")
    draws = ok[ok["draw"].notna()]
    if not draws.empty and draws.groupby(["cycle", "T_amb", "strategy"]).size().max() > 1:
        keys = sorted(draws.groupby(["strategy", "cycle", "T_amb"]).groups)
        fig, axs = plt.subplots(len(metrics), 1, figsize=(max(6.0, 0.55 * len(keys) + 2), 3.6 * len(metrics)),
                                squeeze=False)
        for ax, m in zip(axs[:, 0], metrics):
            data = [draws[(draws["strategy"] == s) & (draws["cycle"] == c) & (draws["T_amb"] == t)][m].values
                    for s, c, t in keys]
            ax.boxplot(data, showfliers=True)
            ax.set_xticks(range(1, len(keys) + 1),
                          [f"{c}\n{t:g} degC" + (f"\n{NAMES.get(s, s)}" if draws["strategy"].nunique() > 1 else "")
                           for s, c, t in keys], fontsize=7)
            ax.set_ylabel(labels[m].format(ref=ref))
            ax.grid(alpha=0.3, axis="y")
        axs[0, 0].set_title(f"{name}: spread over {draws['draw'].nunique()} parameter draws", fontsize=10)
        save(fig, "saving_spread.png")
    return paths


def plot_policy(policy, path=None, demands_W=(0.0, 5e3, 12e3, 25e3)):
    """Maps of the chosen battery power (engine on) and engine mode over SOC x T_cl for a few demands."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    ds = sorted({int(np.argmin(np.abs(policy.demand_W - x))) for x in demands_W})
    fig, axs = plt.subplots(2, len(ds), figsize=(3.4 * len(ds), 6.2), squeeze=False)
    ext = [policy.tcl_grid[0], policy.tcl_grid[-1], policy.soc_grid[0], policy.soc_grid[-1]]
    for c, d in enumerate(ds):
        e = policy.e_mode[d]
        pb = np.where(e == 3, policy.P_bat_mg[d] / 1e3, np.nan)
        im = axs[0, c].imshow(pb, origin="lower", aspect="auto", extent=ext, cmap="coolwarm",
                              vmin=-25, vmax=25)
        axs[0, c].set_title(f"demand {policy.demand_W[d] / 1e3:.1f} kW", fontsize=9)
        im2 = axs[1, c].imshow(e, origin="lower", aspect="auto", extent=ext, cmap="viridis", vmin=1, vmax=3)
        axs[1, c].set_xlabel("coolant [degC]")
    axs[0, 0].set_ylabel("SOC [-]  (P_bat_mg when on)")
    axs[1, 0].set_ylabel("SOC [-]  (engine mode)")
    fig.colorbar(im, ax=axs[0, :].tolist(), label="P_bat_mg [kW] (+ discharge)")
    cb = fig.colorbar(im2, ax=axs[1, :].tolist(), ticks=[1, 2, 3])
    cb.ax.set_yticklabels(["off", "idle", "on"])
    fig.suptitle(f"SDP policy at {policy.config.T_amb:g} degC ambient, heater {policy.config.Q_heat:g} W",
                 fontsize=10)
    if path is not None:
        from calib.fileio import save_figure

        save_figure(fig, path)
    return fig


def plot_dp_result(res, path=None, title=None):
    """A generic DP solution: each state, each control and the cumulative stage cost against the step.
    Written atomically when ``path`` is given. Returns the Figure."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    nx, nu = res.x.shape[1], res.u.shape[1]
    fig, ax = plt.subplots(nx + nu + 1, 1, figsize=(8, 1.7 * (nx + nu + 1) + 0.8), sharex=True, squeeze=False)
    ax = ax[:, 0]
    k = np.arange(res.x.shape[0])
    for d in range(nx):
        ax[d].plot(k, res.x[:, d], "C0", lw=0.9)
        ax[d].set_ylabel(f"state x{d}")
    for j in range(nu):
        ax[nx + j].step(k[:-1], res.u[:, j], "C1", where="post", lw=0.9)
        ax[nx + j].set_ylabel(f"control u{j}")
    ax[-1].plot(k, np.concatenate([[0.0], np.cumsum(res.stage_cost)]), "C2", lw=0.9)
    ax[-1].set_ylabel("cumulative cost")
    ax[-1].set_xlabel("step k")
    for a in ax:
        a.grid(alpha=0.3)
    status = "feasible" if res.feasible else "INFEASIBLE"
    return finish_figure(fig, path, title or f"DP solution: cost {res.cost:.4g} ({status})")
