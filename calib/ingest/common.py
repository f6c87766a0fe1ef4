"""Helpers shared by the readers: channel names, ``"channel [unit]"`` specs, time checks, file sniffing."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from calib.drivelog import CHANNELS
from calib.errors import LogFormatError
from calib.units import UnitError, convert, parse_unit

# Base names a human header uses for each channel (the canonical name without its unit suffix), plus a
# few common synonyms. Matching is case-insensitive and ignores spaces/dashes.
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
    except UnitError:
        raise LogFormatError(path, f"unknown unit {unit!r}", where,
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


def check_nonempty(path) -> None:
    """Raise :class:`LogFormatError` if ``path`` is missing or empty."""
    p = Path(path)
    if not p.exists():
        raise LogFormatError(path, "no such file")
    if p.is_dir():
        raise LogFormatError(path, "is a folder, not a log file")
    if p.stat().st_size == 0:
        raise LogFormatError(path, "empty file")


def make_series(t, v, channel: str) -> pd.Series:
    """A stream: finite samples of ``channel`` indexed by ``time_s``, sorted by time, duplicates averaged.

    Times are rounded to the microsecond (candump's resolution), so the same sample read from formats
    with different clock representations lands at the same time and in the same resampling bin.
    """
    t = np.round(np.asarray(t, dtype=float), 6)
    v = np.asarray(v, dtype=float)
    ok = np.isfinite(t) & np.isfinite(v)
    t, v = t[ok], v[ok]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    if len(t) > 1 and np.any(np.diff(t) == 0):
        # Two messages at the same log time carry the same signal twice (e.g. two buses): average them.
        s = pd.Series(v, index=t).groupby(level=0).mean()
        t, v = s.index.to_numpy(float), s.to_numpy(float)
    return pd.Series(v, index=pd.Index(t, name="time_s"), name=channel)


def merge_streams(parts: dict[str, list[tuple[np.ndarray, np.ndarray]]]) -> dict:
    """Concatenate per-channel chunks ``[(t, v), ...]`` into streams."""
    out = {}
    for ch, chunks in parts.items():
        if not chunks:
            continue
        t = np.concatenate([c[0] for c in chunks])
        v = np.concatenate([c[1] for c in chunks])
        s = make_series(t, v, ch)
        if len(s):
            out[ch] = s
    return out
