"""Channel-map profiles for the formats real test data come in.

- ``d3``: Argonne National Laboratory's Downloadable Dynamometer Database (D3) test files
  (``NNNNNNNN Test Data.txt``): tab-separated, 10 Hz, one test per file, column names such as
  ``Time[s]_RawFacilities``, ``Dyno_Spd[mph]``, ``Eng_FuelFlow_Direct2[gps]``,
  ``HVBatt_SOC_high_precision_PCAN__per``, ``engine_coolant_temp_PCAN__C``, ``Cabin_Temp[C]``,
  ``Cell_Temp[C]`` (the test-cell air, i.e. the car's ambient). Other D3 channels (engine speed, battery
  current and voltage) are named differently from test to test: add them with ``--map``. Samples before the test start carry
  negative times; they are kept and the log is shifted to start at 0 (a note says so).
  ``HVAC_Power_Hioki_P3[W]`` is the electrical power the HVAC draws (blower, compressor), not heat taken
  from the coolant, so it is recognised but not mapped (a note says so).
- ``ved``: the Vehicle Energy Dataset's dynamic CSV (one file holds many vehicles and trips):
  ``DayNum``, ``VehId``, ``Trip``, ``Timestamp(ms)`` (from the trip's start), ``Vehicle Speed[km/h]``,
  ``OAT[DegC]``, ``Fuel Rate[L/hr]``, ``Heater Power[Watts]``, ``HV Battery Current[A]``,
  ``HV Battery SOC[%]``, ``HV Battery Voltage[V]``, ``Engine RPM[RPM]``; irregular, about 1 Hz, with gaps.
  One (vehicle, trip) is read at a time: ``vehicle=``/``trip=`` (``--vehicle``/``--trip``); a file with
  one trip needs neither. Fuel in L/h becomes g/s through the gasoline density of :mod:`calib.units`. A
  trip without fuel-rate samples (VED logs no fuel rate for many of its cars) gets a fuel rate estimated
  from ``MAF[g/sec]`` at the stoichiometric ratio, labelled as an estimate
  (:func:`calib.ingest.common.fuel_from_maf`).
  ``Heater Power`` in VED is the electric cabin heater of plug-in vehicles; it is read as heat delivered
  to the cabin (a note says so).

:func:`detect_profile` recognises both from their header line, so ``iptm ingest`` picks them up without
``--profile`` when the file is unambiguous. A user column map (``--map``) overrides single columns.

Time order: a D3 file's time may step back by up to :data:`~calib.ingest.csvlog.MAX_BACKSTEP_S` (jitter,
sorted); a larger step back is an error naming the line. Empty cells are no sample; ``inf`` is a
non-finite reading, dropped and counted in ``meta.channel_counts``.

The OBD-app exports (``torque``, ``carscanner``, :mod:`calib.ingest.obdcsv`) are read by the CSV reader,
which recognises them from their header; :func:`read_profile_streams` accepts their names too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from calib.drivelog import LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.ingest.common import fuel_from_maf, make_series, parse_target, to_channel_unit
from calib.ingest.csvlog import MAX_BACKSTEP_S
from calib.ingest.obdcsv import APPS


@dataclass(frozen=True)
class Profile:
    """How one file format maps onto canonical channels."""

    name: str
    title: str
    delimiter: str
    time_column: str
    time_unit: str
    columns: dict  # column -> "channel [unit]"
    signature: tuple  # columns whose presence identifies the format
    unmapped: dict = field(default_factory=dict)  # known columns deliberately not read -> why
    vehicle_column: str | None = None
    trip_column: str | None = None
    notes: tuple = ()
    maf_column: tuple | None = None  # (column, unit) of the intake air mass flow: fuel estimate without fuel


D3 = Profile(
    name="d3", title="Argonne D3 dynamometer test file", delimiter="\t",
    time_column="Time[s]_RawFacilities", time_unit="s",
    columns={
        "Dyno_Spd[mph]": "speed_mps [mph]",
        "Eng_FuelFlow_Direct2[gps]": "fuel_rate_g_per_s [g/s]",
        "HVBatt_SOC_high_precision_PCAN__per": "soc [%]",
        "engine_coolant_temp_PCAN__C": "coolant_temp_degC [degC]",
        "Cabin_Temp[C]": "cabin_temp_degC [degC]",
        "Cell_Temp[C]": "ambient_temp_degC [degC]",
    },
    signature=("Time[s]_RawFacilities", "Dyno_Spd[mph]"),
    unmapped={"HVAC_Power_Hioki_P3[W]": "electrical power drawn by the HVAC (blower, compressor), not heat taken "
                                        "from the coolant; not used as heater_power_W"},
    notes=("Cell_Temp[C] (test-cell air) read as the ambient temperature",),
)

VED = Profile(
    name="ved", title="Vehicle Energy Dataset dynamic CSV", delimiter=",",
    time_column="Timestamp(ms)", time_unit="ms",
    columns={
        "Vehicle Speed[km/h]": "speed_mps [km/h]",
        "OAT[DegC]": "ambient_temp_degC [degC]",
        "Fuel Rate[L/hr]": "fuel_rate_g_per_s [L/h]",
        "Heater Power[Watts]": "heater_power_W [W]",
        "HV Battery Current[A]": "bat_current_A [A]",
        "HV Battery SOC[%]": "soc [%]",
        "HV Battery Voltage[V]": "bat_voltage_V [V]",
        "Engine RPM[RPM]": "engine_speed_rpm [rpm]",
    },
    signature=("VehId", "Trip", "Timestamp(ms)"),
    unmapped={"DayNum": "day number of the trip (selection and start time only)",
              "VehId": "vehicle id (selection)", "Trip": "trip id (selection)"},
    vehicle_column="VehId", trip_column="Trip", maf_column=("MAF[g/sec]", "g/s"),
    notes=("Heater Power[Watts] (electric cabin heater) read as heat delivered to the cabin",
           "HV Battery Current[A] read with + = discharge as logged; check the sign on a known charge event"),
)

PROFILES: dict[str, Profile] = {"d3": D3, "ved": VED}


def _header(path) -> list[str] | None:
    """The first line of a text file split on tab or comma (None if unreadable/binary)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError:
        return None
    if not head or b"\x00" in head:
        return None
    line = head.decode("utf-8", errors="replace").splitlines()[0] if head.strip() else ""
    line = line.lstrip("\ufeff")
    sep = "\t" if line.count("\t") > line.count(",") else ","
    return [c.strip().strip('"') for c in line.split(sep)]


def detect_profile(path) -> str | None:
    """The profile whose signature columns are all in the file's header, or None (none or ambiguous)."""
    cols = _header(path)
    if not cols:
        return None
    hits = [n for n, p in PROFILES.items() if all(c in cols for c in p.signature)]
    return hits[0] if len(hits) == 1 else None


def _numeric(s: pd.Series, path, col: str, first_line: int) -> np.ndarray:
    return _cells(s, path, col, first_line)[0]


def _cells(s: pd.Series, path, col: str, first_line: int) -> tuple[np.ndarray, np.ndarray]:
    """Values and the mask of empty cells (no sample); ``inf`` is a (non-finite) reading."""
    txt = s.astype(str).str.strip()
    empty = txt.isin(["", "nan", "NaN", "NA", "null", "None"]).to_numpy()
    num = np.array(pd.to_numeric(txt.where(~empty, None), errors="coerce"), dtype=float)
    bad = np.flatnonzero(np.isnan(num) & ~empty)
    if len(bad):
        i = int(bad[0])
        raise LogFormatError(path, f"not a number: {txt.iloc[i][:40]!r}", f"line {first_line + i}, column {col!r}")
    return num, empty


def _pick(values: pd.Series, want, what: str, path, flag: str):
    """Rows whose ``values`` equal ``want`` (compared as text and as a number)."""
    txt = values.astype(str).str.strip()
    w = str(want).strip()
    mask = txt == w
    if not mask.any():
        try:
            mask = pd.to_numeric(txt, errors="coerce") == float(w)
        except ValueError:
            pass
    if not mask.any():
        avail = sorted(set(txt), key=lambda x: (len(x), x))
        raise LogFormatError(path, f"no {what} {w!r} in the file", hint=f"{flag} one of: {', '.join(avail[:20])}"
                             + (" ..." if len(avail) > 20 else ""))
    return mask.to_numpy()


def read_profile_streams(path, profile: str | Profile, *, column_map: dict | None = None,
                         vehicle=None, trip=None, strict: bool = False) -> tuple[dict, LogMeta]:
    """Read a file in a profile's format into canonical streams.

    Parameters
    ----------
    path : str or Path
    profile : "d3", "ved", "torque", "carscanner" or a :class:`Profile`
    column_map : dict, optional
        ``{column: "channel [unit]"}`` overriding or adding to the profile's map.
    vehicle, trip : optional
        VED: the vehicle and trip to read (needed when the file holds more than one).

    Returns
    -------
    (Streams, LogMeta)

    Raises
    ------
    LogFormatError
        Not the profile's format (signature columns missing), no time column, non-numeric cells, time
        going backwards, no matching or an ambiguous vehicle/trip selection.
    """
    if isinstance(profile, str) and profile in APPS:
        from calib.ingest.csvlog import read_csv_streams

        return read_csv_streams(path, column_map=column_map, app=profile, strict=strict)
    prof = PROFILES.get(profile) if isinstance(profile, str) else profile
    if prof is None:
        raise LogFormatError(path, f"unknown profile {profile!r}",
                             hint=f"one of {', '.join(list(PROFILES) + list(APPS))}")
    p = Path(path)
    if not p.exists():
        raise LogFormatError(path, "no such file")
    if p.stat().st_size == 0:
        raise LogFormatError(path, "empty file")
    try:
        df = pd.read_csv(p, sep=prof.delimiter, dtype=str, keep_default_na=False, encoding="utf-8-sig",
                         on_bad_lines="error", engine="c")
    except pd.errors.ParserError as exc:
        raise LogFormatError(path, f"malformed {prof.title}: {str(exc).strip().splitlines()[-1]}") from None
    except UnicodeDecodeError as exc:
        raise LogFormatError(path, f"binary file, not a {prof.title} (byte {exc.start} is not UTF-8)") from None
    except pd.errors.EmptyDataError:
        raise LogFormatError(path, "empty file") from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in prof.signature if c not in df.columns]
    if missing:
        raise LogFormatError(path, f"not a {prof.title}: column(s) {', '.join(map(repr, missing))} missing",
                             "line 1", "check --profile, or pass a column map with --map")
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format=f"csv/{prof.name}")
    meta.notes.append(f"read with the {prof.name} profile ({prof.title})")
    first_line = 2
    rows = np.ones(len(df), bool)
    if prof.vehicle_column:
        vcol, tcol = prof.vehicle_column, prof.trip_column
        if vehicle is not None:
            rows &= _pick(df[vcol], vehicle, "vehicle", path, "--vehicle")
        if trip is not None:
            rows &= _pick(df[tcol], trip, "trip", path, "--trip")
        if not rows.any():
            raise LogFormatError(path, f"no rows for vehicle {vehicle} trip {trip}")
        pairs = df.loc[rows, [vcol, tcol]].drop_duplicates()
        if len(pairs) > 1:
            listing = ", ".join(f"{a}/{b}" for a, b in pairs.head(12).itertuples(index=False))
            raise LogFormatError(path, f"{len(pairs)} vehicle/trip pairs in the file; one log is one trip",
                                 hint=f"select with --vehicle and --trip (vehicle/trip: {listing}"
                                      + (" ..." if len(pairs) > 12 else "") + ")")
        veh, tr = pairs.iloc[0]
        meta.vehicle_id = f"{veh}"
        meta.notes.append(f"vehicle {veh}, trip {tr}")
        if "DayNum" in df.columns:
            day = _numeric(df.loc[rows, "DayNum"], path, "DayNum", first_line)
            if np.isfinite(day).any():
                meta.notes.append(f"DayNum at start {np.nanmin(day):.6f}")
    idx = np.flatnonzero(rows)
    sub = df.iloc[idx]
    if prof.time_column not in sub.columns:
        raise LogFormatError(path, f"no time column {prof.time_column!r}", "line 1")
    t_raw = _numeric(sub[prof.time_column], path, prof.time_column, first_line)
    ok_t = np.isfinite(t_raw)
    t = to_channel_unit_time(t_raw, prof.time_unit)
    if prof.vehicle_column:
        # VED rows of a trip are in time order in the published files; sort in case a file was merged
        order = np.argsort(np.where(ok_t, t, np.inf), kind="stable")
    else:
        order = np.arange(len(t))
        tt = t[ok_t]
        back = np.concatenate([[0.0], np.maximum.accumulate(tt)[:-1] - tt[1:]]) if len(tt) else tt
        if np.any(back > MAX_BACKSTEP_S):
            k = int(np.flatnonzero(back > MAX_BACKSTEP_S)[0])
            j = int(np.flatnonzero(ok_t)[k])
            raise LogFormatError(path, f"time goes backwards by {back[k]:.3f} s: {t_raw[j]!r}",
                                 f"line {first_line + int(idx[j])}",
                                 f"times may repeat, or step back by up to {MAX_BACKSTEP_S:g} s (jitter, sorted)")
    t, ok_t, sub = t[order], ok_t[order], sub.iloc[order]
    if not ok_t.any():
        raise LogFormatError(path, "no time values", f"column {prof.time_column!r}")
    t0 = float(np.nanmin(t))
    t = t - t0
    if t0 != 0.0:
        meta.notes.append(f"time shifted by {-t0:g} s so the log starts at 0")
    cmap = dict(prof.columns)
    cmap.update(column_map or {})
    streams, ignored, seen = {}, [], {}
    for col in sub.columns:
        if col == prof.time_column:
            continue
        if prof.maf_column and col == prof.maf_column[0] and col not in cmap:
            continue
        if col not in cmap:
            if col in prof.unmapped:
                meta.notes.append(f"column {col!r} not used: {prof.unmapped[col]}")
            else:
                ignored.append(col)
            continue
        ch, unit = parse_target(cmap[col], path, f"{prof.name} profile column {col!r}")
        if unit is None:
            raise LogFormatError(path, f"no unit for column {col!r} in the column map", "line 1")
        if ch in seen:
            raise LogFormatError(path, f"columns {seen[ch]!r} and {col!r} both map to channel {ch}", "line 1")
        seen[ch] = col
        v, empty = _cells(sub[col], path, col, first_line)
        v = to_channel_unit(v, unit, ch, path, f"column {col!r}")
        s = make_series(t[ok_t], v[ok_t], ch, meta=meta, absent=empty[ok_t])
        if len(s):
            streams[ch] = s
            meta.channel_sources[ch] = col
            meta.original_units[ch] = unit
    if prof.maf_column and prof.maf_column[0] in sub.columns and "fuel_rate_g_per_s" not in streams:
        col, unit = prof.maf_column
        maf, empty = _cells(sub[col], path, col, first_line)
        there = ok_t & ~empty
        if there.any():
            fuel = fuel_from_maf(t[there], to_channel_unit_time(maf[there], unit, "g/s"), meta, col)
            if len(fuel):
                streams["fuel_rate_g_per_s"] = fuel
    elif prof.maf_column and prof.maf_column[0] in sub.columns:
        meta.notes.append(f"column {prof.maf_column[0]!r} not used: the log has a fuel rate")
    absent = [c for c in cmap if c not in sub.columns and c not in (column_map or {})]
    if absent:
        meta.notes.append(f"profile columns not in this file: {', '.join(absent)}")
    used = {meta.channel_sources.get(ch) for ch in streams}
    meta.notes.extend(n for n in prof.notes if any(c in n for c in used))
    if ignored:
        meta.notes.append(f"ignored columns: {', '.join(ignored)}")
    if not streams:
        raise LogFormatError(path, f"no samples of any canonical channel ({prof.title})")
    return streams, meta


def to_channel_unit_time(values, unit: str, to: str = "s") -> np.ndarray:
    """``values`` in ``unit`` converted to ``to`` (seconds by default)."""
    from calib.units import convert

    return np.asarray(convert(np.asarray(values, float), unit, to), dtype=float)


__all__ = ["Profile", "PROFILES", "D3", "VED", "detect_profile", "read_profile_streams"]
