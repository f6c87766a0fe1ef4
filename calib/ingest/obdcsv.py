"""CSV exports of OBD-II phone apps: the conventions of Torque Pro and Car Scanner.

Both apps log what the car answers to OBD-II Mode 01 requests, each PID polled in turn, so every channel
has its own irregular sample times. :mod:`calib.ingest.csvlog` reads them with its wide and long CSV
machinery; this module holds what is particular to each app: how its header is recognised, which of its
column (Torque) or PID (Car Scanner) names are canonical channels, which look like one but are not, its
marker for a missing reading, and its unit spellings.

- **Torque Pro** (``trackLog.csv``): wide, comma separated, headers written with a space after the comma
  (``GPS Time, Device Time, Longitude, Latitude,GPS Speed (Meters/second),...``), the unit in the last
  parentheses (``Speed (OBD)(km/h)``, ``Engine Coolant Temperature(°C)``), ``-`` for a PID with no
  reading in that row. The time base is ``Device Time`` (the phone's clock, ``19-Dec-2013 13:22:48.242``,
  local time without a zone); ``GPS Time`` is ``-`` until the phone has a fix and is not used. With
  several ECUs answering, columns carry the ECU's address (``ECU(7EA): Engine RPM(rpm)``).
- **Car Scanner** (CSV export): long, semicolon separated, every cell quoted, a trailing ``;`` on every
  line: ``"SECONDS";"PID";"VALUE";"UNITS"`` (optionally ``"LATITUDE";"LONGTITUDE"``), one row per PID
  reading. ``SECONDS`` is the app's own clock in seconds (not a date), so the log has no start time.

Fuel: a log with the intake air mass flow (MAF, PID 0x10) and no fuel rate gets a fuel rate estimated
at the stoichiometric ratio (:func:`calib.ingest.common.fuel_from_maf`), labelled as an estimate. The
fuel flow both apps compute themselves (Torque's ``Fuel flow rate/hour``, Car Scanner's ``Calculated
instant fuel rate``) is derived by the app from MAF with its own assumptions and is not read as a measured
fuel rate; PID 0x5E (``Engine fuel rate``, Torque's ``Fuel Rate (direct from ECU)``) is the engine ECU's
own fuel rate and is read as one.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

#: Target of a column or PID that is the intake air mass flow (not a canonical channel: fuel is estimated
#: from it when the log has no fuel rate).
MAF = "maf"

_NAME_KEY = re.compile(r"[\s_\-]+")


def name_key(name: str) -> str:
    """A column/PID name compared case-, space- and dash-insensitively."""
    return _NAME_KEY.sub(" ", str(name).strip()).lower()


@dataclass(frozen=True)
class AppConvention:
    """How one app writes its CSV export."""

    name: str
    title: str
    layout: str  # "wide" or "long"
    channels: dict  # name_key(column or PID name) -> (canonical channel or MAF, default unit or None)
    unused: dict  # name_key -> why a look-alike is not read
    absent: frozenset = frozenset()  # cell text that means "no reading in this row"
    time_column: str | None = None  # wide: the column that is the time base
    not_time: dict = field(default_factory=dict)  # other clock columns -> why not used
    unit_fixes: dict = field(default_factory=dict)  # unit as the app writes it -> pint spelling
    notes: tuple = ()


TORQUE = AppConvention(
    name="torque", title="Torque Pro CSV log", layout="wide",
    channels={
        "speed (obd)": ("speed_mps", None),
        "engine rpm": ("engine_speed_rpm", None),
        "engine coolant temperature": ("coolant_temp_degC", None),
        "ambient air temp": ("ambient_temp_degC", None),
        "mass air flow rate": (MAF, None),
        "fuel rate (direct from ecu)": ("fuel_rate_g_per_s", None),
        "hybrid battery charge (%)": ("soc", None),
    },
    unused={
        "gps speed": "GPS speed, not the car's speed sensor",
        "speed (gps)": "GPS speed, not the car's speed sensor",
        "voltage (control module)": "the 12-V system at the engine ECU, not the traction battery",
        "voltage (obd adapter)": "the 12-V system at the OBD socket, not the traction battery",
        "torque": "computed by the app from acceleration and the vehicle profile's mass, not engine torque",
        "engine kw (at the wheels)": "computed by the app from acceleration and the vehicle profile's mass",
        "horsepower (at the wheels)": "computed by the app from acceleration and the vehicle profile's mass",
        "fuel flow rate/hour": "computed by the app from MAF with its own air-fuel ratio, not measured",
        "fuel flow rate/minute": "computed by the app from MAF with its own air-fuel ratio, not measured",
        "intake air temperature": "air in the intake manifold, warmed by the engine bay: not the ambient",
        "engine load": "a percentage of peak air flow, not a torque",
        "engine load(absolute)": "a percentage of peak air flow, not a torque",
    },
    absent=frozenset({"-"}),
    time_column="device time",
    not_time={"gps time": "the GPS fix's time ('-' until the phone has a fix); Device Time is the time base"},
    # Torque writes litres per minute as "L/m" (litres per metre to pint) and hours as "hr".
    unit_fixes={"L/m": "L/min", "l/m": "L/min", "l/hr": "L/h", "L/hr": "L/h"},
    notes=("Device Time is the phone's local clock (no time zone in the file)",),
)

CAR_SCANNER = AppConvention(
    name="carscanner", title="Car Scanner CSV export", layout="long",
    channels={
        "vehicle speed": ("speed_mps", "km/h"),
        "engine rpm": ("engine_speed_rpm", "rpm"),
        "engine coolant temperature": ("coolant_temp_degC", "degC"),
        "ambient air temperature": ("ambient_temp_degC", "degC"),
        "maf air flow rate": (MAF, "g/s"),
        "engine fuel rate": ("fuel_rate_g_per_s", "L/h"),
        "hybrid battery pack remaining life": ("soc", "%"),
    },
    unused={
        "speed (gps)": "GPS speed, not the car's speed sensor",
        "calculated engine load value": "a percentage of peak air flow, not a torque",
        "calculated instant fuel rate": "computed by the app from MAF with its own air-fuel ratio, not measured",
        "fuel flow rate": "computed by the app, not measured",
        "control module voltage": "the 12-V system at the engine ECU, not the traction battery",
        "battery terminal voltage": "the 12-V battery, not the traction battery",
        "intake air temperature": "air in the intake manifold, warmed by the engine bay: not the ambient",
        "engine rpm x1000": "the same engine speed divided by 1000 (Engine RPM is read)",
    },
    unit_fixes={"g/sec": "g/s"},
    notes=("SECONDS is the app's own clock, not a date: the log has no start time",),
)

APPS: dict[str, AppConvention] = {a.name: a for a in (TORQUE, CAR_SCANNER)}

_ECU_PREFIX = re.compile(r"^\s*ECU\s*\(\s*([0-9A-Fa-f]{3,8})\s*\)\s*:\s*")


def detect_app(columns) -> AppConvention | None:
    """The app whose export has this header (column names already stripped), or None."""
    keys = {name_key(c) for c in columns}
    if "device time" in keys and ("gps time" in keys or "longitude" in keys):
        return TORQUE
    if {"seconds", "pid", "value"} <= keys:
        return CAR_SCANNER
    return None


def split_app_column(col: str) -> tuple[str, str | None, str | None]:
    """``"ECU(7EA): Speed (OBD)(km/h)"`` -> ``("Speed (OBD)", "km/h", "7EA")``.

    The unit is the last parenthesised group when the name has text before it (Torque writes the PID's
    own parentheses first: ``Speed (OBD)``); a name that is only parentheses keeps them.
    """
    col = str(col).strip()
    ecu = None
    m = _ECU_PREFIX.match(col)
    if m:
        ecu = m.group(1).upper()
        col = col[m.end():]
    if col.endswith(")"):
        depth, i = 0, len(col) - 1
        while i >= 0:
            if col[i] == ")":
                depth += 1
            elif col[i] == "(":
                depth -= 1
                if depth == 0:
                    break
            i -= 1
        name, unit = col[:i].rstrip(), col[i + 1:-1].strip()
        if i > 0 and name:
            return name, (unit or None), ecu
    return col, None, ecu


def app_target(app: AppConvention, name: str) -> tuple[tuple[str, str | None] | None, str | None]:
    """``((channel or MAF, default unit), None)`` for a name the app table reads, ``(None, why)`` for a
    known look-alike, ``(None, None)`` for anything else."""
    key = name_key(name)
    if key in app.channels:
        return app.channels[key], None
    return None, app.unused.get(key)


def fix_unit(app: AppConvention | None, unit: str | None) -> str | None:
    """The pint spelling of a unit as the app writes it."""
    if unit is None or app is None:
        return unit
    return app.unit_fixes.get(unit.strip(), unit)


__all__ = ["AppConvention", "APPS", "TORQUE", "CAR_SCANNER", "MAF", "detect_app", "split_app_column",
           "app_target", "fix_unit", "name_key"]
