"""Units: one shared pint registry, the aliases loggers write, and a checked ``convert``.

Every unit conversion in the workbench goes through :func:`convert` so that factors are never written by
hand. Unit strings are normalised first (``kph`` -> ``km/h``, ``°C`` -> ``degC``, ``%`` -> ``percent``,
``Nm`` -> ``N*m``, ``L/h`` stays a volume flow...), then parsed by pint.

Fuel flow logged as a volume (``L/h``, ``mL/s``, ``gal/h``) converts to a mass flow (``g/s``) through a
density: gasoline, :data:`GASOLINE_DENSITY_KG_PER_L` = 0.74 kg/L (a typical E0-E10 pump fuel at 15 degC;
see ``calib/data/prius_facts.md``). Pass ``density=`` (kg/L) to override it.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pint

from calib.errors import IptmError

#: The registry shared by the whole project (quantities from different registries cannot be mixed).
ureg = pint.UnitRegistry(autoconvert_offset_to_baseunit=True)

#: Density used to turn a volume flow of fuel into a mass flow, kg/L (gasoline at 15 degC).
GASOLINE_DENSITY_KG_PER_L = 0.74

#: Engine speed: rad/s per rpm (the one definition; numba kernels read it as a constant).
RPM = 2.0 * math.pi / 60.0

# Spellings found in logger headers and DBCs -> pint spellings. Keys are compared case-sensitively
# first, then lower-cased (so "KPH" and "Kph" work, but "mA" vs "MA" stay distinct).
ALIASES: dict[str, str] = {
    "kph": "km/h",
    "kmh": "km/h",
    "km/hr": "km/h",
    "kmph": "km/h",
    "mph": "mile/hour",
    "mi/h": "mile/hour",
    "m/sec": "m/s",
    "mps": "m/s",
    "°c": "degC",
    "℃": "degC",
    "℉": "degF",
    "ºc": "degC",
    "deg c": "degC",
    "degc": "degC",
    "celsius": "degC",
    "c": "degC",  # a bare C in a temperature header means Celsius, never coulomb
    "°f": "degF",
    "ºf": "degF",
    "deg f": "degF",
    "degf": "degF",
    "fahrenheit": "degF",
    "f": "degF",
    "k": "kelvin",
    "%": "percent",
    "pct": "percent",
    "percent": "percent",
    "fraction": "dimensionless",
    "frac": "dimensionless",
    "ratio": "dimensionless",
    "1": "dimensionless",
    "rpm": "rpm",
    "1/min": "rpm",  # in a logger header 1/min is an engine speed (pint would drop the 2 pi)
    "r/min": "rpm",
    "rev/min": "rpm",
    "nm": "N*m",
    "n.m": "N*m",
    "n m": "N*m",
    "n*m": "N*m",
    "l/h": "L/h",
    "l/hr": "L/h",
    "lph": "L/h",
    "ml/s": "mL/s",
    "ml/min": "mL/min",
    "gal/h": "gallon/hour",
    "gph": "gallon/hour",
    "g/s": "g/s",
    "g/h": "g/h",
    "kg/h": "kg/h",
    "kg/s": "kg/s",
    "s": "s",
    "sec": "s",
    "secs": "s",
    "ms": "ms",
    "us": "us",
    "ns": "ns",
    "min": "minute",
    "h": "hour",
    "hr": "hour",
    "w": "W",
    "kw": "kW",
    "v": "V",
    "a": "A",
    "ma": "mA",
    "ah": "A*h",
    "rad": "rad",
    "deg": "degree",
}


class UnitError(IptmError):
    """A unit string cannot be parsed, or two units are not convertible."""


def normalize_unit(unit: str) -> str:
    """Map a logger's spelling of a unit to one pint understands.

    Parameters
    ----------
    unit : str
        As written in a header, a DBC or a map (``"km/h"``, ``"kph"``, ``"°C"``, ``"%"``...).

    Returns
    -------
    str
        The pint spelling (the input, stripped, when no alias applies).
    """
    u = str(unit).strip()
    if u in ALIASES:
        return ALIASES[u]
    low = re.sub(r"\s+", " ", u.lower())
    return ALIASES.get(low, u)


#: Limits of the unit grammar: a unit string is checked against them before pint sees it (pint evaluates
#: ``km/h**9**9**9`` as a power tower and never returns).
MAX_UNIT_CHARS = 64
MAX_UNIT_EXPONENT = 4
MAX_UNIT_NESTING = 3
MAX_UNIT_FACTORS = 8

_UNIT_TOKEN = re.compile(r"\s*(?:(?P<pow>\*\*|\^)|(?P<op>[*/-])|(?P<lp>\()|(?P<rp>\))"
                         r"|(?P<num>[0-9]{1,6}(?:\.[0-9]{1,6})?)|(?P<name>[^\W\d][\w°º]*|[°º%µΩ][\w°º]*))")


def check_unit_grammar(unit: str) -> None:
    """Refuse a unit string that is not a short product of named units with small exponents.

    Grammar: ``term := factor (('*' | '/' | ' ') factor)*``, ``factor := atom (('**' | '^') ['-'] number)?``,
    ``atom := name | number | '(' term ')'``; at most :data:`MAX_UNIT_CHARS` characters,
    :data:`MAX_UNIT_FACTORS` factors, exponents of magnitude at most :data:`MAX_UNIT_EXPONENT`, no exponent of
    an exponent, parentheses nested at most :data:`MAX_UNIT_NESTING` deep.

    Raises
    ------
    UnitError
        Saying which limit the string breaks.
    """
    u = str(unit)
    if len(u) > MAX_UNIT_CHARS:
        raise UnitError(f"unit {u[:24]!r}... is {len(u)} characters long (at most {MAX_UNIT_CHARS})")
    toks, pos = [], 0
    while pos < len(u):
        if u[pos:].strip() == "":
            break
        m = _UNIT_TOKEN.match(u, pos)
        if not m or m.end() == pos:
            raise UnitError(f"unit {u!r}: unexpected character {u[pos:].strip()[:1]!r}")
        toks.append((m.lastgroup, m.group(m.lastgroup)))
        pos = m.end()
    i, depth, factors = 0, 0, 0

    def atom():
        nonlocal i, depth, factors
        if i >= len(toks):
            raise UnitError(f"unit {u!r} ends where a unit was expected")
        kind, _ = toks[i]
        if kind == "lp":
            depth += 1
            if depth > MAX_UNIT_NESTING:
                raise UnitError(f"unit {u!r}: parentheses nested deeper than {MAX_UNIT_NESTING}")
            i += 1
            term()
            if i >= len(toks) or toks[i][0] != "rp":
                raise UnitError(f"unit {u!r}: '(' without ')'")
            depth -= 1
            i += 1
        elif kind in ("name", "num"):
            factors += 1
            if factors > MAX_UNIT_FACTORS:
                raise UnitError(f"unit {u!r} has more than {MAX_UNIT_FACTORS} factors")
            i += 1
        else:
            raise UnitError(f"unit {u!r}: {toks[i][1]!r} where a unit was expected")
        if i < len(toks) and toks[i][0] == "pow":
            i += 1
            if i < len(toks) and toks[i] == ("op", "-"):
                i += 1
            if i >= len(toks) or toks[i][0] != "num":
                raise UnitError(f"unit {u!r}: an exponent must be a plain number")
            if abs(float(toks[i][1])) > MAX_UNIT_EXPONENT:
                raise UnitError(f"unit {u!r}: exponent {toks[i][1]} is larger than {MAX_UNIT_EXPONENT}")
            i += 1
            if i < len(toks) and toks[i][0] == "pow":
                raise UnitError(f"unit {u!r}: an exponent of an exponent")

    def term():
        nonlocal i
        atom()
        while i < len(toks) and toks[i][0] != "rp":
            if toks[i][0] == "op":
                i += 1
            atom()  # a space between two units multiplies them ("N m")

    term()
    if i != len(toks):
        raise UnitError(f"unit {u!r}: unmatched ')'")


def parse_unit(unit: str) -> pint.Unit:
    """Parse ``unit`` (after alias normalisation) into a pint unit.

    The string is first checked against a small grammar with limits (:func:`check_unit_grammar`), so that no
    unit string, wherever it comes from (a CSV header, a DBC, a parameter file, a map), can make pint work
    for long.

    Raises
    ------
    UnitError
        Empty or unknown unit, or one that breaks the grammar's limits.
    """
    if unit is None or not str(unit).strip():
        raise UnitError("empty unit")
    norm = normalize_unit(unit)
    check_unit_grammar(norm)
    try:
        u = ureg.Unit(norm)
    except (pint.errors.UndefinedUnitError, pint.errors.DefinitionSyntaxError, AttributeError,
            TypeError, ValueError, AssertionError, KeyError) as exc:
        # pint raises a zoo of types for garbage input; all mean "not a unit".
        raise UnitError(f"unknown unit {unit!r}") from exc
    except Exception as exc:  # noqa: BLE001 - pint's tokenizer can raise anything on odd strings
        raise UnitError(f"unknown unit {unit!r} ({type(exc).__name__})") from exc
    # what pint parsed, checked again: an exponent the text hid (1e308) and units pint parses but cannot
    # convert (a logarithmic unit such as dB inside a product) are refused here, not where data is converted
    big = [e for e in dict(u._units).values() if not abs(e) <= MAX_UNIT_EXPONENT]
    if big:
        raise UnitError(f"unit {unit!r}: exponent {big[0]:g} is larger than {MAX_UNIT_EXPONENT}")
    try:
        ureg.Quantity(1.0, u).to_root_units()
    except Exception as exc:  # noqa: BLE001 - pint raises assertion, key and undefined-unit errors here
        raise UnitError(f"unit {unit!r} cannot be converted to anything (a logarithmic or offset unit inside "
                        "a product?)") from exc
    return u


def is_known_unit(unit: str) -> bool:
    """True when :func:`parse_unit` accepts ``unit``."""
    try:
        parse_unit(unit)
        return True
    except UnitError:
        return False


def _is_volume_flow(u: pint.Unit) -> bool:
    return u.dimensionality == ureg.Unit("L/h").dimensionality


def _is_mass_flow(u: pint.Unit) -> bool:
    return u.dimensionality == ureg.Unit("g/s").dimensionality


def convert(values, from_unit: str, to_unit: str, *, density: float | None = None):
    """Convert ``values`` from ``from_unit`` to ``to_unit``.

    Parameters
    ----------
    values : float or array_like
        Magnitudes in ``from_unit``.
    from_unit, to_unit : str
        Unit strings; aliases such as ``kph``, ``mph``, ``L/h``, ``degF``, ``%``, ``rpm`` are accepted.
    density : float, optional
        Fuel density in kg/L, used only to convert a volume flow into a mass flow or back. Defaults to
        :data:`GASOLINE_DENSITY_KG_PER_L`.

    Returns
    -------
    float or numpy.ndarray
        Magnitudes in ``to_unit`` (a float for scalar input).

    Raises
    ------
    UnitError
        Unknown unit, or units of different dimensions (e.g. ``km/h`` to ``degC``).
    """
    src = parse_unit(from_unit)
    dst = parse_unit(to_unit)
    scalar = np.ndim(values) == 0
    arr = np.asarray(values, dtype=float)
    if src == dst:
        out = arr.copy()
        return float(out) if scalar else out
    q = ureg.Quantity(arr, src)
    if _is_volume_flow(src) and _is_mass_flow(dst):
        rho = ureg.Quantity(GASOLINE_DENSITY_KG_PER_L if density is None else density, "kg/L")
        q = q * rho
    elif _is_mass_flow(src) and _is_volume_flow(dst):
        rho = ureg.Quantity(GASOLINE_DENSITY_KG_PER_L if density is None else density, "kg/L")
        q = q / rho
    try:
        out = np.asarray(q.to(dst).magnitude, dtype=float)
    except pint.errors.DimensionalityError as exc:
        raise UnitError(f"cannot convert {from_unit!r} to {to_unit!r}: different dimensions") from exc
    return float(out) if scalar else out
