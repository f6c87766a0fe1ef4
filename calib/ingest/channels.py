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
    rep = pd.DataFrame(rows).set_index("channel")
    rep["derivable"] = False
    for ch, parts in DERIVABLE.items():
        if ch in rep.index and not rep.loc[ch, "present"] and all(rep.loc[c, "present"] for c in parts):
            rep.loc[ch, "derivable"] = True
    return rep


def format_report(report: pd.DataFrame, title: str = "") -> str:
    """Plain-text table of a :func:`channel_report` (missing channels listed at the end)."""
    lines = [title] if title else []
    lines.append(f"{'channel':22s} {'n':>8s} {'rate Hz':>8s} {'gaps':>5s} {'longest':>8s} {'min':>10s} {'max':>10s}  unit")
    missing, derived = [], []
    for ch, r in report.iterrows():
        if not r["present"]:
            (derived if bool(r.get("derivable", False)) else missing).append(ch)
            continue
        rate = f"{r['rate_hz']:8.2f}" if np.isfinite(r["rate_hz"]) else f"{'-':>8s}"
        lines.append(f"{ch:22s} {int(r['n']):8d} {rate} {int(r['gaps']):5d} {r['longest_gap_s']:8.1f} "
                     f"{r['min']:10.4g} {r['max']:10.4g}  {r['unit']}")
    if derived:
        lines.append("derivable: " + ", ".join(f"{ch} (from {' x '.join(DERIVABLE[ch])})" for ch in derived))
    lines.append("missing: " + (", ".join(missing) if missing else "none"))
    return "\n".join(lines)
