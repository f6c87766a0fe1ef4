"""Channel report: which canonical channels a log has, at what rate, with what gaps and ranges."""
from __future__ import annotations

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS, DERIVABLE, DriveLog


def _gaps(t: np.ndarray, threshold: float) -> tuple[int, float]:
    if len(t) < 2:
        return 0, 0.0
    d = np.diff(t)
    big = d[d > threshold]
    return int(len(big)), float(big.max()) if len(big) else 0.0


def channel_report(log: DriveLog, streams: dict | None = None, max_gap_s: float = 5.0) -> pd.DataFrame:
    """One row per canonical channel.

    Parameters
    ----------
    log : DriveLog
        The resampled log.
    streams : dict, optional
        The raw streams it came from; with them, sample counts, native rates and gaps describe the
        original samples rather than the resampled grid.
    max_gap_s : float
        A gap is a stretch without samples longer than this (or, on the resampled grid, a run of NaN).

    Returns
    -------
    pandas.DataFrame
        Index ``channel``; columns ``present`` (bool), ``n`` (samples), ``rate_hz`` (median native rate),
        ``gaps`` (count), ``longest_gap_s``, ``min``, ``max``, ``unit``, ``derivable`` (absent, but follows
        from channels that are present: engine power from speed and torque, battery power from V and I).
        ``attrs["damage"]`` is the log's damage summary (empty for an intact file), ``attrs["speed_source"]``
        where speed came from.
    """
    rows = []
    for ch, (unit, _desc) in CHANNELS.items():
        col = log.data[ch] if ch in log.data.columns else None
        present = col is not None and bool(col.notna().any())
        row = {"channel": ch, "present": present, "n": 0, "rate_hz": np.nan, "gaps": 0,
               "longest_gap_s": 0.0, "min": np.nan, "max": np.nan, "unit": unit}
        if streams is not None and ch in streams and len(streams[ch]):
            s = streams[ch]
            t = s.index.to_numpy(float)
            row["n"] = int(len(s))
            if len(t) > 1:
                md = float(np.median(np.diff(t)))
                row["rate_hz"] = 1.0 / md if md > 0 else np.nan
            row["gaps"], row["longest_gap_s"] = _gaps(t, max_gap_s)
            row["min"], row["max"] = float(s.min()), float(s.max())
            row["present"] = True
        elif present:
            ok = col.notna().to_numpy()
            t = log.data.index.to_numpy(float)
            row["n"] = int(ok.sum())
            row["rate_hz"] = 1.0 / log.dt
            # On the grid, a gap is a run of NaN between valid points.
            row["gaps"], row["longest_gap_s"] = _gaps(t[ok], log.dt * 1.5)
            row["min"], row["max"] = float(col.min()), float(col.max())
        rows.append(row)
    out = pd.DataFrame(rows).set_index("channel")
    out["derivable"] = False
    for ch, parts in DERIVABLE.items():
        if ch in out.index and not out.loc[ch, "present"] and all(out.loc[c, "present"] for c in parts):
            out.loc[ch, "derivable"] = True
    out.attrs["damage"] = dict(log.meta.damage or {})
    out.attrs["speed_source"] = log.meta.channel_sources.get("speed_mps", "")
    return out


#: How a channel is shown to a reader when its canonical unit is not the one engineers read:
#: (display unit, factor from the canonical unit). Speed is shown in km/h beside m/s.
DISPLAY_UNITS = {"soc": ("%", 100.0)}
SECOND_UNIT = {"speed_mps": ("km/h", 3.6)}


def _decimals(lo: float, hi: float, sig: int = 3) -> int:
    """Decimals that show ``sig`` significant digits of the larger magnitude: a resampling artefact such as
    a minimum of 0.0006 m/s beside a maximum of 20 m/s prints as 0.00."""
    big = max(abs(lo), abs(hi)) if np.isfinite(lo) and np.isfinite(hi) else 0.0
    if big == 0.0:
        return 0
    return int(max(0, sig - 1 - np.floor(np.log10(big))))


def _num(v: float, dec: int) -> str:
    if not np.isfinite(v):
        return "-"
    s = f"{v:.{dec}f}"
    return "0" + ("." + "0" * dec if dec else "") if float(s) == 0.0 else s  # no "-0.00"


def display_report(report: pd.DataFrame) -> pd.DataFrame:
    """The channel report as a reader sees it: present channels only, ranges rounded to the channel's own
    scale (3 significant digits of its largest magnitude), SOC in %, speed in m/s and km/h.

    Returns a DataFrame of strings and integers with columns ``channel, samples, rate Hz, gaps,
    longest gap s, min, max, unit``.
    """
    rows = []
    for ch, r in report.iterrows():
        if not r["present"]:
            continue
        unit, f = r["unit"], 1.0
        if ch in DISPLAY_UNITS:
            unit, f = DISPLAY_UNITS[ch]
        lo, hi = float(r["min"]) * f, float(r["max"]) * f
        dec = _decimals(lo, hi)
        mn, mx = _num(lo, dec), _num(hi, dec)
        if ch in SECOND_UNIT:
            u2, f2 = SECOND_UNIT[ch]
            d2 = _decimals(lo * f2, hi * f2)
            mn, mx = f"{mn} ({_num(lo * f2, d2)})", f"{mx} ({_num(hi * f2, d2)})"
            unit = f"{unit} ({u2})"
        rate = r["rate_hz"]
        rows.append({"channel": ch, "samples": int(r["n"]),
                     "rate Hz": f"{rate:.2f}" if np.isfinite(rate) else "-", "gaps": int(r["gaps"]),
                     "longest gap s": f"{float(r['longest_gap_s']):.1f}", "min": mn, "max": mx, "unit": unit})
    return pd.DataFrame(rows, columns=["channel", "samples", "rate Hz", "gaps", "longest gap s", "min", "max",
                                       "unit"])


def format_report(report: pd.DataFrame, title: str = "") -> str:
    """Plain-text table of a :func:`channel_report` (as :func:`display_report`; missing channels listed at
    the end)."""
    lines = [title] if title else []
    disp = display_report(report)
    lines.append(f"{'channel':22s} {'n':>8s} {'rate Hz':>8s} {'gaps':>5s} {'longest':>8s} {'min':>16s} "
                 f"{'max':>16s}  unit")
    for _, r in disp.iterrows():
        lines.append(f"{r['channel']:22s} {r['samples']:8d} {r['rate Hz']:>8s} {r['gaps']:5d} "
                     f"{r['longest gap s']:>8s} {r['min']:>16s} {r['max']:>16s}  {r['unit']}")
    missing = [ch for ch, r in report.iterrows() if not r["present"] and not bool(r.get("derivable", False))]
    derived = [ch for ch, r in report.iterrows() if not r["present"] and bool(r.get("derivable", False))]
    if derived:
        lines.append("derivable: " + ", ".join(f"{ch} (from {' x '.join(DERIVABLE[ch])})" for ch in derived))
    src = report.attrs.get("speed_source")
    if src:
        lines.append(f"speed from: {src}")
    dmg = report.attrs.get("damage")
    if dmg:
        lines.append(f"RECOVERED: {dmg.get('summary', 'damaged log')}")
    lines.append("missing: " + (", ".join(missing) if missing else "none"))
    return "\n".join(lines)
