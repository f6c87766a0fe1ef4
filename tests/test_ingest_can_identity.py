"""A CAN message is (bus, frame type, ID): other buses and 29-bit look-alikes of 11-bit DBC IDs are not merged."""
from pathlib import Path

import can
import numpy as np
import pytest

from calib.errors import LogFormatError
from calib.ingest import read_log, read_streams
from calib.ingest.canlog import read_can_streams
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import can_frames

ROOT = Path(__file__).resolve().parents[1]
WINTER = ROOT / "logs" / "winter_warm_restart.log"
T0 = 1_700_000_000.0


def _lines(frames, iface, t_shift=0.0, extended=False):
    """candump -L lines ``(t, text)`` of :func:`can_frames` output on ``iface``."""
    out = []
    for k in range(len(frames["t"])):
        ident = f"{int(frames['id'][k]):08X}" if extended else f"{int(frames['id'][k]):03X}"
        t = T0 + frames["t"][k] + t_shift
        out.append((t, f"({t:.6f}) {iface} {ident}#{bytes(frames['data'][k, : frames['dlc'][k]]).hex().upper()}\n"))
    return out


def _write(path, lines):
    path.write_text("".join(text for _, text in sorted(lines, key=lambda x: x[0])))
    return path


def _distance_km(log):
    return float(np.nansum(log.data["speed_mps"].to_numpy(float)) * log.dt / 1000)


@pytest.fixture(scope="module")
def drives():
    a, _ = fabricate_streams(120, seed=0, dropout=None, channels=["speed_mps", "soc"])
    b, _ = fabricate_streams(60, seed=5, dropout=None, channels=["speed_mps", "soc"])
    return a, b


def test_second_bus_is_not_merged(tmp_path, drives):
    a, b = drives
    p = _write(tmp_path / "two.log", _lines(can_frames(a), "can0") + _lines(can_frames(b), "can1", 0.0003))
    s, m = read_streams(p)
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), a["speed_mps"].to_numpy(), atol=0.005 / 3.6)
    assert len(s["speed_mps"]) == len(a["speed_mps"]) and len(s["soc"]) == len(a["soc"])
    assert m.channel_counts["speed_mps"]["read"] == len(a["speed_mps"])
    assert m.channel_sources["speed_mps"] == "can0:SPEED.SPEED"
    n_b = len(b["speed_mps"]) + len(b["soc"])
    assert f"bus can1: {n_b:,} frames with DBC IDs not decoded; pass --bus can1 to read that bus" in m.notes
    assert any(n.startswith("DBC prius_iptm.dbc decoded on bus can0") and "most of its messages" in n for n in m.notes)
    # The other bus on request: its own drive, and can0 named.
    s1, m1 = read_streams(p, bus="can1")
    np.testing.assert_allclose(s1["speed_mps"].to_numpy(), b["speed_mps"].to_numpy(), atol=0.005 / 3.6)
    assert m1.channel_sources["soc"] == "can1:BATTERY_STATE.SOC"
    assert any(n.startswith("bus can0:") and "pass --bus can0" in n for n in m1.notes)
    with pytest.raises(LogFormatError, match=r"on bus 'can2'.*can0 \(.*frames\), can1 \("):
        read_can_streams(p, fmt="candump", bus="can2")


def test_winter_log_with_a_copy_on_can1_keeps_its_distance(tmp_path):
    """The bundled drive plus a copy of its frames on can1 with other speeds: the distance is the drive's."""
    out = []
    with open(WINTER) as fh:
        for line in fh:
            if not line.startswith("("):
                continue
            stamp, _, frame = line.split()
            t = float(stamp[1:-1])
            out.append((t, line))
            idstr, _, data = frame.partition("#")
            if idstr == "0B4":  # other speeds on can1: a third of can0's
                raw = bytearray(bytes.fromhex(data))
                raw[5:7] = (int.from_bytes(raw[5:7], "big") // 3).to_bytes(2, "big")
                data = raw.hex().upper()
            out.append((t + 1e-6, f"({t + 1e-6:.6f}) can1 {idstr}#{data}\n"))
    p = _write(tmp_path / "winter_two_bus.log", out)
    single = read_log(WINTER)
    both = read_log(p)
    assert _distance_km(single) == pytest.approx(4.87, abs=0.005)
    assert _distance_km(both) == pytest.approx(_distance_km(single), rel=1e-9)
    assert len(both.data) == len(single.data)
    n_frames = sum(1 for t, line in out if " can1 " in line and not line.split()[2].startswith("6FF"))
    assert f"bus can1: {n_frames:,} frames with DBC IDs not decoded; pass --bus can1 to read that bus" in both.meta.notes
    # Equal frame counts on both buses: the first by name, and the note says to choose.
    assert any("as many as bus can1" in n for n in both.meta.notes)
    other = read_log(p, bus="can1")
    assert _distance_km(other) == pytest.approx(_distance_km(single) / 3, rel=0.01)


def test_extended_id_equal_to_a_standard_dbc_id_is_not_that_message(tmp_path, drives):
    a, b = drives
    p = _write(tmp_path / "ext.log", _lines(can_frames(a), "can0")
               + _lines(can_frames({"speed_mps": b["speed_mps"]}), "can0", 0.0004, extended=True))
    s, m = read_streams(p)
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), a["speed_mps"].to_numpy(), atol=0.005 / 3.6)
    assert len(s["speed_mps"]) == len(a["speed_mps"])
    n = len(b["speed_mps"])
    assert (f"bus can0: {n:,} extended (29-bit) frames with ID 0x000000B4 not decoded: the DBC's SPEED with that "
            "ID value is a standard (11-bit) frame") in m.notes
    # Only look-alikes in the log: refused, and the message says why.
    q = _write(tmp_path / "only_ext.log", _lines(can_frames({"speed_mps": b["speed_mps"]}), "can0", extended=True))
    with pytest.raises(LogFormatError, match=r"other frame type"):
        read_streams(q)


def test_extended_dbc_message_ignores_standard_frames(tmp_path):
    """The same rule the other way: a 29-bit DBC message is not decoded from an 11-bit frame."""
    dbc = tmp_path / "ext.dbc"
    dbc.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: X\n\n'
                   'BO_ 2147483828 SPEED: 8 X\n SG_ SPEED : 47|16@0+ (0.01,0) [0|655.35] "km/h" X\n')
    lines = [(T0 + i * 0.1, f"({T0 + i * 0.1:.6f}) can0 000000B4#0000000000{1000 + i:04X}00\n") for i in range(10)]
    lines += [(T0 + i * 0.1 + 0.01, f"({T0 + i * 0.1 + 0.01:.6f}) can0 0B4#0000000000FFFE00\n") for i in range(10)]
    s, m = read_streams(_write(tmp_path / "x.log", lines), dbc=dbc)
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), (1000 + np.arange(10)) * 0.01 / 3.6)
    assert any("10 standard (11-bit) frames with ID 0x0B4 not decoded" in n for n in m.notes)


@pytest.mark.parametrize("fmt", ["asc", "blf"])
def test_python_can_formats_keep_channels_and_frame_types_apart(tmp_path, drives, fmt):
    """ASC and BLF written by python-can: channels (numbered from 1 in the file) and the extended flag."""
    a, b = drives
    fa, fb = can_frames(a), can_frames({"speed_mps": b["speed_mps"]})
    msgs = []
    for fr, channel, ext, dt in ((fa, 0, False, 0.0), (fb, 1, False, 0.0002), (fb, 0, True, 0.0004)):
        for k in range(len(fr["t"])):
            msgs.append(can.Message(timestamp=T0 + fr["t"][k] + dt, arbitration_id=int(fr["id"][k]), is_extended_id=ext,
                                    data=bytes(fr["data"][k, : fr["dlc"][k]]), channel=channel))
    msgs.sort(key=lambda x: x.timestamp)
    p = tmp_path / f"two.{fmt}"
    writer = can.BLFWriter(str(p)) if fmt == "blf" else can.ASCWriter(str(p))
    for msg in msgs:
        writer.on_message_received(msg)
    writer.stop()
    s, m = read_streams(p)
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), a["speed_mps"].to_numpy(), atol=0.005 / 3.6)
    assert m.channel_sources["speed_mps"] == "1:SPEED.SPEED"
    n = len(b["speed_mps"])
    assert f"bus 2: {n:,} frames with DBC IDs not decoded; pass --bus 2 to read that bus" in m.notes
    assert any(f"bus 1: {n:,} extended (29-bit) frames with ID 0x000000B4" in x for x in m.notes)
    s2, m2 = read_streams(p, bus=2)
    np.testing.assert_allclose(s2["speed_mps"].to_numpy(), b["speed_mps"].to_numpy(), atol=0.005 / 3.6)
