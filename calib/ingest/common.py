"""Helpers shared by the readers: channel names, ``"channel [unit]"`` specs, time checks, file sniffing."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS, RANGES
from calib.errors import LogFormatError
from calib.units import UnitError, convert, parse_unit

# Base names a human header uses for each channel (the canonical name without its unit suffix), plus a
# few common synonyms. Matching is case-insensitive and ignores spaces/dashes.
#: Header base names of the time column (CSV).
TIME_NAMES = {"time", "t", "timestamp", "time_s", "times", "time_sec", "elapsed"}

CHANNEL_ALIASES: dict[str, str] = {}
for _ch in CHANNELS:
    CHANNEL_ALIASES[_ch] = _ch
_BASE = {
    "speed": "speed_mps", "vehicle_speed": "speed_mps", "velocity": "speed_mps",
    "bat_current": "bat_current_A", "battery_current": "bat_current_A", "current": "bat_current_A",
    "bat_voltage": "bat_voltage_V", "battery_voltage": "bat_voltage_V", "voltage": "bat_voltage_V",
    "soc": "soc", "state_of_charge": "soc",
    "bat_temp": "bat_temp_degC", "battery_temp": "bat_temp_degC", "battery_temperature": "bat_temp_degC",
    "engine_speed": "engine_speed_rpm", "rpm": "engine_speed_rpm", "engine_rpm": "engine_speed_rpm",
    "engine_torque": "engine_torque_Nm", "torque": "engine_torque_Nm",
    "engine_power": "engine_power_W", "bat_power": "bat_power_W", "battery_power": "bat_power_W",
    "fuel_rate": "fuel_rate_g_per_s", "fuel_flow": "fuel_rate_g_per_s", "fuel": "fuel_rate_g_per_s",
    "coolant_temp": "coolant_temp_degC", "coolant_temperature": "coolant_temp_degC", "ect": "coolant_temp_degC",
    "coolant": "coolant_temp_degC", "engine_coolant_temp": "coolant_temp_degC",
    "bay_temp": "bay_temp_degC", "engine_bay_temp": "bay_temp_degC",
    "ambient_temp": "ambient_temp_degC", "ambient_temperature": "ambient_temp_degC",
    "outside_temp": "ambient_temp_degC", "ambient": "ambient_temp_degC",
    "cabin_temp": "cabin_temp_degC", "cabin_temperature": "cabin_temp_degC", "interior_temp": "cabin_temp_degC",
    "heater_power": "heater_power_W",
    "vent_temp": "vent_temp_degC", "vent_temperature": "vent_temp_degC",
    "blower_flow": "blower_flow_kg_per_s", "blower_air_flow": "blower_flow_kg_per_s",
    "hvac_setpoint": "hvac_setpoint_degC", "setpoint": "hvac_setpoint_degC", "set_point": "hvac_setpoint_degC",
    "grade": "grade_rad", "road_grade": "grade_rad",
}
CHANNEL_ALIASES.update(_BASE)

#: Human base name per channel, used by the writers (``speed [km/h]``, ``coolant_temp [degC]``).
HUMAN_NAME: dict[str, str] = {
    "speed_mps": "speed", "bat_current_A": "bat_current", "bat_voltage_V": "bat_voltage", "soc": "soc",
    "bat_temp_degC": "bat_temp", "engine_speed_rpm": "engine_speed", "engine_torque_Nm": "engine_torque",
    "engine_power_W": "engine_power", "bat_power_W": "bat_power",
    "fuel_rate_g_per_s": "fuel_rate", "coolant_temp_degC": "coolant_temp", "bay_temp_degC": "bay_temp",
    "ambient_temp_degC": "ambient_temp", "cabin_temp_degC": "cabin_temp", "heater_power_W": "heater_power",
    "vent_temp_degC": "vent_temp", "blower_flow_kg_per_s": "blower_flow",
    "hvac_setpoint_degC": "hvac_setpoint", "grade_rad": "grade",
}

_SPEC_RE = re.compile(r"^\s*(?P<name>[^\[\]()]*?)\s*(?:[\[(](?P<unit>[^\[\]()]*)[\])])?\s*$")


def canonical_name(name: str) -> str | None:
    """The canonical channel for a header/field base name, or None if it is not one we know."""
    key = re.sub(r"[\s\-.]+", "_", str(name).strip()).lower()
    for alias, ch in CHANNEL_ALIASES.items():
        if alias.lower() == key:
            return ch
    return None


def aliases_of(channel: str) -> list[str]:
    """Every header base name accepted for ``channel`` (its canonical name first)."""
    return [channel] + sorted(a for a, ch in CHANNEL_ALIASES.items() if ch == channel and a != channel)


def _tokens(name: str) -> set[str]:
    key = re.sub(r"[\s\-.]+", "_", str(name).strip()).lower()
    return {t for t in key.split("_") if t}


# Words that say what kind of quantity a column is, not which one: a shared word like these alone does not
# make a column look like a channel.
_GENERIC = {"temp", "temperature", "speed", "rate", "power", "flow", "air", "the", "of", "value", "signal",
            "sensor", "engine", "battery", "bat", "a", "v", "s", "w", "degc", "degf"}


def _unit_fits(unit: str | None, channel: str) -> bool:
    if unit is None:
        return True
    try:
        convert(1.0, unit, CHANNELS[channel][0])
        return True
    except (UnitError, Exception):  # noqa: BLE001 - pint raises several types
        return False


def suggest_channel(name: str, unit: str | None = None) -> tuple[str | None, list[str]]:
    """A header name that is not an accepted spelling but looks like a known channel.

    A channel "looks like" the column when one of its accepted names shares a distinctive word with the
    column name (``coolant [degF]`` shares ``coolant`` with ``coolant_temp``) or is a close spelling of it
    (``colant_temp``), and the column's unit (when given) converts to the channel's unit.

    Returns
    -------
    (channel or None, candidates)
        The channel when exactly one candidate fits (safe to use), else None and the candidates (possibly
        empty) for a warning.
    """
    import difflib

    all_words = _tokens(name)
    words = all_words - _GENERIC
    key = "_".join(sorted(all_words))
    strong, weak = [], []
    for ch in CHANNELS:
        if not _unit_fits(unit, ch):
            continue
        tok = [_tokens(a) for a in aliases_of(ch)]
        if any(words & (at - _GENERIC) for at in tok) or any(
                difflib.SequenceMatcher(None, key, "_".join(sorted(at))).ratio() >= 0.85 for at in tok):
            strong.append(ch)
        elif any(all_words & at for at in tok):
            weak.append(ch)  # only a generic word in common (``engine [rpm]``): worth a warning, not a match
    if strong:
        return (strong[0] if len(strong) == 1 else None), strong
    return None, weak


def describe_channels() -> str:
    """The canonical channels, their units and every accepted header spelling (``iptm ingest --list-channels``)."""
    lines = [f"{'channel':22s} {'unit':14s} accepted header names (case and spaces/dashes ignored; "
             "write the unit in brackets, e.g. 'coolant_temp [degF]')"]
    for ch, (unit, desc) in CHANNELS.items():
        lines.append(f"{ch:22s} {unit:14s} {', '.join(aliases_of(ch))}")
        lines.append(f"{'':22s} {'':14s} ({desc})")
    lines.append("time column: " + ", ".join(sorted(TIME_NAMES)) + " (with a time unit, e.g. 'time [s]')")
    return "\n".join(lines)


def split_spec(spec: str) -> tuple[str, str | None]:
    """Split ``"speed [km/h]"`` or ``"speed (km/h)"`` into ``("speed", "km/h")``; unit None if absent."""
    m = _SPEC_RE.match(str(spec))
    if not m:
        return str(spec).strip(), None
    unit = m.group("unit")
    return m.group("name"), (unit.strip() if unit is not None and unit.strip() else None)


def parse_target(spec, path, where: str) -> tuple[str, str | None]:
    """Parse a map value: ``"channel"`` or ``"channel [unit]"`` or ``{"channel": ..., "unit": ...}``.

    Returns the canonical channel and the source unit (None when the map does not give one).
    """
    if isinstance(spec, dict):
        name, unit = spec.get("channel"), spec.get("unit")
    elif isinstance(spec, (list, tuple)) and len(spec) == 2:
        name, unit = spec
    else:
        name, unit = split_spec(str(spec))
    ch = canonical_name(name) if name is not None else None
    if ch is None:
        raise LogFormatError(path, f"map target {name!r} is not a canonical channel", where,
                             f"use one of {', '.join(CHANNELS)}")
    if unit is not None:
        check_unit(unit, ch, path, where)
    return ch, unit


def check_unit(unit: str, channel: str, path, where: str) -> None:
    """Raise a :class:`LogFormatError` unless ``unit`` converts to the channel's unit."""
    try:
        parse_unit(unit)
    except UnitError as exc:
        raise LogFormatError(path, str(exc) if str(exc).startswith("unit ") else f"unknown unit {unit!r}", where,
                             "write a pint unit such as km/h, mph, degC, degF, %, A, V, g/s, L/h") from None
    try:
        convert(1.0, unit, CHANNELS[channel][0])
    except UnitError:
        raise LogFormatError(path, f"unit {unit!r} does not fit channel {channel} ({CHANNELS[channel][0]})",
                             where) from None


def to_channel_unit(values, unit: str, channel: str, path, where: str) -> np.ndarray:
    """Convert ``values`` in ``unit`` to the canonical unit of ``channel`` (errors name file and where)."""
    check_unit(unit, channel, path, where)
    return np.asarray(convert(np.asarray(values, dtype=float), unit, CHANNELS[channel][0]), dtype=float)


def implied_unit(channel: str) -> str:
    """The unit a canonical column name carries in itself (``speed_mps`` -> ``m/s``)."""
    return CHANNELS[channel][0]


def sniff_text(path, kind: str, n: int = 65536) -> str:
    """Return the head of a text file; error if it is empty or binary.

    Raises
    ------
    LogFormatError
        Empty file, NUL bytes, or not UTF-8 text.
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(n)
    except OSError as exc:
        raise LogFormatError(path, f"cannot open: {exc.strerror or exc}") from None
    if not head.strip():
        raise LogFormatError(path, "empty file")
    if b"\x00" in head:
        raise LogFormatError(path, f"binary file, not a {kind} text file")
    try:
        # A multi-byte character may be cut at the end of the sample; ignore only that.
        return head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start >= len(head) - 4:
            return head[: exc.start].decode("utf-8")
        raise LogFormatError(path, f"binary file, not a {kind} text file (byte {exc.start} is not UTF-8)") from None


#: A text log whose head has more than this fraction of NUL or non-UTF-8 bytes is binary, not damaged text.
BINARY_FRACTION = 0.05


def sniff_text_lenient(path, kind: str, n: int = 65536) -> str:
    """Like :func:`sniff_text`, but a few bad bytes (a damaged text log) are allowed.

    Raises
    ------
    LogFormatError
        Empty file, or a head that is mostly not text (a binary file).
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(n)
    except OSError as exc:
        raise LogFormatError(path, f"cannot open: {exc.strerror or exc}") from None
    if not head.strip():
        raise LogFormatError(path, "empty file")
    text = head.decode("utf-8", errors="replace")
    bad = text.count("\ufffd") + text.count("\x00")
    if bad > BINARY_FRACTION * max(len(text), 1):
        raise LogFormatError(path, f"binary file, not a {kind} text file")
    return text


def check_nonempty(path) -> None:
    """Raise :class:`LogFormatError` if ``path`` is missing or empty."""
    p = Path(path)
    if not p.exists():
        raise LogFormatError(path, "no such file")
    if p.is_dir():
        raise LogFormatError(path, "is a folder, not a log file")
    if p.stat().st_size == 0:
        raise LogFormatError(path, "empty file")


#: Out-of-range sample times listed per channel in ``LogMeta.channel_counts`` (all are counted).
MAX_LISTED_TIMES = 5


def make_series(t, v, channel: str, meta=None, absent=None) -> pd.Series:
    """A stream: the finite, physically possible samples of ``channel`` indexed by ``time_s``, sorted by
    time, samples sharing a time averaged.

    Times are rounded to the microsecond (candump's resolution), so the same sample read from formats
    with different clock representations lands at the same time and in the same resampling bin.

    Parameters
    ----------
    t, v : array-like
        Sample times (s) and values in the channel's canonical unit.
    channel : str
        Canonical channel; its :data:`calib.drivelog.RANGES` entry bounds the values kept.
    meta : LogMeta, optional
        When given, the accounting of this channel (``read``, ``nonfinite``, ``out_of_range``, ``merged``,
        ``kept``, and the first times of out-of-range values) is added to ``meta.channel_counts[channel]``.
    absent : array of bool, optional
        Samples that were never there (an empty CSV cell): not counted as read. Without it every NaN counts
        as a non-finite reading.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # a time of 1e308 s rounds to inf: non-finite, counted
        t = np.round(np.asarray(t, dtype=float), 6)
    v = np.asarray(v, dtype=float)
    if absent is not None:
        there = ~np.asarray(absent, dtype=bool)
        t, v = t[there], v[there]
    fin = np.isfinite(t) & np.isfinite(v)
    lo, hi = RANGES.get(channel, (-np.inf, np.inf))
    inside = fin & (v >= lo) & (v <= hi)
    out = fin & ~inside
    t_out = np.sort(t[out])
    t, v = t[inside], v[inside]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    n_in = len(t)
    if len(t) > 1 and np.any(np.diff(t) == 0):
        # Two samples at the same log time (one row per channel at one instant, two buses): their mean.
        s = pd.Series(v, index=t).groupby(level=0).mean()
        t, v = s.index.to_numpy(float), s.to_numpy(float)
    if meta is not None:
        acc = meta.channel_counts.setdefault(channel, {"read": 0, "nonfinite": 0, "out_of_range": 0,
                                                        "merged": 0, "kept": 0})
        acc["read"] += int(len(fin))
        acc["nonfinite"] += int((~fin).sum())
        acc["out_of_range"] += int(out.sum())
        acc["merged"] += int(n_in - len(t))
        acc["kept"] += int(len(t))
        if out.any():
            acc["range"] = [float(lo), float(hi)]
            times = acc.setdefault("out_of_range_times_s", [])
            times.extend(float(x) for x in t_out[: max(MAX_LISTED_TIMES - len(times), 0)])
    return pd.Series(v, index=pd.Index(t, name="time_s"), name=channel)


#: Stoichiometric air-fuel mass ratio of gasoline (E0; E10 is 14.1): fuel = MAF / AFR at lambda = 1. A
#: spark-ignition engine runs at lambda = 1 under closed-loop control, but richer at full load and during a
#: cold start's enrichment and leaner (zero fuel) on overrun cut-off, so fuel from MAF is an estimate.
AFR_STOICH = 14.7


def fuel_from_maf(t, maf_g_per_s, meta, source: str) -> pd.Series:
    """Fuel rate (g/s) estimated from the intake air mass flow at the stoichiometric ratio.

    The estimate is labelled in ``meta.estimated["fuel_rate_g_per_s"]``, ``meta.channel_sources`` and a
    note, so that no report presents it as a measured fuel rate.
    """
    maf = np.asarray(maf_g_per_s, dtype=float)
    s = make_series(t, maf / AFR_STOICH, "fuel_rate_g_per_s", meta)
    how = (f"ESTIMATE from the intake air mass flow ({source}) at the stoichiometric air-fuel ratio "
           f"{AFR_STOICH:g}: not a measured fuel rate (off during enrichment and fuel cut-off)")
    meta.estimated["fuel_rate_g_per_s"] = how
    meta.channel_sources["fuel_rate_g_per_s"] = f"{source} / {AFR_STOICH:g} (estimate)"
    meta.notes.append(f"warning: fuel_rate_g_per_s is an {how}")
    return s
