"""Property-based: valid files with known content read back that content; random and mutated input to every
reader either reads or raises IptmError.

Nothing else (struct.error, zlib.error, UnicodeDecodeError, KeyError, pint errors...) may escape.
"""
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib.drivelog import DriveLog
from calib.errors import IptmError
from calib.ingest import read_log
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import write_streams

FORMATS = {"csv": "csv", "mcap": "mcap", "candump": "log", "blf": "blf", "asc": "asc"}
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

_DIR = Path(tempfile.mkdtemp(prefix="iptm-prop-"))
_streams, _meta = fabricate_streams(8, dropout=None, rates={"speed_mps": 5.0, "bat_current_A": 5.0,
                                                             "bat_voltage_V": 5.0, "engine_speed_rpm": 5.0,
                                                             "engine_torque_Nm": 5.0, "fuel_rate_g_per_s": 5.0})
GOOD = {f: write_streams(_streams, _meta, _DIR / f"good.{ext}", f).read_bytes() for f, ext in FORMATS.items()}


def _good_mf4():
    """A small MDF4 file (asammdf is an optional extra: skip the MDF cases without it)."""
    try:
        import asammdf
        import numpy as np
    except ImportError:
        return None
    mdf = asammdf.MDF(version="4.10")
    t = np.arange(0.0, 5.0, 0.5)
    mdf.append([asammdf.Signal(samples=t * 2, timestamps=t, name="speed", unit="km/h")])
    mdf.save(_DIR / "good.mf4", overwrite=True)
    mdf.close()
    return (_DIR / "good.mf4").read_bytes()


_mf4 = _good_mf4()
if _mf4 is not None:
    FORMATS["mf4"] = "mf4"
    GOOD["mf4"] = _mf4


def teardown_module(_module):
    shutil.rmtree(_DIR, ignore_errors=True)


def _check(fmt: str, data: bytes):
    p = _DIR / f"case.{FORMATS[fmt]}"
    p.write_bytes(data)
    try:
        out = read_log(p, fmt=fmt)
    except IptmError as exc:
        assert "\n" not in str(exc) and p.name in str(exc), str(exc)
        return
    assert isinstance(out, DriveLog)


@st.composite
def mutated(draw, fmt):
    data = bytearray(GOOD[fmt])
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["flip", "cut", "dup", "insert", "delete"]))
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        if kind == "flip":
            data[i] ^= draw(st.integers(1, 255))
        elif kind == "cut":
            data = data[:i]
        elif kind == "dup":
            j = draw(st.integers(i, min(len(data), i + 200)))
            data[i:i] = data[i:j]
        elif kind == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        else:
            del data[i: i + draw(st.integers(1, 50))]
    return bytes(data)


@pytest.mark.parametrize("fmt", list(FORMATS))
@SETTINGS
@given(data=st.binary(max_size=2048))
def test_random_bytes(fmt, data):
    _check(fmt, data)


@pytest.mark.parametrize("fmt", list(FORMATS))
@SETTINGS
@given(data=st.data())
def test_mutated_valid_files(fmt, data):
    _check(fmt, data.draw(mutated(fmt)))


@SETTINGS
@given(text=st.text(alphabet=st.sampled_from(list("0123456789.,-e#[]/ \nabcdeghkmpst%_")), max_size=400))
def test_random_csv_text(text):
    _check("csv", ("time [s],speed [km/h],soc [%]\n" + text).encode())


@SETTINGS
@given(text=st.text(alphabet=st.sampled_from(list("0123456789ABCDEF().# can\n")), max_size=400))
def test_random_candump_text(text):
    _check("candump", text.encode())


# ----------------------------------------------------------------------------------------------------
# valid files with known content: what is read back must be what was written
# ----------------------------------------------------------------------------------------------------
SPEED_UNITS = {"km/h": 1 / 3.6, "m/s": 1.0, "mph": 0.44704}  # -> m/s


@st.composite
def valid_csv(draw):
    """A CSV log with 1 Hz samples jittered by up to 0.4 s (first and last on time), columns in any order,
    speed in any of three units; returns (text, expected channel -> values at 0, 1, .. s)."""
    n = draw(st.integers(3, 30))
    jitter = [0.0] + draw(st.lists(st.floats(-0.4, 0.4), min_size=n - 2, max_size=n - 2)) + [0.0]
    t = [k + j for k, j in enumerate(jitter)]
    unit = draw(st.sampled_from(sorted(SPEED_UNITS)))
    speed = draw(st.lists(st.floats(0, 80, allow_nan=False), min_size=n, max_size=n))  # inside every unit's range
    soc = draw(st.lists(st.floats(0, 100, allow_nan=False), min_size=n, max_size=n))
    cool = draw(st.lists(st.floats(-40, 120, allow_nan=False), min_size=n, max_size=n))
    cols = [("time [s]", t), (f"speed [{unit}]", speed), ("soc [%]", soc), ("coolant_temp [degC]", cool)]
    order = draw(st.permutations(range(1, 4)))
    cols = [cols[0]] + [cols[i] for i in order]
    text = ",".join(c for c, _ in cols) + "\n" + "".join(
        ",".join(repr(float(v[k])) for _, v in cols) + "\n" for k in range(n))
    expected = {"speed_mps": [s * SPEED_UNITS[unit] for s in speed], "soc": [s / 100 for s in soc],
                "coolant_temp_degC": cool}
    return text, expected


@SETTINGS
@given(case=valid_csv())
def test_valid_csv_reads_back_its_content(case):
    text, expected = case
    p = _DIR / "valid.csv"
    p.write_text(text)
    log = read_log(p, fmt="csv")
    n = len(expected["soc"])
    assert list(log.data.index) == [float(k) for k in range(n)]
    for ch, vals in expected.items():
        np.testing.assert_allclose(log.data[ch].to_numpy(), vals, rtol=1e-12, atol=1e-12, err_msg=ch)


def _motorola16(data: bytearray, msb_byte: int, raw: int):
    data[msb_byte], data[msb_byte + 1] = raw >> 8, raw & 0xFF


@st.composite
def valid_candump(draw):
    """A candump log of three Prius messages (speed, coolant, SOC) once a second, encoded here by hand from
    the DBC's layout (big-endian, scale, offset); returns (text, expected channel -> values)."""
    n = draw(st.integers(2, 20))
    t0 = draw(st.floats(0, 2e9, allow_nan=False))
    v_raw = draw(st.lists(st.integers(0, 25000), min_size=n, max_size=n))  # 0.01 km/h, bytes 5-6
    T_raw = draw(st.lists(st.integers(0, 180), min_size=n, max_size=n))  # 1 degC offset -40, byte 1
    s_raw = draw(st.lists(st.integers(0, 200), min_size=n, max_size=n))  # 0.5 %, bytes 2-3
    lines = []
    for k in range(n):
        t = f"({t0 + k:.6f}) can0"
        d = bytearray(8)
        _motorola16(d, 5, v_raw[k])
        lines.append(f"{t} 0B4#{d.hex().upper()}")
        lines.append(f"{t} 52C#00{T_raw[k]:02X}")
        d = bytearray(7)
        _motorola16(d, 2, s_raw[k])
        lines.append(f"{t} 3CB#{d.hex().upper()}")
    expected = {"speed_mps": [r * 0.01 / 3.6 for r in v_raw], "coolant_temp_degC": [r - 40.0 for r in T_raw],
                "soc": [r * 0.5 / 100 for r in s_raw]}
    return "\n".join(lines) + "\n", expected


@SETTINGS
@given(case=valid_candump())
def test_valid_candump_reads_back_its_content(case):
    text, expected = case
    p = _DIR / "valid.log"
    p.write_text(text)
    log = read_log(p, fmt="candump")
    assert len(log.data) == len(expected["soc"])
    for ch, vals in expected.items():
        np.testing.assert_allclose(log.data[ch].to_numpy(), vals, rtol=1e-9, atol=1e-9, err_msg=ch)
