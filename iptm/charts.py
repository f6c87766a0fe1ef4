"""Interactive time-series charts for the dashboard (Altair, which ships with Streamlit).

Panels stacked vertically share one time axis: dragging or zooming one (mouse wheel, or drag to pan)
moves all of them, so a stop can be inspected in every signal at once; hovering shows the values. Only
data reshaping is done here: the series come from :class:`calib.fit.validate.Replay` and
:class:`calib.simulate.SimResult`. The HTML report keeps static matplotlib figures (self-contained).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

STRATEGY_COLORS = {"Rule-based (tuned)": "#222222", "Baseline-DP on thermal model": "#1f77b4",
                   "Thermal-DP": "#d62728", "Thermal-Cabin-DP": "#2ca02c",
                   "Baseline-DP (own optimum, f_cl = 1)": "#9467bd"}


def _stack(df: pd.DataFrame, panels: list[tuple[str, str]], color: str, domain=None, colors=None,
           height: int = 140):
    """Vertically stacked line charts of ``df`` (columns time_s, panel, series, value), one per panel,
    with a shared, linked x (time) axis."""
    import altair as alt

    scale = alt.Scale(domain=domain, range=colors) if domain and colors else alt.Undefined
    charts = []
    for i, (key, title) in enumerate(panels):
        # each panel zooms/pans its x scale; the scale is shared, so every panel follows
        zoom = alt.selection_interval(bind="scales", encodings=["x"], name=f"zoom_{i}")
        sub = df[df["panel"] == key]
        if sub.empty:
            continue
        c = (alt.Chart(sub).mark_line(strokeWidth=1.2, interpolate="linear")
             .encode(x=alt.X("time_s:Q", title="time [s]"),
                     y=alt.Y("value:Q", title=title, scale=alt.Scale(zero=False)),
                     color=alt.Color(f"{color}:N", scale=scale, legend=alt.Legend(orient="top", title=None, labelLimit=320)),
                     strokeDash=alt.StrokeDash("kind:N", legend=None) if "kind" in sub.columns else alt.Undefined,
                     tooltip=[alt.Tooltip("time_s:Q", title="t [s]", format=".0f"), f"{color}:N",
                              alt.Tooltip("value:Q", title=title, format=".4g")])
             .properties(height=height, width="container")
             .add_params(zoom))
        charts.append(c)
    if not charts:
        return None
    return alt.vconcat(*charts).resolve_scale(x="shared", color="shared")


def _long(t, series: dict, panel: str, label: str, label_col: str, kind=None) -> pd.DataFrame:
    n = min(len(t), len(series))
    d = pd.DataFrame({"time_s": np.asarray(t, float)[:n], "value": np.asarray(series, float)[:n]})
    d["panel"], d[label_col] = panel, label
    if kind is not None:
        d["kind"] = kind
    return d.dropna(subset=["value"])


VALIDATION_PANELS = [("soc", "SOC [-]"), ("coolant_temp", "coolant [degC]"), ("cabin_temp", "cabin [degC]"),
                     ("fuel_rate", "fuel rate [g/s]"), ("cumulative_fuel", "cumulative fuel [g]")]


def validation_frame(rep) -> pd.DataFrame:
    """Measured and simulated series of a replay in long form (cumulative fuel included)."""
    parts = []
    for key, _ in VALIDATION_PANELS[:-1]:
        for kind, src in (("measured", rep.measured), ("simulated", rep.simulated)):
            if key in src and key in rep.measured:
                parts.append(_long(rep.t, src[key], key, kind, "series", kind))
    cum = rep.cumulative_fuel() if "fuel_rate" in rep.measured else None
    if cum is not None:  # both over the same seconds (calib.fit.validate.Replay.cumulative_fuel)
        parts.append(_long(rep.t, cum[0], "cumulative_fuel", "measured", "series", "measured"))
        parts.append(_long(rep.t, cum[1], "cumulative_fuel", "simulated", "series", "simulated"))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["time_s", "value", "panel", "series", "kind"])


def validation_chart(rep):
    """Measured (solid) vs simulated (dashed) SOC, coolant, cabin, fuel rate and cumulative fuel."""
    return _stack(validation_frame(rep), VALIDATION_PANELS, "series", domain=["measured", "simulated"],
                  colors=["#222222", "#d62728"], height=120)


TRAJECTORY_PANELS = [("speed", "speed [km/h]"), ("soc", "SOC [-]"), ("coolant", "coolant [degC]"),
                     ("cabin", "cabin [degC]"), ("engine_power", "engine power [kW]"),
                     ("battery_power", "battery power [kW]"), ("heater", "heater delivered [W]"),
                     ("cumulative_fuel", "cumulative fuel [g]")]


def trajectories_frame(sims: dict, labels: dict) -> pd.DataFrame:
    """Every strategy's states, powers and cumulative fuel in long form (column ``strategy``)."""
    parts = []
    first = True
    for key, s in sims.items():
        lab = labels.get(key, key)
        if first:  # the cycle is the same for every strategy
            parts.append(_long(s.t, s.v * 3.6, "speed", "cycle", "strategy"))
            first = False
        f = s.flows
        tt = s.t[:-1]
        parts += [_long(s.t, s.soc, "soc", lab, "strategy"), _long(s.t, s.T_cl, "coolant", lab, "strategy"),
                  _long(s.t, s.T_cab, "cabin", lab, "strategy"),
                  _long(tt, f["P_e"] / 1e3, "engine_power", lab, "strategy"),
                  _long(tt, f["P_bat"] / 1e3, "battery_power", lab, "strategy"),
                  _long(tt, f["Q_heat"], "heater", lab, "strategy"),
                  _long(s.t, np.concatenate([[0.0], np.cumsum(f["W_f"]) * s.Ts]), "cumulative_fuel", lab,
                        "strategy")]
    return pd.concat(parts, ignore_index=True)


def trajectories_chart(sims: dict, labels: dict):
    """The strategies' trajectories, one panel per signal, one colour per strategy, linked time axes."""
    df = trajectories_frame(sims, labels)
    present = set(df["strategy"])
    dom = [lab for lab in ["cycle", *STRATEGY_COLORS] if lab in present]
    dom += sorted(present - set(dom))
    pal = {"cycle": "#7f7f7f", **STRATEGY_COLORS}
    return _stack(df, TRAJECTORY_PANELS, "strategy", domain=dom,
                  colors=[pal.get(d, "#bcbd22") for d in dom], height=130)
