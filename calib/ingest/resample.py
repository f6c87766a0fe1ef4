"""Put irregular streams on a common uniform time base without inventing data across long gaps."""
from __future__ import annotations

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS, DriveLog, LogMeta
from calib.errors import IptmError, LogFormatError

#: Most rows of a resampled table (23 days at 1 Hz); more means garbled timestamps, not a drive.
MAX_ROWS = 2_000_000


#: A channel polled slowly (an OBD PID read every 5-15 s) is interpolated between its own samples up to this many
#: times its median sampling interval; a longer silence is a dropout and stays empty.
POLL_GAP_FACTOR = 2.5


def native_interval(t: np.ndarray) -> float:
    """Median interval between a stream's distinct sample times (s); NaN with fewer than two."""
    if len(t) < 2:
        return float("nan")
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else float("nan")


#: Fewest samples from which a stream's own sampling interval is taken (two samples cannot tell a slow rate
#: from a gap).
MIN_SAMPLES_FOR_RATE = 5


def stream_gap_limit(t: np.ndarray, max_gap_s: float) -> float:
    """The longest gap interpolated across for a stream: ``max_gap_s``, or more for a channel that is
    polled more slowly than that (:data:`POLL_GAP_FACTOR` times its median interval, from at least
    :data:`MIN_SAMPLES_FOR_RATE` samples)."""
    if len(t) < MIN_SAMPLES_FOR_RATE:
        return max_gap_s
    md = native_interval(t)
    return max(max_gap_s, POLL_GAP_FACTOR * md) if np.isfinite(md) else max_gap_s


def resample_stream(s: pd.Series, grid: np.ndarray, dt: float, max_gap_s: float, return_mask: bool = False):
    """Values of one stream on ``grid``.

    A grid point gets the mean of the samples within half a step of it when there are any (so a 10 Hz
    signal is averaged, not decimated, onto 1 Hz), else the linear interpolation between the samples
    either side of it, but only when those two are at most ``max_gap_s`` apart. Outside the first and
    last sample, and inside longer gaps, the value is NaN: nothing is invented.

    Each bin's mean is summed from its own samples, so a value (however large) changes only its own bin.
    With ``return_mask``, returns ``(values, sampled)``: ``sampled`` is True where the bin holds a sample
    (False where the value is interpolated or NaN).
    """
    t = s.index.to_numpy(dtype=float)
    v = s.to_numpy(dtype=float)
    out = np.full(len(grid), np.nan)
    if len(t) == 0:
        return (out, np.zeros(len(grid), bool)) if return_mask else out
    # Bin means over [g - dt/2, g + dt/2).
    lo = np.searchsorted(t, grid - dt / 2, side="left")
    hi = np.searchsorted(t, grid + dt / 2, side="left")
    n = hi - lo
    has = n > 0
    if has.any():
        # Sum each bin on its own (reduceat over [lo, hi) pairs; a running sum would carry one huge value's
        # rounding into every later bin).
        idx = np.empty(2 * int(has.sum()), dtype=np.intp)
        idx[0::2], idx[1::2] = lo[has], hi[has]
        sums = np.add.reduceat(np.append(v, 0.0), idx)[0::2]
        out[has] = sums / n[has]
    # Interpolation for empty bins, within short gaps only.
    if len(t) >= 2:
        need = ~has & (grid >= t[0]) & (grid <= t[-1])
        if need.any():
            g = grid[need]
            j = np.clip(np.searchsorted(t, g, side="right"), 1, len(t) - 1)
            gap = t[j] - t[j - 1]
            vals = np.interp(g, t, v)
            vals[gap > max_gap_s] = np.nan
            out[need] = vals
    return (out, has) if return_mask else out


def to_drivelog(streams: dict, meta: LogMeta, rate_hz: float = 1.0, max_gap_s: float = 5.0) -> DriveLog:
    """Resample streams onto a uniform base starting at 0 s.

    Parameters
    ----------
    streams : dict
        Channel -> :class:`pandas.Series` of samples indexed by seconds from the log's start.
    meta : LogMeta
        Provenance; a note on the resampling is appended (to a copy).
    rate_hz : float
        Output rate (default 1 Hz).
    max_gap_s : float
        Gaps between samples longer than this stay NaN (never interpolated across); for a channel sampled
        more slowly, the limit is :data:`POLL_GAP_FACTOR` times its own median interval.

    Returns
    -------
    DriveLog
        Columns in :data:`CHANNELS` order, index ``time_s`` = 0, dt, 2 dt, ... up to the last sample.
    """
    if not (rate_hz > 0 and np.isfinite(rate_hz)):
        raise IptmError(f"resampling rate must be a positive number of Hz, got {rate_hz}")
    if not (max_gap_s >= 0 and np.isfinite(max_gap_s)):
        raise IptmError(f"max gap must be a non-negative number of seconds, got {max_gap_s}")
    dt = 1.0 / rate_hz
    t_end = max((float(s.index[-1]) for s in streams.values() if len(s)), default=0.0)
    if t_end / dt > MAX_ROWS:
        raise LogFormatError(meta.source, f"log spans {t_end:.4g} s: {t_end / dt:.3g} rows at {rate_hz:g} Hz is more "
                                          f"than {MAX_ROWS:.0e}", hint="check the timestamps (a garbled one?) or "
                                                                        "resample at a lower rate")
    n = int(np.floor(t_end / dt + 1e-9)) + 1
    grid = np.arange(n) * dt
    cols, interpolated = {}, {}
    for ch in CHANNELS:
        if ch in streams and len(streams[ch]):
            s = streams[ch]
            cols[ch], has = resample_stream(s, grid, dt, stream_gap_limit(s.index.to_numpy(float), max_gap_s),
                                            return_mask=True)
            filled = ~has & np.isfinite(cols[ch])
            if filled.any():  # rows whose value was interpolated between samples, as [start, stop) runs
                edges = np.flatnonzero(np.diff(np.concatenate([[0], filled.astype(np.int8), [0]])))
                interpolated[ch] = edges.reshape(-1, 2).tolist()
    data = pd.DataFrame(cols, index=pd.Index(grid, name="time_s"))
    new_meta = LogMeta.from_dict(meta.to_dict())
    new_meta.interpolated_rows = interpolated
    new_meta.notes = list(meta.notes) + [f"resampled to {rate_hz:g} Hz (bin means; interpolation only across gaps <= {max_gap_s:g} s, "
                                        f"or {POLL_GAP_FACTOR:g} sampling intervals of a slower channel)"]
    return DriveLog(data=data, meta=new_meta)
