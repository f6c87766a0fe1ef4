"""CSV drive logs: units in the header (``speed [km/h]``) or a user column map.

Layout accepted::

    # SYNTHETIC drive log ...            <- optional comment lines at the top ('#'),
    # vehicle_id: prius-synth               'key: value' lines become metadata
    time [s],speed [km/h],soc [%],coolant_temp [degC]
    0.0,0.0,55.0,
    0.1,0.4,,
    ...

- The time column is the one named ``time``, ``t``, ``timestamp`` or ``time_s`` (any unit of time), or
  the column a map sends to ``time``. Times must be strictly increasing: a repeat or a step back is an
  error naming the file line, since a CSV row has no other identity.
- Every other column is a channel if its name (without the unit) is a canonical channel or a known
  alias, or if the column map names it. Its unit comes from the header bracket, the map, or the
  canonical name itself (``speed_mps`` is in m/s). A channel column with no unit is an error.
- A column whose name is not an accepted spelling but resembles exactly one channel whose unit fits
  (``coolant [degF]``) is read as that channel, with a warning in ``meta.notes``; one that resembles
  several, or none, is ignored (a warning names the accepted spellings of the look-alikes). ``iptm ingest
  --list-channels`` prints every accepted name. Empty cells are missing samples.
"""
from __future__ import annotations

import csv
import io
import re

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS, LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.units import UnitError, convert, parse_unit
from calib.ingest.common import (
    TIME_NAMES,
    aliases_of,
    canonical_name,
    implied_unit,
    make_series,
    parse_target,
    sniff_text,
    sniff_text_lenient,
    split_spec,
    suggest_channel,
    to_channel_unit,
)
from calib.ingest.damage import Damage



def _read_comments(text: str) -> tuple[list[str], int]:
    lines = []
    n = 0
    for line in text.splitlines():
        if line.startswith("#"):
            lines.append(line[1:].strip())
            n += 1
        elif not line.strip() and not lines:
            n += 1  # leading blank lines
        else:
            break
    return lines, n


def _meta_from_comments(comments: list[str], meta: LogMeta) -> None:
    if comments and "SYNTHETIC" in comments[0].upper():
        meta.synthetic = True
    for c in comments:
        if ":" not in c:
            continue
        key, _, val = c.partition(":")
        key, val = key.strip().lower(), val.strip()
        if key == "vehicle_id":
            meta.vehicle_id = val
        elif key == "start_time":
            meta.start_time = val or None
        elif key == "synthetic":
            meta.synthetic = meta.synthetic or val.lower() in ("true", "yes", "1")
        elif key == "note":
            meta.notes.append(val)


class _RowDamage(LogFormatError):
    """A data row that cannot be trusted (raised as is under ``strict``; otherwise the slow reader skips it)."""


def read_csv_streams(path, column_map: dict | None = None, strict: bool = False) -> tuple[dict, LogMeta]:
    """Read a CSV log into streams.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    column_map : dict, optional
        ``{column header: "channel [unit]"}`` (or ``"channel"`` when the header carries the unit, or
        ``"time [unit]"`` for the time column). Overrides header recognition for the columns it names.
    strict : bool
        Refuse the file at its first damaged data row. By default damaged rows (wrong number of fields,
        a cell that is not a number, a time out of order, bytes that are not text) are skipped line by
        line and listed in ``meta.damage``; the header must be intact.

    Returns
    -------
    (Streams, LogMeta)

    Raises
    ------
    LogFormatError
        Empty or binary file, no time column, unknown unit, no readable row; under ``strict`` also a
        non-numeric cell or a non-monotonic or duplicate time (naming the line).
    """
    try:
        return _read_csv(path, column_map, fast=True)
    except _RowDamage:
        if strict:
            raise
    return _read_csv(path, column_map, fast=False)


def _columns(columns, column_map, path, header_line):
    """Time column, its unit, channel columns ``[(column, channel, unit)]`` and ignored columns."""
    time_col, time_unit = None, None
    channel_cols: list[tuple[str, str, str]] = []  # (column, channel, unit)
    ignored = []
    looks_like, matched = [], []  # warnings: unknown names that resemble a channel
    fuzzy: list[tuple[str, str, str | None]] = []  # (column, channel, unit) matched by resemblance only
    for col in columns:
        where = f"line {header_line}, column {col!r}"
        name, unit = split_spec(col)
        if col in column_map:
            target = column_map[col]
            tname, tunit = split_spec(target) if isinstance(target, str) else (None, None)
            if tname is not None and tname.strip().lower() in TIME_NAMES:
                time_col, time_unit = col, tunit or unit
                continue
            ch, munit = parse_target(target, path, f"column map entry {col!r}")
            unit = munit or unit
            if unit is None:
                raise LogFormatError(path, f"no unit for column {col!r}", where,
                                     "write 'name [unit]' in the header or give the unit in the column map")
            channel_cols.append((col, ch, unit))
            continue
        if name.strip().lower() in TIME_NAMES:
            if time_col is None:
                time_col, time_unit = col, unit
            else:
                ignored.append(col)
            continue
        ch = canonical_name(name)
        if ch is None:
            ch, cands = suggest_channel(name, unit)
            if ch is None:
                ignored.append(col)
                if len(cands) > 2:
                    looks_like.append(f"column {col!r} was not used: it could be any of {', '.join(cands)}; "
                                      "rename it to an accepted name (`iptm ingest --list-channels`) or map it "
                                      "with --map")
                elif cands:
                    looks_like.append(
                        f"column {col!r} was not used: it looks like "
                        + " or ".join(f"{c} (accepted names: {', '.join(aliases_of(c))})" for c in cands)
                        + "; rename the column or map it with --map")
                continue
            fuzzy.append((col, ch, unit))
            continue
        if unit is None:
            if name.strip() == ch and ch in CHANNELS:
                unit = implied_unit(ch)  # the canonical name carries its unit (speed_mps is m/s)
            else:
                raise LogFormatError(path, f"no unit for channel column {col!r}", where,
                                     "write 'name [unit]' in the header or give the unit in a column map")
        channel_cols.append((col, ch, unit))

    taken = {ch for _, ch, _ in channel_cols}
    for col, ch, unit in fuzzy:
        if ch in taken or unit is None:  # an exact name wins; a look-alike needs its unit in the header
            ignored.append(col)
            looks_like.append(f"column {col!r} was not used: it looks like {ch} (accepted names: "
                              f"{', '.join(aliases_of(ch))})" + (", but has no unit" if unit is None else
                                                                 ", which another column already gives"))
            continue
        taken.add(ch)
        channel_cols.append((col, ch, unit))
        matched.append(f"column {col!r} read as {ch} (accepted names: {', '.join(aliases_of(ch))})")
    missing_map = [c for c in column_map if c not in columns]
    if missing_map:
        raise LogFormatError(path, f"column map names column(s) not in the file: {', '.join(map(repr, missing_map))}",
                             f"line {header_line}")
    if time_col is None:
        raise LogFormatError(path, "no time column", f"line {header_line}",
                             "name one 'time [s]' or map a column to 'time [unit]'")
    if time_unit is None:
        if split_spec(time_col)[0].strip().lower() == "time_s":
            time_unit = "s"
        else:
            raise LogFormatError(path, f"no unit for time column {time_col!r}", f"line {header_line}",
                                 "write e.g. 'time [s]'")
    try:
        if parse_unit(time_unit).dimensionality != parse_unit("s").dimensionality:
            raise LogFormatError(path, f"time column unit {time_unit!r} is not a time", f"line {header_line}")
    except UnitError:
        raise LogFormatError(path, f"unknown unit {time_unit!r}", f"line {header_line}, column {time_col!r}") from None
    if not channel_cols:
        raise LogFormatError(path, "no column is a known channel", f"line {header_line}",
                             "name columns like 'speed [km/h]' or pass a column map")
    seen = {}
    for col, ch, _unit in channel_cols:
        if ch in seen:
            raise LogFormatError(path, f"columns {seen[ch]!r} and {col!r} both map to channel {ch}",
                                 f"line {header_line}", "drop one or map it elsewhere")
        seen[ch] = col
    return time_col, time_unit, channel_cols, ignored, matched + looks_like


def _read_csv(path, column_map, fast: bool):
    """``fast``: pandas, any damaged row raises :class:`_RowDamage`; else line by line, skipping damage."""
    head = sniff_text(path, "CSV") if fast else sniff_text_lenient(path, "CSV")
    comments, n_skip = _read_comments(head)
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format="csv")
    _meta_from_comments(comments, meta)
    column_map = dict(column_map or {})
    header_line = n_skip + 1
    dmg = Damage(path, strict=False, unit="line")

    try:
        df = pd.read_csv(path, skiprows=n_skip, dtype=str, keep_default_na=False, skipinitialspace=True,
                         encoding="utf-8", encoding_errors="strict" if fast else "replace",
                         on_bad_lines="error", engine="c", comment=None, nrows=None if fast else 0)
    except pd.errors.EmptyDataError:
        raise LogFormatError(path, "no header line (file holds only comments)") from None
    except pd.errors.ParserError as exc:
        msg = str(exc).strip().splitlines()[-1]
        line = _line_from_pandas(msg, n_skip)
        raise _RowDamage(path, f"malformed CSV: {msg}", line) from None
    except UnicodeDecodeError:
        raise _RowDamage(path, "bytes that are not UTF-8 text in a CSV file", _first_bad_utf8_line(path)) from None
    if df.shape[1] < 2:
        raise LogFormatError(path, "fewer than two columns: need a time column and at least one channel",
                             f"line {header_line}", "is the delimiter a comma?")
    time_col, time_unit, channel_cols, ignored, notes = _columns(list(df.columns), column_map, path, header_line)
    meta.notes.extend(f"warning: {m}" for m in notes)
    if fast:
        if len(df) == 0:
            raise LogFormatError(path, "header but no data rows", f"line {header_line}")
        if not _ends_with_newline(path):
            raise _RowDamage(path, "last line cut short (no line end)", "last line")
        if df.isna().to_numpy().any():  # a row with fewer fields than the header (keep_default_na=False)
            i = int(np.flatnonzero(df.isna().to_numpy().any(axis=1))[0])
            raise _RowDamage(path, f"row has fewer fields than the header's {df.shape[1]}", f"line {header_line + 1 + i}")
        first_data_line = header_line + 1
        t_raw = _numeric(df[time_col], path, time_col, first_data_line, allow_empty=False)
        values = {col: _numeric(df[col], path, col, first_data_line, allow_empty=True) for col, _, _ in channel_cols}
        line_of = None
    else:
        t_raw, values, line_of = _rows_recovering(path, list(df.columns), header_line, time_col,
                                                  [c for c, _, _ in channel_cols], dmg)
        if len(t_raw) == 0:
            raise LogFormatError(path, "no readable data row", f"after line {header_line}",
                                 dmg.where[0] if dmg.where else None)
    t = np.asarray(convert(t_raw, time_unit, "s"), dtype=float)
    d = np.diff(t)
    bad = np.flatnonzero(~(d > 0))
    if len(bad):
        i = int(bad[0]) + 1
        kind = "duplicate time" if d[bad[0]] == 0 else "time goes backwards"
        if fast:
            raise _RowDamage(path, f"{kind}: {t_raw[i]!r} after {t_raw[i - 1]!r}",
                             f"line {header_line + 1 + i}", "times must be strictly increasing")
        # Keep the longest run of rows whose times increase: one garbled time costs one row.
        keep = _longest_increasing(t)
        for j in np.flatnonzero(~keep):
            prev = t[:j][keep[:j]]
            dmg.bad(LogFormatError(path, "time out of order", f"line {line_of[j]}"),
                    float(prev[-1]) if len(prev) else -np.inf)
        t, t_raw = t[keep], t_raw[keep]
        values = {k: v[keep] for k, v in values.items()}
        line_of = line_of[keep]
    if not fast and dmg:
        for tt in t:  # close the spans of lost rows at the next kept row
            if dmg._open_span is None:
                break
            if tt > dmg._open_span:
                dmg.good(tt)
    t0 = float(t[0])
    if not fast:
        meta.damage = dmg.finish(t0, float(t[-1]))
    t = t - t0
    if t0 != 0.0:
        meta.notes.append(f"time shifted by {-t0:g} s so the log starts at 0")

    streams = {}
    for col, ch, unit in channel_cols:
        v = to_channel_unit(values[col], unit, ch, path, f"column {col!r}")
        s = make_series(t, v, ch)
        if len(s):
            streams[ch] = s
        meta.channel_sources[ch] = col
        meta.original_units[ch] = unit
    if ignored:
        meta.notes.append(f"ignored columns: {', '.join(ignored)}")
    return streams, meta


def _first_bad_utf8_line(path) -> str | None:
    with open(path, "rb") as fh:
        for lineno, raw in enumerate(fh, 1):
            try:
                raw.decode("utf-8")
            except UnicodeDecodeError:
                return f"line {lineno}"
    return None


def _ends_with_newline(path) -> bool:
    with open(path, "rb") as fh:
        fh.seek(0, 2)
        if fh.tell() == 0:
            return True
        fh.seek(-1, 2)
        return fh.read(1) in (b"\n", b"\r")


_EMPTY = {"", "nan", "NaN", "NA", "null", "None"}


def _rows_recovering(path, columns, header_line, time_col, value_cols, dmg: Damage):
    """Parse the data rows one line at a time; a row with a wrong field count or a bad cell is skipped."""
    ncol = len(columns)
    it = columns.index(time_col)
    iv = [columns.index(c) for c in value_cols]
    times, lines = [], []
    vals = [[] for _ in iv]
    t_last = -np.inf
    with open(path, "r", encoding="utf-8", errors="replace", newline="") as fh:
        for lineno, line in enumerate(fh, 1):
            if lineno <= header_line:
                continue
            if not line.strip():
                continue
            where = f"line {lineno}"
            if not line.endswith(("\n", "\r")):
                dmg.bad(LogFormatError(path, "line cut short (no line end)", where), t_last)
                continue
            try:
                row = next(csv.reader([line], skipinitialspace=True))
            except (csv.Error, StopIteration):
                dmg.bad(LogFormatError(path, "malformed CSV row", where), t_last)
                continue
            if len(row) != ncol:
                dmg.bad(LogFormatError(path, f"expected {ncol} fields, saw {len(row)}", where), t_last)
                continue
            try:
                cell = row[it].strip()
                if cell in _EMPTY:
                    raise ValueError("empty time cell")
                tv = float(cell)
                rv = []
                for k in iv:
                    c = row[k].strip()
                    rv.append(np.nan if c in _EMPTY else float(c))
                if not np.isfinite(tv) or np.isinf(rv).any():
                    raise ValueError("infinite value")
            except ValueError as exc:
                dmg.bad(LogFormatError(path, f"not a number: {str(exc)[:50]}", where), t_last)
                continue
            times.append(tv)
            lines.append(lineno)
            for lst, v in zip(vals, rv):
                lst.append(v)
            t_last = tv
    return (np.asarray(times, dtype=float), {c: np.asarray(v, dtype=float) for c, v in zip(value_cols, vals)},
            np.asarray(lines, dtype=np.int64))


def _longest_increasing(t: np.ndarray) -> np.ndarray:
    """Mask of a longest strictly increasing subsequence of ``t`` (O(n log n))."""
    import bisect

    n = len(t)
    tails, tails_idx = [], []
    prev = np.full(n, -1, dtype=np.int64)
    for i, x in enumerate(t.tolist()):
        k = bisect.bisect_left(tails, x)
        if k == len(tails):
            tails.append(x)
            tails_idx.append(i)
        else:
            tails[k] = x
            tails_idx[k] = i
        prev[i] = tails_idx[k - 1] if k > 0 else -1
    keep = np.zeros(n, dtype=bool)
    i = tails_idx[-1] if tails_idx else -1
    while i >= 0:
        keep[i] = True
        i = prev[i]
    return keep


def _numeric(col: pd.Series, path, name: str, first_line: int, allow_empty: bool) -> np.ndarray:
    s = col.astype(str).str.strip()
    empty = s.isin(["", "nan", "NaN", "NA", "null", "None"])
    num = pd.to_numeric(s.where(~empty, None), errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(np.isnan(num) & ~empty.to_numpy())
    if len(bad):
        i = int(bad[0])
        raise _RowDamage(path, f"not a number: {s.iloc[i][:40]!r}", f"line {first_line + i}, column {name!r}")
    if not allow_empty and empty.any():
        i = int(np.flatnonzero(empty.to_numpy())[0])
        raise _RowDamage(path, "empty time cell", f"line {first_line + i}, column {name!r}")
    if np.isinf(num).any():
        i = int(np.flatnonzero(np.isinf(num))[0])
        raise _RowDamage(path, "infinite value", f"line {first_line + i}, column {name!r}")
    return num


def _line_from_pandas(msg: str, n_skip: int) -> str | None:
    m = re.search(r"line (\d+)", msg)
    return f"line {int(m.group(1)) + n_skip}" if m else None


def sniff_is_csv(path) -> bool:
    """Heuristic used by format detection: text whose first non-comment line has a comma."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    if b"\x00" in head:
        return False
    text = head.decode("utf-8", errors="replace")
    for line in io.StringIO(text):
        if line.startswith("#") or not line.strip():
            continue
        try:
            return len(next(csv.reader([line]))) >= 2
        except csv.Error:
            return False
    return False


__all__ = ["read_csv_streams", "sniff_is_csv"]
