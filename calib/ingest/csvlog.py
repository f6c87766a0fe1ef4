"""CSV drive logs: wide or long, any clock, units in the header or a column map, OBD-app exports.

Layouts accepted::

    # SYNTHETIC drive log ...            <- optional comment lines at the top ('#'),
    # vehicle_id: prius-synth               'key: value' lines become metadata
    time [s],speed [km/h],soc [%],coolant_temp [degC]      <- wide: one column per channel
    0.0,0.0,55.0,
    0.0,,,-3                                                <- rows may share a time
    0.1,0.4,,

    time [ms],signal,value,unit                             <- long: one sample per row
    0,speed,0.0,km/h
    0,soc,55,%

- Delimiter: comma, semicolon or tab, whichever splits the header line into the most fields. In a file
  separated by semicolons or tabs a decimal comma (``12,5``) is read as a decimal point (a note says so).
- Time column: named ``time``, ``t``, ``timestamp``, ``time_s``, ``seconds`` ... or the column a map sends to
  ``time``. Its clock is read by the header's unit (``time [ms]``: s, ms, us, ns, min, h). Without a unit
  it is recognised, and a note says what was assumed: numbers of the size of a Unix time (1e9 to 4.2e9 s
  after 1970, i.e. 2001 to 2103) in s, ms, us or ns; dates and times (ISO 8601 such as
  ``2026-01-05T07:31:02.250`` or ``2026-01-05 07:31:02+01:00``, or Torque's ``18-Nov-2016 08:23:45.123``,
  read with ``pandas.to_datetime``). Other numbers without a unit are an error (seconds and milliseconds
  cannot be told apart). An absolute clock sets ``meta.start_time`` (UTC where the file gives a zone, the
  logger's local time where it does not).
- Time order: rows may share a time (a logger writing each channel on its own row at one instant); every
  channel keeps its samples, and a channel given twice at one time becomes the mean of the two
  (:func:`~calib.ingest.common.make_series` counts the merges). Time may step back by up to
  :data:`MAX_BACKSTEP_S` (clock jitter; the rows are sorted and a note counts them). A row whose time lies
  further back than that, or a lone row far ahead of its neighbours (a garbled digit), is damage: skipped
  and named in ``meta.damage``, or an error under ``strict``. Where the clock truly restarts, the longer
  run of rows is kept.
- Wide: every other column is a channel if its name (without the unit) is a canonical channel or a known
  alias, or if the column map names it. Its unit comes from the header bracket, the map, or the canonical
  name itself (``speed_mps`` is in m/s). A channel column with no unit is an error. A column whose name is
  not an accepted spelling but resembles exactly one channel whose unit fits (``coolant [degF]``) is read
  as that channel, with a warning in ``meta.notes``; one that resembles several, or none, is ignored (a
  warning names the accepted spellings of the look-alikes). ``iptm ingest --list-channels`` prints every
  accepted name.
- Long: detected from the header: a time column, a signal column (``signal``, ``channel``, ``name``,
  ``pid``), a ``value`` column and optionally a ``unit``/``units`` column, or columns mapped to ``time``,
  ``signal``, ``value``, ``unit``. A signal is read when its name is a canonical channel or alias or is a
  key of the column map; the unit is the row's unit cell, else the value column's header bracket
  (``value [km/h]``), the map, or the canonical name's own unit. A signal logged in several units is
  converted row by row (a note says so). Unknown signals are listed in a note.
- Intake air mass flow (a column or signal named ``maf``, ``mass_air_flow``...): when the log has no fuel
  rate, fuel is estimated from it at the stoichiometric ratio and labelled as an estimate
  (:func:`~calib.ingest.common.fuel_from_maf`).
- OBD-app exports (Torque Pro, Car Scanner) are recognised from their header and read with their own
  names, missing-reading marker and clock (:mod:`calib.ingest.obdcsv`).
- Cells: empty, ``NA``, ``NaN``, ``null`` or ``None`` is no sample; ``inf`` or a number beyond the float
  range (``1e400``) is a non-finite reading, dropped and counted with the channel's out-of-range values.
  Any other text in a cell that is read is damage (the row is skipped and named, or an error under
  ``strict``). A line with the wrong number of fields, or a last line with no line end (a cut file), is
  damage too. A line that repeats the header (a logger resuming into the same file) is skipped and
  counted in a note.
"""
from __future__ import annotations

import bisect
import csv
import gc
import io
import re
import unicodedata
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS, LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.ingest import obdcsv
from calib.ingest.canlog import MAX_BACKSTEP_S
from calib.ingest.common import (
    TIME_NAMES,
    aliases_of,
    canonical_name,
    fuel_from_maf,
    implied_unit,
    make_series,
    parse_target,
    sniff_text_lenient,
    split_spec,
    suggest_channel,
    to_channel_unit,
)
from calib.ingest.damage import Damage
from calib.ingest.obdcsv import MAF
from calib.units import UnitError, convert, parse_unit

#: Time-column names beyond :data:`calib.ingest.common.TIME_NAMES`, with the unit the name itself states.
_TIME_NAME_UNITS = {"time_s": "s", "time_sec": "s", "seconds": "s", "secs": "s", "sec": "s", "time_ms": "ms",
                    "timestamp_ms": "ms", "millis": "ms", "milliseconds": "ms", "time_us": "us",
                    "time_ns": "ns", "datetime": None, "date_time": None}
#: Names of an intake air mass flow column or signal (wide and long layouts).
_MAF_NAMES = {"maf", "mass_air_flow", "mass_air_flow_rate", "maf_air_flow_rate", "maf_rate", "maf_air_flow",
              "intake_air_flow"}
_SIGNAL_NAMES = {"signal", "channel", "name", "pid", "signal_name", "channel_name", "parameter"}
_VALUE_NAMES = {"value", "val"}
_UNIT_NAMES = {"unit", "units"}
#: Cell text meaning "no sample here" (compared lower-case).
_ABSENT = {"", "na", "n/a", "nan", "-nan", "+nan", "null", "none"}
#: A clock whose values, in seconds, lie here is a Unix time (2001-09-09 to 2103), not time since the start.
EPOCH_RANGE_S = (1e9, 4.2e9)
_EPOCH_UNITS = (("s", 1.0), ("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9))
#: Date-time layouts tried, in order, on a time column that is not numeric.
_DATETIME_FORMATS = (("ISO8601", "ISO 8601"), ("%d-%b-%Y %H:%M:%S.%f", "dd-Mon-yyyy hh:mm:ss.fff"),
                     ("%d-%b-%Y %H:%M:%S", "dd-Mon-yyyy hh:mm:ss"))
_ZONE = re.compile(r"(?:Z|[+-]\d\d:?\d\d|UTC|GMT)\s*$", re.IGNORECASE)
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+(?:[eE][+-]?\d+)?$")


def _key(name) -> str:
    return re.sub(r"[\s\-.]+", "_", str(name).strip()).lower()


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


def read_csv_streams(path, column_map: dict | None = None, strict: bool = False,
                     app: str | None = None) -> tuple[dict, LogMeta]:
    """Read a CSV log into streams.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    column_map : dict, optional
        ``{column header: "channel [unit]"}`` (or ``"channel"`` when the header carries the unit, or
        ``"time [unit]"`` for the time column). In a long file also ``{signal name: "channel [unit]"}`` and
        ``{column: "signal" | "value" | "unit"}``. Overrides header recognition for what it names.
    strict : bool
        Refuse the file at its first damaged data row. By default damaged rows (wrong number of fields,
        a cell that is not a number, a time far out of order, bytes that are not text, a cut last line)
        are skipped and listed in ``meta.damage``; the header must be intact.
    app : {"torque", "carscanner"}, optional
        Read with an OBD app's conventions (:mod:`calib.ingest.obdcsv`); recognised from the header when
        omitted.

    Returns
    -------
    (Streams, LogMeta)

    Raises
    ------
    LogFormatError
        Empty or binary file, no time column, a time column without a unit whose clock cannot be
        recognised, unknown unit, no readable row; under ``strict`` also the first damaged row (naming
        the line and, for a bad cell, the column).
    """
    # absurd clocks (1e308 s) overflow in the shifts and roundings; they end as non-finite samples, counted
    with np.errstate(over="ignore", invalid="ignore"):
        return _read_csv(path, column_map, strict, app)


def _read_csv(path, column_map, strict, app):
    head = sniff_text_lenient(path, "CSV").lstrip("\ufeff")
    comments, n_skip = _read_comments(head)
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format="csv")
    _meta_from_comments(comments, meta)
    table = _read_table(path, head, n_skip, strict)
    conv = obdcsv.APPS.get(app) if app else obdcsv.detect_app(table.header)
    if app and conv is None:
        raise LogFormatError(path, f"unknown OBD app {app!r}", hint=f"one of {', '.join(obdcsv.APPS)}")
    layout = _layout(table, dict(column_map or {}), conv, path)
    if conv is not None:
        meta.format = f"csv/{conv.name}"
        meta.notes.append(f"read as a {conv.title}")
        meta.notes.extend(conv.notes)
    elif layout.long:
        meta.format = "csv/long"
    meta.notes.extend(f"warning: {m}" for m in layout.warnings)
    meta.notes.extend(layout.notes)
    if table.repeated_headers:
        meta.notes.append(f"{len(table.repeated_headers)} line(s) repeating the header skipped (line "
                          + ", ".join(map(str, table.repeated_headers[:5]))
                          + (" ..." if len(table.repeated_headers) > 5 else "") + ")")
    if not table.rows and not table.broken:
        raise LogFormatError(path, "header but no data rows", f"line {table.header_line}")

    rows = _Rows(table, layout, conv, path)
    t = rows.time(meta)
    bad = rows.bad_rows()  # (row index, LogFormatError for strict, problem for damage)
    ok = np.ones(len(t), bool)
    for i, _err, _ in bad:
        ok[i] = False
    keep, back = _time_order(t, ok)
    events = list(bad)
    for i in np.flatnonzero(ok & ~keep):
        raw_prev = rows.time_cell(int(back[1][i])) if back[1][i] >= 0 else None
        if back[0][i] > 0:
            what = f"time goes backwards by {back[0][i]:.3f} s"
        else:
            what = f"time jumps ahead by {-back[0][i]:.3f} s and back"
        err = LogFormatError(path, f"{what}: {rows.time_cell(int(i))!r}"
                             + (f" after {raw_prev!r}" if raw_prev is not None else ""),
                             f"line {table.lines[i]}",
                             f"times may repeat, or step back by up to {MAX_BACKSTEP_S:g} s (jitter, sorted); "
                             "a larger step back is damage")
        events.append((int(i), err, f"time out of order: {what}"))
    if strict:
        first = min([(table.lines[i], e) for i, e, _ in events] + [(ln, LogFormatError(path, p, f"line {ln}"))
                                                                  for ln, p in table.broken],
                    key=lambda x: x[0], default=None)
        if first is not None:
            raise first[1]
    keep &= ok
    if not keep.any():
        raise LogFormatError(path, "no readable data row", f"after line {table.header_line}",
                             (events[0][1].problem if events else table.broken[0][1]) if events or table.broken
                             else None)
    t_kept = t[keep]
    n_jitter = int(np.sum(t_kept[1:] < np.maximum.accumulate(t_kept)[:-1]))
    if n_jitter:
        meta.notes.append(f"{n_jitter} row(s) stepped back in time by less than {MAX_BACKSTEP_S:g} s (clock "
                          "jitter) and were sorted")
    t0 = float(t_kept.min())
    if events or table.broken:
        meta.damage = _damage(path, table, events, t, keep, t0)
    rows.finish_clock(meta, t0)
    streams = rows.streams(t - t0, keep, meta)
    if not streams:
        raise LogFormatError(path, "no samples of any canonical channel in the log")
    return streams, meta


# ----------------------------------------------------------------------------------------------------
# the table: header and data rows as text, with their file lines
# ----------------------------------------------------------------------------------------------------
@dataclass
class _Table:
    header: list
    header_line: int
    sep: str
    rows: list = field(default_factory=list)
    lines: np.ndarray | None = None
    broken: list = field(default_factory=list)  # (line, problem): a line that is not a row of the table
    repeated_headers: list = field(default_factory=list)
    columns: list | None = None  # the rows' cells by column (built when first needed)


def _delimiter(line: str) -> str:
    best, n = ",", 1
    for sep in (",", ";", "\t"):
        try:
            k = len(next(csv.reader([line], delimiter=sep)))
        except (csv.Error, StopIteration):
            continue
        if k > n:
            best, n = sep, k
    return best


def _read_table(path, head: str, n_skip: int, strict: bool) -> _Table:
    lines = head.splitlines()
    if len(lines) <= n_skip:
        raise LogFormatError(path, "no header line (file holds only comments)")
    sep = _delimiter(lines[n_skip])
    try:
        return _split_rows(path, n_skip, sep, "strict")
    except UnicodeDecodeError:
        if strict:
            raise LogFormatError(path, "bytes that are not UTF-8 text in a CSV file", _first_bad_utf8_line(path),
                                 "re-export the log as UTF-8") from None
    # A damaged text log: undecodable bytes become U+FFFD and the cells they fall in are damage.
    return _split_rows(path, n_skip, sep, "replace")


def _split_rows(path, n_skip: int, sep: str, errors: str) -> _Table:
    # The collector would otherwise rescan the growing list of rows many times over.
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        return _split_rows_gc(path, n_skip, sep, errors)
    finally:
        if was_enabled:
            gc.enable()


def _split_rows_gc(path, n_skip: int, sep: str, errors: str) -> _Table:
    rows, lines, broken, repeated = [], [], [], []
    with open(path, "r", encoding="utf-8-sig", errors=errors, newline="") as fh:
        text = fh.read()
    # Each line is split on its own, so that a stray quote in a damaged line cannot swallow the lines after
    # it; a file without quotes needs no CSV parser at all.
    quoted = '"' in text
    header, header_line, ncol, trailing = None, n_skip + 1, 0, False
    for lineno, line in enumerate(io.StringIO(text, newline=""), 1):
        if lineno <= n_skip:
            continue
        try:
            if quoted:
                row = next(csv.reader((line,), delimiter=sep, skipinitialspace=True), [])
            else:
                row = line.rstrip("\r\n").split(sep)
        except csv.Error:
            if header is None:
                raise LogFormatError(path, "malformed CSV header", f"line {lineno}") from None
            broken.append((lineno, "malformed CSV row"))
            continue
        if header is None:
            header = [h.strip() for h in row]
            if not any(header):
                raise LogFormatError(path, "empty header line", f"line {lineno}")
            if len(header) < 2:
                raise LogFormatError(path, "fewer than two columns: need a time column and at least one channel",
                                     f"line {lineno}", "is the delimiter a comma, a semicolon or a tab?")
            ncol = len(header)
            trailing = header[-1] == ""
            header_line = lineno
            continue
        if not row or (len(row) == 1 and not row[0].strip()):
            continue  # a blank line
        if not line.endswith(("\n", "\r")):
            broken.append((lineno, "line cut short (no line end)"))
            continue
        if len(row) != ncol:
            # A trailing delimiter on the header or the rows but not both (Car Scanner writes one).
            if trailing and len(row) == ncol - 1:
                row = row + [""]
            elif len(row) == ncol + 1 and not row[-1].strip():
                row = row[:-1]
            else:
                broken.append((lineno, f"expected {ncol} fields, saw {len(row)}"))
                continue
        if row[0].strip() == header[0] and [c.strip() for c in row] == header:
            repeated.append(lineno)
            continue
        rows.append(row)
        lines.append(lineno)
    if header is None:
        raise LogFormatError(path, "no header line (file holds only comments)")
    return _Table(header=header, header_line=header_line, sep=sep, rows=rows,
                  lines=np.asarray(lines, dtype=np.int64), broken=broken, repeated_headers=repeated)


def _first_bad_utf8_line(path) -> str | None:
    with open(path, "rb") as fh:
        for lineno, raw in enumerate(fh, 1):
            try:
                raw.decode("utf-8")
            except UnicodeDecodeError:
                return f"line {lineno}"
    return None


# ----------------------------------------------------------------------------------------------------
# layout: which column is what
# ----------------------------------------------------------------------------------------------------
@dataclass
class _Layout:
    time_col: int
    time_unit: str | None
    long: bool = False
    channels: list = field(default_factory=list)  # wide: (column index, channel, unit)
    maf: tuple | None = None  # wide: (column index, unit)
    signal_col: int | None = None
    value_col: int | None = None
    unit_col: int | None = None
    value_unit: str | None = None
    signal_map: dict = field(default_factory=dict)  # long: signal name -> (channel or MAF, unit or None)
    absent: frozenset = frozenset()
    warnings: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def _unit_ok(unit: str) -> bool:
    try:
        parse_unit(unit)
        return True
    except UnitError:
        return False


def _norm_unit(unit: str | None, conv=None) -> str | None:
    """The unit as pint reads it: the app's spelling fixed, compatibility characters (``℃``) normalised."""
    unit = obdcsv.fix_unit(conv, unit)
    if unit is None or _unit_ok(unit):
        return unit
    alt = unicodedata.normalize("NFKC", unit)
    return alt if _unit_ok(alt) else unit


def _is_mass_flow(unit: str | None) -> bool:
    try:
        convert(1.0, unit, "g/s")
        return True
    except Exception:  # noqa: BLE001 - pint raises several types
        return False


def _role(target) -> str | None:
    """``"time"``/``"signal"``/``"value"``/``"unit"`` for a column-map value that names a column's role."""
    if not isinstance(target, str):
        return None
    name = split_spec(target)[0].strip().lower()
    if name in TIME_NAMES:
        return "time"
    return name if name in ("signal", "value", "unit") else None


def _layout(table: _Table, column_map: dict, conv, path) -> _Layout:
    header = table.header
    where0 = f"line {table.header_line}"
    split = (lambda c: obdcsv.split_app_column(c)[:2]) if conv is not None and conv.layout == "wide" else split_spec
    roles = {}
    for j, col in enumerate(header):
        if col in column_map and _role(column_map[col]):
            roles.setdefault(_role(column_map[col]), j)
    # The time column: mapped, the app's, or the first one named like time.
    time_col, time_unit = None, None
    if "time" in roles:
        time_col = roles["time"]
        time_unit = split_spec(column_map[header[time_col]])[1] or split_spec(header[time_col])[1]
    elif conv is not None and conv.time_column:
        for j, col in enumerate(header):
            if obdcsv.name_key(col) == conv.time_column:
                time_col = j
    if time_col is None:
        for j, col in enumerate(header):
            name, unit = split_spec(col)
            is_time, implied = _time_name(name)
            if is_time:
                time_col, time_unit = j, unit or implied
                break
    if time_col is None:
        raise LogFormatError(path, "no time column", where0, "name one 'time [s]' or map a column to 'time [unit]'")
    if time_unit is not None:
        try:
            if parse_unit(time_unit).dimensionality != parse_unit("s").dimensionality:
                raise LogFormatError(path, f"time column unit {time_unit!r} is not a time", where0)
        except UnitError:
            raise LogFormatError(path, f"unknown unit {time_unit!r}", f"{where0}, column {header[time_col]!r}") \
                from None
    lay = _Layout(time_col=time_col, time_unit=time_unit, absent=conv.absent if conv is not None else frozenset())

    keys = {j: _key(split_spec(c)[0]) for j, c in enumerate(header)}
    sig = roles.get("signal", next((j for j, k in keys.items() if k in _SIGNAL_NAMES and j != time_col), None))
    val = roles.get("value", next((j for j, k in keys.items() if k in _VALUE_NAMES and j != time_col), None))
    if sig is not None and val is not None and sig != val:
        unit_col = roles.get("unit", next((j for j, k in keys.items() if k in _UNIT_NAMES), None))
        _long_layout(lay, table, column_map, conv, sig, val, unit_col, path)
    else:
        _wide_layout(lay, table, column_map, conv, split, path)
    for j, col in enumerate(header):
        if col in column_map or j == time_col:
            continue
        if conv is not None and obdcsv.name_key(col) in conv.not_time:
            lay.notes.append(f"column {col!r} not used: {conv.not_time[obdcsv.name_key(col)]}")
    return lay


def _time_name(name) -> tuple[bool, str | None]:
    key = _key(name)
    if key in _TIME_NAME_UNITS:
        return True, _TIME_NAME_UNITS[key]
    return str(name).strip().lower() in TIME_NAMES, None


def _wide_layout(lay: _Layout, table: _Table, column_map: dict, conv, split, path) -> None:
    header = table.header
    where0 = f"line {table.header_line}"
    ignored, unnamed = [], []
    looks_like, matched = [], []
    fuzzy: list[tuple[int, str, str | None]] = []  # matched by resemblance only
    app_unused = []
    app_cols = []  # (answered by a named ECU, column, channel or MAF, unit)
    for j, col in enumerate(header):
        if j == lay.time_col:
            continue
        where = f"{where0}, column {col!r}"
        if col in column_map:
            target = column_map[col]
            if _role(target) is not None:
                continue
            name, unit = split(col)
            if isinstance(target, str) and _key(split_spec(target)[0]) in _MAF_NAMES:
                lay.maf = (j, _norm_unit(split_spec(target)[1] or unit, conv))
                continue
            ch, munit = parse_target(target, path, f"column map entry {col!r}")
            unit = munit or _norm_unit(unit, conv)
            if unit is None:
                raise LogFormatError(path, f"no unit for column {col!r}", where,
                                     "write 'name [unit]' in the header or give the unit in the column map")
            lay.channels.append((j, ch, unit))
            continue
        if not col:
            unnamed.append(j)
            continue
        name, unit = split(col)
        unit = _norm_unit(unit, conv)
        if conv is not None:
            # An app's columns are its own vocabulary: read what its table names, ignore the rest.
            if obdcsv.name_key(col) in conv.not_time:
                continue
            tgt, why = obdcsv.app_target(conv, name)
            if tgt is None:
                (app_unused.append(f"{col!r} ({why})") if why else ignored.append(col))
                continue
            ch, dunit = tgt
            unit = unit or dunit
            if unit is None:
                raise LogFormatError(path, f"no unit for column {col!r}", where, "map it with --map")
            app_cols.append((obdcsv.split_app_column(col)[2] is not None, j, ch, unit))
            continue
        if _time_name(name)[0]:
            ignored.append(col)
            continue
        if _key(name) in _MAF_NAMES and unit is not None and _is_mass_flow(unit):
            lay.maf = (j, unit)
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
            fuzzy.append((j, ch, unit))
            continue
        if unit is None:
            if name.strip() == ch and ch in CHANNELS:
                unit = implied_unit(ch)  # the canonical name carries its unit (speed_mps is m/s)
            else:
                raise LogFormatError(path, f"no unit for channel column {col!r}", where,
                                     "write 'name [unit]' in the header or give the unit in a column map")
        lay.channels.append((j, ch, unit))

    taken = {ch for _, ch, _ in lay.channels} | ({MAF} if lay.maf is not None else set())
    # Several ECUs answering one PID: the column without an ECU address (the app's default) is read.
    for _ecu, j, ch, unit in sorted(app_cols, key=lambda x: (x[0], x[1])):
        if ch in taken:
            app_unused.append(f"{header[j]!r} (the same PID from another ECU; one column per channel is read)")
            continue
        taken.add(ch)
        if ch == MAF:
            lay.maf = (j, unit)
        else:
            lay.channels.append((j, ch, unit))
    for j, ch, unit in fuzzy:
        col = header[j]
        if ch in taken or unit is None:  # an exact name wins; a look-alike needs its unit in the header
            ignored.append(col)
            looks_like.append(f"column {col!r} was not used: it looks like {ch} (accepted names: "
                              f"{', '.join(aliases_of(ch))})" + (", but has no unit" if unit is None else
                                                                 ", which another column already gives"))
            continue
        taken.add(ch)
        lay.channels.append((j, ch, unit))
        matched.append(f"column {col!r} read as {ch} (accepted names: {', '.join(aliases_of(ch))})")
    missing_map = [c for c in column_map if c not in header]
    if missing_map:
        raise LogFormatError(path, f"column map names column(s) not in the file: {', '.join(map(repr, missing_map))}",
                             where0)
    if not lay.channels and lay.maf is None:
        raise LogFormatError(path, "no column is a known channel", where0,
                             "name columns like 'speed [km/h]' or pass a column map")
    seen = {}
    for j, ch, _unit in lay.channels:
        if ch in seen:
            raise LogFormatError(path, f"columns {header[seen[ch]]!r} and {header[j]!r} both map to channel {ch}",
                                 where0, "drop one or map it elsewhere")
        seen[ch] = j
    if lay.maf is not None and not _is_mass_flow(lay.maf[1]):
        raise LogFormatError(path, f"air mass flow column {header[lay.maf[0]]!r} has no mass-flow unit "
                                   f"({lay.maf[1]!r})", where0, "write it like 'maf [g/s]'")
    for j in unnamed:
        if any(r[j].strip() for r in table.rows):
            ignored.append(f"(unnamed column {j + 1})")
    lay.warnings.extend(matched + looks_like)
    if app_unused:
        lay.notes.append("columns not used: " + "; ".join(app_unused))
    if ignored:
        lay.notes.append(f"ignored columns: {', '.join(ignored)}")


def _long_layout(lay: _Layout, table: _Table, column_map: dict, conv, sig: int, val: int, unit_col, path) -> None:
    header = table.header
    lay.long = True
    lay.signal_col, lay.value_col, lay.unit_col = sig, val, unit_col
    lay.value_unit = _norm_unit(split_spec(header[val])[1], conv)
    used = {lay.time_col, sig, val} | ({unit_col} if unit_col is not None else set())
    other = [c for j, c in enumerate(header) if j not in used and c and c not in column_map]
    if other:
        lay.notes.append(f"ignored columns: {', '.join(other)}")
    names = pd.unique(pd.Series([r[sig].strip() for r in table.rows], dtype=object)) if table.rows else []
    sig_map, unknown, app_unused, looks_like = {}, [], [], []
    for name in names:
        if not name:
            continue
        if name in column_map:
            target = column_map[name]
            if isinstance(target, str) and _key(split_spec(target)[0]) in _MAF_NAMES:
                sig_map[name] = (MAF, split_spec(target)[1])
            else:
                sig_map[name] = parse_target(target, path, f"column map entry {name!r}")
            continue
        if conv is not None:
            tgt, why = obdcsv.app_target(conv, name)
            if tgt is not None:
                sig_map[name] = tgt
            elif why:
                app_unused.append(f"{name!r} ({why})")
            else:
                unknown.append(name)
            continue
        if _key(name) in _MAF_NAMES:
            sig_map[name] = (MAF, None)
            continue
        ch = canonical_name(name)
        if ch is not None:
            sig_map[name] = (ch, None)
            continue
        unknown.append(name)
        _, cands = suggest_channel(name, None)
        if cands:
            looks_like.append(f"signal {name!r} was not used: it looks like " + " or ".join(
                f"{c} (accepted names: {', '.join(aliases_of(c))})" for c in cands) + "; map it with --map")
    in_file = set(header) | set(names)
    missing_map = [c for c in column_map if c not in in_file]
    if missing_map:
        raise LogFormatError(path, "column map names column(s) or signal(s) not in the file: "
                             + ", ".join(map(repr, missing_map)), f"line {table.header_line}")
    seen = {}
    for name, (ch, _u) in sig_map.items():
        if ch in seen:
            raise LogFormatError(path, f"signals {seen[ch]!r} and {name!r} both map to channel {ch}",
                                 f"line {table.header_line}", "map one of them elsewhere with --map")
        seen[ch] = name
    if not sig_map and table.rows:
        raise LogFormatError(path, "no signal is a known channel", f"column {header[sig]!r}",
                             "name signals like 'speed' or 'coolant_temp', or map them with --map "
                             f"(signals in the file: {', '.join(map(repr, list(names)[:12]))})")
    lay.signal_map = sig_map
    lay.warnings.extend(looks_like)
    if app_unused:
        lay.notes.append("signals not used: " + "; ".join(app_unused))
    if unknown:
        lay.notes.append(f"ignored signals: {', '.join(unknown[:20])}" + (" ..." if len(unknown) > 20 else ""))


# ----------------------------------------------------------------------------------------------------
# cells -> numbers, times, streams
# ----------------------------------------------------------------------------------------------------
def _cells(table: _Table, j: int) -> np.ndarray:
    """Column ``j`` as an object array of the cells' text (not stripped)."""
    if table.columns is None:
        table.columns = [np.asarray(c, dtype=object) for c in zip(*table.rows)] if table.rows else \
            [np.zeros(0, dtype=object)] * len(table.header)
    return table.columns[j]


def _stripped(cells: np.ndarray) -> pd.Series:
    return pd.Series(cells, dtype=object).str.strip()


def _numbers(cells: np.ndarray, absent_markers: frozenset, decimal_comma: bool):
    """Values, absent mask (no sample), bad mask (text that is not a number), and whether commas were decimal."""
    num = np.array(pd.to_numeric(pd.Series(cells, dtype=object), errors="coerce"), dtype=float)
    absent = np.asarray(cells == "", dtype=bool)
    bad = np.zeros(len(cells), bool)
    used_comma = False
    rest = np.flatnonzero(np.isnan(num) & ~absent)  # text pandas did not read as a number: look closer
    if len(rest):
        sub = _stripped(cells[rest])
        ab = (sub.str.lower().isin(_ABSENT) | sub.isin(absent_markers)).to_numpy()
        v = np.where(ab, np.nan, pd.to_numeric(sub, errors="coerce").to_numpy(dtype=float))
        nan_text = sub.str.lower().isin({"nan", "-nan", "+nan"}).to_numpy()
        b = np.isnan(v) & ~ab & ~nan_text
        if decimal_comma and b.any():
            cand = b & sub.str.match(_DECIMAL_COMMA).to_numpy()
            if cand.any():
                v[cand] = pd.to_numeric(sub[cand].str.replace(",", ".", regex=False), errors="coerce")
                b = np.isnan(v) & ~ab
                used_comma = True
        absent[rest] = ab
        num[rest] = v
        bad[rest] = b
    return num, absent, bad, used_comma


class _Rows:
    """The data rows of one table read by a layout: times, damaged rows, and the streams."""

    def __init__(self, table: _Table, lay: _Layout, conv, path):
        self.table, self.lay, self.conv, self.path = table, lay, conv, path
        self.decimal_comma = table.sep != ","
        self.comma_used = False
        self.t_cells = _stripped(_cells(table, lay.time_col))
        self.clock = None
        self._values = {}
        self._problems = []  # (row, column name, problem)

    def time_cell(self, i: int) -> str:
        return str(self.t_cells.iloc[i])

    def time(self, meta) -> np.ndarray:
        """Seconds from the clock's origin (NaN where the cell is not a time)."""
        t, bad, self.clock = _parse_time(self.t_cells, self.lay.time_unit, self.table.header[self.lay.time_col],
                                         self.decimal_comma, self.path, self.table)
        col = self.table.header[self.lay.time_col]
        for i in np.flatnonzero(bad):
            cell = self.time_cell(int(i))
            self._problems.append((int(i), col, "empty time cell" if not cell else
                                   f"not a time: {cell[:40]!r}"))
        if self.clock.get("note"):
            meta.notes.append(self.clock["note"])
        return t

    def _value_columns(self):
        lay = self.lay
        if lay.long:
            return [lay.value_col]
        return [j for j, _, _ in lay.channels] + ([lay.maf[0]] if lay.maf is not None else [])

    def bad_rows(self):
        """``[(row, LogFormatError, problem)]`` for rows with a cell that cannot be read (time or value)."""
        lay = self.lay
        if lay.long:
            sig = _stripped(_cells(self.table, lay.signal_col))
            read = sig.isin(list(lay.signal_map)).to_numpy()
            self._signals = sig
        for j in self._value_columns():
            num, absent, bad, comma = _numbers(_cells(self.table, j), lay.absent, self.decimal_comma)
            self.comma_used |= comma
            if lay.long:
                bad &= read
            self._values[j] = (num, absent)
            col = self.table.header[j]
            for i in np.flatnonzero(bad):
                cell = str(self.table.rows[i][j]).strip()
                self._problems.append((int(i), col, f"not a number: {cell[:40]!r}"))
        out, seen = [], set()
        for i, col, problem in sorted(self._problems, key=lambda x: x[0]):
            if i in seen:
                continue
            seen.add(i)
            ln = int(self.table.lines[i])
            out.append((i, LogFormatError(self.path, problem, f"line {ln}, column {col!r}"),
                        f"{problem.split(':')[0]} (column {col!r})"))
        return out

    def finish_clock(self, meta, t0: float) -> None:
        clock = self.clock
        if clock["origin"] is not None:
            start = clock["origin"] + pd.Timedelta(seconds=t0)
            meta.start_time = start.isoformat()
        else:
            shift = clock["ref_s"] + t0
            if shift != 0.0:
                meta.notes.append(f"time shifted by {-shift:g} s so the log starts at 0")
        if self.comma_used:
            meta.notes.append("decimal commas read as decimal points")

    def streams(self, t: np.ndarray, keep: np.ndarray, meta) -> dict:
        lay, path = self.lay, self.path
        streams = {}
        if lay.long:
            return self._long_streams(t, keep, meta)
        for j, ch, unit in lay.channels:
            col = self.table.header[j]
            num, absent = self._values[j]
            v = to_channel_unit(num[keep], unit, ch, path, f"column {col!r}")
            s = make_series(t[keep], v, ch, meta=meta, absent=absent[keep])
            if len(s):
                streams[ch] = s
            meta.channel_sources[ch] = col
            meta.original_units[ch] = unit
        if lay.maf is not None:
            j, unit = lay.maf
            self._maf(streams, t[keep], self._values[j][0][keep], self._values[j][1][keep], unit,
                      self.table.header[j], meta)
        return streams

    def _maf(self, streams, t, maf, absent, unit, source, meta) -> None:
        if "fuel_rate_g_per_s" in meta.channel_sources:
            meta.notes.append(f"air mass flow {source!r} not used for fuel: the log has a fuel rate")
            return
        there = ~absent
        g_s = np.asarray(convert(maf[there], unit, "g/s"), dtype=float)
        s = fuel_from_maf(t[there], g_s, meta, source)
        meta.original_units.setdefault("fuel_rate_g_per_s", f"{unit} (air)")
        if len(s):
            streams["fuel_rate_g_per_s"] = s

    def _long_streams(self, t, keep, meta) -> dict:
        lay, path, table = self.lay, self.path, self.table
        num, absent = self._values[lay.value_col]
        sig = self._signals
        units = _stripped(_cells(table, lay.unit_col)) if lay.unit_col is not None else None
        streams, maf = {}, None
        for name, (ch, map_unit) in lay.signal_map.items():
            rows = np.flatnonzero(keep & (sig == name).to_numpy())
            row_units = (units.iloc[rows] if units is not None
                         else pd.Series([""] * len(rows), dtype=object, index=rows))
            fallback = lay.value_unit or map_unit
            if ch != MAF and fallback is None and name.strip() == ch:
                fallback = implied_unit(ch)
            if self.conv is not None and fallback is None:
                tgt = obdcsv.app_target(self.conv, name)[0]
                fallback = tgt[1] if tgt is not None else None
            if map_unit is not None:
                row_units = pd.Series([map_unit] * len(rows), dtype=object, index=rows)  # the user's map rules
            elif fallback is not None:
                row_units = row_units.where(row_units != "", fallback)
            tt, vv, aa, seen_units = [], [], [], []
            for u in pd.unique(row_units.astype(object)):
                sel = rows[(row_units == u).to_numpy()]
                if u == "":
                    first = int(table.lines[sel[0]])
                    raise LogFormatError(path, f"no unit for signal {name!r}", f"line {first}",
                                         "give a unit column, write 'value [unit]' in the header, or map the "
                                         "signal with --map 'name=channel [unit]'")
                unit = _norm_unit(u, self.conv)
                if ch == MAF:
                    if not _is_mass_flow(unit):
                        raise LogFormatError(path, f"air mass flow {name!r} in {u!r}, not a mass flow",
                                             f"line {int(table.lines[sel[0]])}")
                    vals = num[sel]
                else:
                    vals = to_channel_unit(num[sel], unit, ch, path,
                                           f"signal {name!r} (line {int(table.lines[sel[0]])})")
                if ch == MAF:
                    vals = np.asarray(convert(vals, unit, "g/s"), dtype=float)
                tt.append(t[sel])
                vv.append(vals)
                aa.append(absent[sel])
                seen_units.append(u)
            if not tt:
                continue
            tt, vv, aa = np.concatenate(tt), np.concatenate(vv), np.concatenate(aa)
            if len(seen_units) > 1:
                meta.notes.append(f"signal {name!r} is logged in {len(seen_units)} units "
                                  f"({', '.join(map(str, seen_units))}): each sample converted by its own unit")
            if ch == MAF:
                maf = (tt, vv, aa, name)
                continue
            s = make_series(tt, vv, ch, meta=meta, absent=aa)
            if len(s):
                streams[ch] = s
            meta.channel_sources[ch] = name
            meta.original_units[ch] = str(seen_units[0])
        if maf is not None:
            self._maf(streams, maf[0], maf[1], maf[2], "g/s", maf[3], meta)
        return streams


def _parse_time(cells: pd.Series, unit: str | None, col: str, decimal_comma: bool, path, table):
    """``(t, bad, clock)``: seconds from the clock's origin, unreadable cells, and the clock's description.

    ``clock["origin"]`` is the absolute time (pandas Timestamp) of ``t == 0`` for an absolute clock, else
    None and ``clock["ref_s"]`` is the file's time value (s) of ``t == 0``.
    """
    n = len(cells)
    if n == 0:
        return np.zeros(0), np.zeros(0, bool), {"origin": None, "ref_s": 0.0, "note": None}
    num, absent, bad_num, _ = _numbers(cells.to_numpy(dtype=object), frozenset(), decimal_comma)
    present = ~absent
    sample = cells[present].head(200)
    n_num = int((~np.isnan(num[present][:200])).sum())
    if n_num * 2 >= max(len(sample), 1):
        return _numeric_time(cells, num, absent | bad_num | ~np.isfinite(num), unit, col, path, table)
    return _datetime_time(cells, sample, col, path, table)


def _numeric_time(cells, num, bad, unit, col, path, table):
    good = ~bad
    if not good.any():
        return np.full(len(num), np.nan), bad, {"origin": None, "ref_s": 0.0, "note": None}
    note = None
    epoch = False
    if unit is None:
        lo, hi = np.min(num[good]), np.max(num[good])
        for u, f in _EPOCH_UNITS:
            if EPOCH_RANGE_S[0] <= lo * f and hi * f <= EPOCH_RANGE_S[1]:
                unit, epoch = u, True
                note = (f"time column {col!r} has no unit; its values ({cells[good].iloc[0]}) are read as Unix "
                        f"time in {u} (UTC)")
                break
        if unit is None:
            raise LogFormatError(path, f"no unit for time column {col!r}", f"line {table.header_line}",
                                 "write e.g. 'time [s]' or 'time [ms]' (Unix times and dates are recognised "
                                 "without one)")
    factor = float(convert(1.0, unit, "s"))
    txt = cells[good]
    if txt.str.fullmatch(r"[+-]?\d{1,18}").all():
        # Integer clocks (ms, us, ns since 1970) are differenced exactly before they become floats.
        ints = np.zeros(len(num), dtype=np.int64)
        ints[good] = txt.astype(np.int64).to_numpy()
        ref = int(ints[good].min())
        t = (ints - ref).astype(float) * factor
        ref_s = ref * factor
    else:
        ref = float(np.min(num[good]))
        t = (num - ref) * factor
        ref_s = ref * factor
    t[bad] = np.nan
    if not epoch and EPOCH_RANGE_S[0] <= ref_s <= EPOCH_RANGE_S[1]:
        epoch = True
        note = f"time column {col!r} read as Unix time in {unit} (UTC)"
    if epoch:
        exact = isinstance(ref, int) and unit in ("s", "ms", "us", "ns")
        origin = pd.Timestamp(ref, unit=unit, tz="UTC") if exact else pd.Timestamp(ref_s, unit="s", tz="UTC")
        return t, bad, {"origin": origin, "ref_s": ref_s, "note": note}
    return t, bad, {"origin": None, "ref_s": ref_s, "note": note}


def _datetime_time(cells, sample, col, path, table):
    fmt, desc = None, None
    for f, d in _DATETIME_FORMATS:
        ok = pd.to_datetime(sample, format=f, errors="coerce", utc=True)
        if ok.notna().sum() * 2 >= max(len(sample), 1):
            fmt, desc = f, d
            break
    if fmt is None:
        first = next((c for c in sample if c), "")
        raise LogFormatError(path, f"time column {col!r} holds neither numbers nor dates: {first[:40]!r}",
                             f"line {table.header_line}",
                             "write seconds with a unit ('time [s]') or ISO 8601 dates (2026-01-05T07:31:02.250)")
    aware = bool(sample.str.contains(_ZONE).any())
    empty = (cells == "").to_numpy()
    dt = pd.to_datetime(cells.where(~empty, None), format=fmt, errors="coerce", utc=aware)
    bad = dt.isna().to_numpy()
    good = ~bad
    if not good.any():
        return np.full(len(cells), np.nan), bad, {"origin": None, "ref_s": 0.0, "note": None}
    origin = dt[good].min()
    t = np.array((dt - origin).dt.total_seconds(), dtype=float)
    t[bad] = np.nan
    zone = ("with a time zone: start time in UTC" if aware else
            "without a time zone: start time is the logger's local time")
    note = f"time column {col!r} read as dates and times ({desc}), {zone}"
    return t, bad, {"origin": origin, "ref_s": 0.0, "note": note}


def _longest_nondecreasing(t: np.ndarray) -> np.ndarray:
    """Mask of a longest non-decreasing subsequence of ``t`` (O(n log n))."""
    n = len(t)
    tails, tails_idx = [], []
    prev = np.full(n, -1, dtype=np.int64)
    for i, x in enumerate(t.tolist()):
        k = bisect.bisect_right(tails, x)
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


def _time_order(t: np.ndarray, ok: np.ndarray):
    """Rows whose times fit the log's order, and for the others how far back they step.

    Returns ``(keep, (step, prev_row))``: ``step[i] > 0`` is how far row ``i`` lies behind the latest earlier
    kept time, ``step[i] < 0`` how far it lies ahead of the next kept one; ``prev_row[i]`` the earlier row it
    is compared with (-1: none).
    """
    n = len(t)
    idx = np.flatnonzero(ok)
    keep = np.zeros(n, bool)
    step = np.zeros(n)
    prev_row = np.full(n, -1, dtype=np.int64)
    if len(idx) == 0:
        return keep, (step, prev_row)
    tt = t[idx]
    runmax = np.maximum.accumulate(tt)
    if np.all(tt[1:] >= runmax[:-1] - MAX_BACKSTEP_S):
        keep[idx] = True
        return keep, (step, prev_row)
    lis = _longest_nondecreasing(tt)
    before = np.maximum.accumulate(np.where(lis, tt, -np.inf))
    prev_max = np.concatenate([[-np.inf], before[:-1]])
    after = np.minimum.accumulate(np.where(lis, tt, np.inf)[::-1])[::-1]
    next_min = np.concatenate([after[1:], [np.inf]])
    fits = lis | ((tt >= prev_max - MAX_BACKSTEP_S) & (tt <= next_min + MAX_BACKSTEP_S))
    keep[idx] = fits
    last_lis = np.maximum.accumulate(np.where(lis, np.arange(len(tt)), -1))
    prev_lis = np.concatenate([[-1], last_lis[:-1]])
    for k in np.flatnonzero(~fits):
        i = idx[k]
        if tt[k] < prev_max[k] - MAX_BACKSTEP_S:
            step[i] = prev_max[k] - tt[k]
        else:
            step[i] = -(tt[k] - next_min[k])
        prev_row[i] = idx[prev_lis[k]] if prev_lis[k] >= 0 else -1
    return keep, (step, prev_row)


def _damage(path, table: _Table, events, t: np.ndarray, keep: np.ndarray, t0: float) -> dict:
    """``meta.damage``: every skipped line in file order, with the stretch of log time it leaves empty."""
    dmg = Damage(path, strict=False, unit="line")
    items = [(ln, 1, LogFormatError(path, p, f"line {ln}")) for ln, p in table.broken]
    items += [(int(table.lines[i]), 1, LogFormatError(path, problem, f"line {int(table.lines[i])}"))
              for i, _err, problem in events]
    kept = np.flatnonzero(keep)
    items += [(int(ln), 0, float(tt)) for ln, tt in zip(table.lines[kept], t[kept])]
    items.sort(key=lambda x: (x[0], x[1]))
    t_last = -np.inf
    for _ln, is_bad, x in items:
        if is_bad:
            dmg.bad(x, t_last)
        else:
            dmg.good(x)
            t_last = max(t_last, x)
    t_end = float(np.max(t[keep]))
    return dmg.finish(t0, t_end)


def sniff_is_csv(path) -> bool:
    """Heuristic used by format detection: text whose first non-comment line has a comma, semicolon or tab."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    if b"\x00" in head:
        return False
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff")
    for line in io.StringIO(text):
        if line.startswith("#") or not line.strip():
            continue
        try:
            return len(next(csv.reader([line], delimiter=_delimiter(line)))) >= 2
        except csv.Error:
            return False
    return False


__all__ = ["read_csv_streams", "sniff_is_csv", "MAX_BACKSTEP_S", "EPOCH_RANGE_S"]
