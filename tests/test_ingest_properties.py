"""Property-based: random and mutated input to every reader either reads or raises IptmError.

Nothing else (struct.error, zlib.error, UnicodeDecodeError, KeyError, pint errors...) may escape.
"""
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib.drivelog import DriveLog
from calib.errors import IptmError
from calib.ingest import read_log
from calib.ingest.fabricate import fabricate_streams
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
