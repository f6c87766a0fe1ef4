"""Bad input: one IptmError line naming the file and, where it applies, the line/message/channel."""
import pytest

from calib.errors import IptmError, LogFormatError
from calib.ingest import read_log, read_streams
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import write_streams


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    d = tmp_path_factory.mktemp("good")
    streams, meta = fabricate_streams(30)
    return {f: write_streams(streams, meta, d / f"g.{ext}", f)
            for f, ext in {"csv": "csv", "mcap": "mcap", "candump": "log", "blf": "blf"}.items()}


def _err(path, **kw) -> str:
    with pytest.raises(IptmError) as ei:
        read_log(path, **kw)
    msg = str(ei.value)
    assert "\n" not in msg, msg
    assert path.name in msg, msg
    return msg


@pytest.mark.parametrize("fmt", ["mcap", "blf"])
def test_truncated_binary_logs(good, tmp_path, fmt):
    data = good[fmt].read_bytes()
    for frac in (0.5, 0.9):
        p = tmp_path / f"trunc{int(frac * 100)}.{fmt}"
        p.write_bytes(data[: int(len(data) * frac)])
        msg = _err(p, strict=True)
        assert "corrupt or truncated" in msg or "truncated" in msg


@pytest.mark.parametrize("fmt", ["mcap", "blf"])
def test_corrupt_binary_logs(good, tmp_path, fmt):
    data = bytearray(good[fmt].read_bytes())
    for i in range(40, len(data) - 40, 97):
        data[i] ^= 0x5A
    p = tmp_path / f"corrupt.{fmt}"
    p.write_bytes(bytes(data))
    _err(p, strict=True)


def test_csv_unknown_unit(tmp_path):
    p = tmp_path / "u.csv"
    p.write_text("time [s],speed [wobbles]\n0,1\n")
    msg = _err(p)
    assert "unknown unit 'wobbles'" in msg and "column 'speed [wobbles]'" in msg


def test_csv_unit_of_wrong_dimension(tmp_path):
    p = tmp_path / "d.csv"
    p.write_text("time [s],speed [degC]\n0,1\n")
    assert "does not fit channel speed_mps" in _err(p)


def test_csv_time_far_out_of_order_is_an_error_jitter_and_repeats_are_not(tmp_path):
    p = tmp_path / "nm.csv"
    p.write_text("# x\ntime [s],speed [m/s]\n0,1\n1,1\n2,1\n0.5,1\n")
    msg = _err(p, strict=True)
    assert "line 6" in msg and "backwards by 1.500 s" in msg
    # A repeated time is two samples at one instant (their mean), a step back under 1 s is clock jitter.
    p = tmp_path / "dup.csv"
    p.write_text("time [s],speed [m/s]\n0,1\n1,1\n1,2\n0.6,4\n")
    streams, meta = read_streams(p, strict=True)
    assert streams["speed_mps"].index.tolist() == [0.0, 0.6, 1.0]
    assert streams["speed_mps"].tolist() == [1.0, 4.0, 1.5]
    assert meta.channel_counts["speed_mps"]["merged"] == 1 and not meta.damage


def test_dbc_that_does_not_match_the_frames(tmp_path):
    p = tmp_path / "other.log"
    p.write_text("".join(f"({i * 0.01:.2f}) can0 123#0011223344556677\n" for i in range(20)))
    msg = _err(p)
    assert "no frame matches the DBC prius_iptm.dbc" in msg
    p = tmp_path / "short.log"
    p.write_text("(0.00) can0 0B4#00000000000A6600\n(0.01) can0 0B4#0000\n")
    msg = _err(p, strict=True)
    assert "line 2" in msg and "SPEED" in msg


def test_bad_dbc_file(tmp_path, good):
    d = tmp_path / "bad.dbc"
    d.write_text("this is not a dbc {{{")
    with pytest.raises(LogFormatError, match="bad.dbc"):
        read_log(good["candump"], dbc=d)


@pytest.mark.parametrize("ext", ["csv", "mcap", "log", "blf", "asc", "mf4"])
def test_empty_file(tmp_path, ext):
    p = tmp_path / f"empty.{ext}"
    p.write_bytes(b"")
    assert "empty file" in _err(p)


def test_binary_file_passed_as_csv(tmp_path, good):
    p = tmp_path / "bin.csv"
    p.write_bytes(good["blf"].read_bytes())
    assert "binary" in _err(p, fmt="csv")
    p2 = tmp_path / "bin2.csv"
    p2.write_bytes(bytes(range(256)) * 4)
    assert "binary" in _err(p2)


def test_malformed_candump_line(tmp_path):
    p = tmp_path / "m.log"
    p.write_text("(0.00) can0 0B4#00000000000A6600\ngarbage here\n")
    assert "line 2" in _err(p, strict=True)


def test_unknown_format(tmp_path):
    p = tmp_path / "x.weird"
    p.write_bytes(b"\x01\x02\x03")
    assert "cannot tell the log format" in _err(p)


def test_a_bad_map_target_names_the_map_file(tmp_path):
    from calib.errors import LogFormatError
    from calib.ingest import load_map

    f = tmp_path / "m.toml"
    for text, msg in (('[signals]\n"SPEED.SPEED" = "speed_mps [km/h**9**9]"\n', "exponent 9"),
                      ('[columns]\nv = "speeed [km/h]"\n', "not a canonical channel"),
                      ('[topics."/x"]\nspeed = "speed_mps [degC]"\n', "does not fit"),
                      ('signals = 3\n', "must be a table")):
        f.write_text(text)
        with pytest.raises(LogFormatError, match=msg) as err:
            load_map(f)
        assert str(f) in str(err.value)
