"""calib.units: aliases, conversions through pint, fuel density, clear errors."""
import numpy as np
import pytest

from calib.errors import IptmError
from calib.units import GASOLINE_DENSITY_KG_PER_L, UnitError, convert, is_known_unit, normalize_unit, parse_unit


@pytest.mark.parametrize("unit, value, to, expected", [
    ("km/h", 36.0, "m/s", 10.0),
    ("kph", 36.0, "m/s", 10.0),
    ("KPH", 36.0, "m/s", 10.0),
    ("mph", 1.0, "m/s", 0.44704),
    ("degF", 212.0, "degC", 100.0),
    ("°F", 32.0, "degC", 0.0),
    ("°C", 20.0, "degC", 20.0),
    ("K", 273.15, "degC", 0.0),
    ("%", 55.0, "dimensionless", 0.55),
    ("pct", 50.0, "dimensionless", 0.5),
    ("kW", 1.5, "W", 1500.0),
    ("Nm", 10.0, "N*m", 10.0),
    ("ms", 1500.0, "s", 1.5),
    ("rpm", 3000.0, "rpm", 3000.0),
    ("1/min", 3000.0, "rpm", 3000.0),
    ("kg/h", 3.6, "g/s", 1.0),
])
def test_aliases_convert(unit, value, to, expected):
    assert convert(value, unit, to) == pytest.approx(expected, abs=1e-9)


def test_arrays_and_scalars():
    out = convert(np.array([0.0, 36.0, 72.0]), "km/h", "m/s")
    assert isinstance(out, np.ndarray)
    np.testing.assert_allclose(out, [0, 10, 20])
    assert isinstance(convert(1.0, "m/s", "km/h"), float)


def test_fuel_volume_flow_uses_gasoline_density_and_is_overridable():
    # 3.6 L/h = 1 mL/s = 0.74 g/s at 0.74 kg/L.
    assert GASOLINE_DENSITY_KG_PER_L == 0.74
    assert convert(3.6, "L/h", "g/s") == pytest.approx(0.74)
    assert convert(3.6, "L/h", "g/s", density=0.8) == pytest.approx(0.8)
    assert convert(0.74, "g/s", "L/h") == pytest.approx(3.6)


def test_unknown_and_incompatible_units_raise_clear_errors():
    with pytest.raises(UnitError, match="unknown unit 'wobbles'"):
        convert(1.0, "wobbles", "m/s")
    with pytest.raises(UnitError, match="different dimensions"):
        convert(1.0, "km/h", "degC")
    with pytest.raises(UnitError, match="empty unit"):
        parse_unit("")
    assert issubclass(UnitError, IptmError)
    assert not is_known_unit("bogus_unit_xyz")
    assert is_known_unit("L/h")
    assert normalize_unit(" kph ") == "km/h"


def test_rpm_constant_is_one_revolution_per_minute_in_rad_per_s():
    """60 rpm is one revolution (2 pi rad) per second; pint's own rpm definition agrees."""
    import math

    from calib.units import RPM

    assert 60.0 * RPM == pytest.approx(2.0 * math.pi, rel=1e-15)
    assert convert(3000.0, "rpm", "rad/s") == pytest.approx(3000.0 * RPM, rel=1e-12)


def test_conversions_do_not_depend_on_offset_autoconversion(monkeypatch):
    """The registry converts offset units to base units in products; the conversions here never multiply a
    temperature, so every pair of alias targets and temperature-rate units converts the same without it
    (this keeps the listed equivalent mutant of that flag honest)."""
    import itertools

    import pint

    import calib.units as U

    units = sorted(set(U.ALIASES.values()) | {"kelvin", "degC/s", "degF/min", "K/s", "W/degC", "W/K", "J/degC",
                                               "1/degC", "1/K", "degC*s"})

    def table():
        out = {}
        for a, b in itertools.product(units, units):
            try:
                out[a, b] = np.round(np.asarray(U.convert([1.5, -20.0], a, b)), 12).tolist()
            except UnitError:
                out[a, b] = "error"
        return out

    with_flag = table()
    monkeypatch.setattr(U, "ureg", pint.UnitRegistry(autoconvert_offset_to_baseunit=False))
    assert len(units) == 41 and table() == with_flag
    assert sum(v != "error" for v in with_flag.values()) == 165
