"""Channel report: which canonical channels a log has, at what rate, with what gaps and ranges."""
from __future__ import annotations

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS, DERIVABLE, DriveLog

#: A channel that loses more than this fraction of the samples read is named in a loud warning.
LOSS_WARN_FRACTION = 0.01


def channel_losses(meta) -> dict:
    """Channels that lost samples where they entered: ``{channel: {"lost", "read", "fraction", "why"}}``.

    ``lost`` counts non-finite and out-of-range samples (merges of samples sharing a time are not losses);
    ``why`` says what they were and, for impossible values, the first times.
    """
    out = {}
    for ch, c in (getattr(meta, "channel_counts", None) or {}).items():
        lost = int(c.get("nonfinite", 0)) + int(c.get("out_of_range", 0))
        if not lost:
            continue
        read = max(int(c.get("read", 0)), 1)
        why = []
        if c.get("nonfinite"):
            why.append(f"{c['nonfinite']} not finite (NaN/inf)")
        if c.get("out_of_range"):
            lo, hi = c.get("range", [float("nan"), float("nan")])
            times = ", ".join(f"{t:.1f}" for t in c.get("out_of_range_times_s", []))
            more = ", ..." if c["out_of_range"] > len(c.get("out_of_range_times_s", [])) else ""
            why.append(f"{c['out_of_range']} outside [{lo:g}, {hi:g}] {CHANNELS[ch][0]} (at {times}{more} s)")
        out[ch] = {"lost": lost, "read": int(c.get("read", 0)), "fraction": lost / read, "why": "; ".join(why)}
    return out


def loss_text(meta, threshold: float = LOSS_WARN_FRACTION) -> str:
    """One line naming every channel that lost more than ``threshold`` of its samples ('' when none did)."""
    bad = {ch: d for ch, d in channel_losses(meta).items() if ch in meta.lossy_channels(threshold)}
    if not bad:
        return ""
    return "channels lost samples: " + "; ".join(
        f"{ch} lost {d['lost']} of {d['read']} ({100 * d['fraction']:.1f} %: {d['why']})" for ch, d in bad.items())


def _gaps(t: np.ndarray, threshold: float) -> tuple[int, float]:
    if len(t) < 2:
        return 0, 0.0
    d = np.diff(t)
    big = d[d > threshold]
    return int(len(big)), float(big.max()) if len(big) else 0.0


def log_warnings(log) -> list[str]:
    """What a user must be told about a log before trusting it, one line each: damage, channels that lost
    more than 1 % of their samples, estimated channels (empty for a clean, measured log)."""
    out = []
    if log.meta.damage:
        out.append(str(log.meta.damage.get("summary", "recovered a damaged log")))
    lost = loss_text(log.meta)
    if lost:
        out.append(lost)
    out.extend(f"{ch} is an {how}" for ch, how in (log.meta.estimated or {}).items())
    return out


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
        ``read`` (samples in the file), ``merged`` (folded into a mean with another at the same time) and
        ``lost`` (non-finite or physically impossible, dropped) where the reader accounted them.
        ``attrs["damage"]`` is the log's damage summary (empty for an intact file), ``attrs["speed_source"]``
        where speed came from, ``attrs["losses"]`` :func:`channel_losses`, ``attrs["estimated"]`` the channels
        that are estimates (fuel from MAF) and how.
    """
    rows = []
    for ch, (unit, _desc) in CHANNELS.items():
        col = log.data[ch] if ch in log.data.columns else None
        present = col is not None and bool(col.notna().any())
        row = {"channel": ch, "present": present, "n": 0, "rate_hz": np.nan, "gaps": 0,
               "longest_gap_s": 0.0, "min": np.nan, "max": np.nan, "unit": unit, "read": 0, "merged": 0,
               "lost": 0}
        cnt = log.meta.channel_counts.get(ch)
        if cnt:
            row["read"], row["merged"] = int(cnt.get("read", 0)), int(cnt.get("merged", 0))
            row["lost"] = int(cnt.get("nonfinite", 0)) + int(cnt.get("out_of_range", 0))
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
    out.attrs["losses"] = channel_losses(log.meta)
    out.attrs["estimated"] = dict(log.meta.estimated or {})
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

    Returns a DataFrame of strings and integers with columns ``channel, samples, lost, rate Hz, gaps,
    longest gap s, min, max, unit`` (``lost``: samples dropped as non-finite or impossible).
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
        rows.append({"channel": ch, "samples": int(r["n"]), "lost": int(r.get("lost", 0) or 0),
                     "rate Hz": (f"{rate:.2f}" if rate >= 0.1 else f"{rate:.2g}") if np.isfinite(rate) else "-", "gaps": int(r["gaps"]),
                     "longest gap s": f"{float(r['longest_gap_s']):.1f}", "min": mn, "max": mx, "unit": unit})
    return pd.DataFrame(rows, columns=["channel", "samples", "lost", "rate Hz", "gaps", "longest gap s", "min",
                                       "max", "unit"])


def format_report(report: pd.DataFrame, title: str = "") -> str:
    """Plain-text table of a :func:`channel_report` (as :func:`display_report`; missing channels listed at
    the end)."""
    lines = [title] if title else []
    disp = display_report(report)
    lines.append(f"{'channel':22s} {'n':>8s} {'lost':>6s} {'rate Hz':>8s} {'gaps':>5s} {'longest':>8s} "
                 f"{'min':>16s} {'max':>16s}  unit")
    for _, r in disp.iterrows():
        lines.append(f"{r['channel']:22s} {r['samples']:8d} {r['lost']:6d} {r['rate Hz']:>8s} {r['gaps']:5d} "
                     f"{r['longest gap s']:>8s} {r['min']:>16s} {r['max']:>16s}  {r['unit']}")
    missing = [ch for ch, r in report.iterrows() if not r["present"] and not bool(r.get("derivable", False))]
    derived = [ch for ch, r in report.iterrows() if not r["present"] and bool(r.get("derivable", False))]
    if derived:
        lines.append("derivable: " + ", ".join(f"{ch} (from {' x '.join(DERIVABLE[ch])})" for ch in derived))
    src = report.attrs.get("speed_source")
    if src and "speed_mps" in report.index and bool(report.loc["speed_mps", "present"]):
        lines.append(f"speed from: {src}")
    for ch, how in (report.attrs.get("estimated") or {}).items():
        lines.append(f"ESTIMATED {ch}: {how}")
    losses = report.attrs.get("losses") or {}
    for ch, d in losses.items():
        loud = "LOST" if d["fraction"] > LOSS_WARN_FRACTION else "lost"
        lines.append(f"{loud} {ch}: {d['lost']} of {d['read']} samples ({100 * d['fraction']:.2f} %): {d['why']}")
    dmg = report.attrs.get("damage")
    if dmg:
        lines.append(f"RECOVERED: {dmg.get('summary', 'damaged log')}")
    lines.append("missing: " + (", ".join(missing) if missing else "none"))
    return "\n".join(lines)
