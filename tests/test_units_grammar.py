"""Unit strings from any front end are checked by a small grammar with limits before pint evaluates them."""
import subprocess
import sys
import time

import pytest

from calib.units import MAX_UNIT_EXPONENT, UnitError, check_unit_grammar, convert, parse_unit


@pytest.mark.parametrize("unit", ["km/h", "degC", "%", "N*m", "N m", "L/h", "1/min", "m/s^2", "m/s**2", "m**-2",
                                  "kg*m**2/s**3", "g/(kW*h)", "W/(m**2*K)", "A*h", "µs", "mile/hour", "°C"])
def test_ordinary_units_pass(unit):
    parse_unit(unit)


@pytest.mark.parametrize("unit, why", [
    ("km/h**9**9**9", "exponent 9"), ("kg**9**9**9", "exponent 9"), ("km/h**2**2", "exponent of an exponent"),
    ("m**5", "exponent 5"), ("(((((m)))))", "nested deeper"), ("m" + "*m" * 20, "factors"),
    ("x" * 200, "characters long"), ("m**(2)", "plain number"), ("m)", "unmatched"), ("(m", "without"),
    ("m;import os", "unexpected character"), ("m**9999999", "exponent"),
])
def test_hostile_units_are_refused_by_name(unit, why):
    t0 = time.perf_counter()
    with pytest.raises(UnitError, match=why.replace("(", r"\(")):
        parse_unit(unit)
    assert time.perf_counter() - t0 < 1.0


def test_exponent_limit_is_the_documented_one():
    check_unit_grammar(f"m**{MAX_UNIT_EXPONENT}")
    with pytest.raises(UnitError):
        check_unit_grammar(f"m**{MAX_UNIT_EXPONENT + 1}")
    assert convert(1.0, "km/h", "m/s") == pytest.approx(1 / 3.6)


@pytest.mark.parametrize("header", ["speed [km/h**9**9**9]", "speed [kg**9**9**9]"])
def test_cli_answers_a_unit_bomb_at_once(tmp_path, header):
    f = tmp_path / "b.csv"
    f.write_text(f"time [s],{header}\n0,1\n1,2\n")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "iptm.cli", "ingest", str(f), "--out", str(tmp_path / "o.parquet")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "exponent 9 is larger than 4" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o.parquet").exists()
    assert time.perf_counter() - t0 < 30
