"""CAN dumps: the real RAV4 log with opendbc's DBC, our Prius DBC, vectorised decoding vs cantools."""
from pathlib import Path

import cantools
import numpy as np
import pandas as pd
import pytest

from calib.errors import LogFormatError
from calib.ingest import PRIUS_DBC, channel_report, decode_can_signals, format_report, read_log, read_streams
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import can_frames, write_streams

DATA = Path(__file__).parent / "data" / "can"
RAV4 = DATA / "toyota_rav4_2017_highway_60s.log"
TOYOTA_DBC = DATA / "toyota_2017.dbc"
WHEELS = [f"WHEEL_SPEEDS.WHEEL_SPEED_{w}" for w in ("FL", "FR", "RL", "RR")]


@pytest.fixture(scope="module")
def rav4():
    return read_log(RAV4, dbc=TOYOTA_DBC)


def test_rav4_speed_and_engine_speed_are_plausible(rav4):
    d = rav4.data
    assert rav4.meta.format == "candump" and not rav4.meta.synthetic
    assert 55 <= rav4.duration_s <= 61
    v, n = d["speed_mps"], d["engine_speed_rpm"]
    assert v.notna().all() and n.notna().all()
    assert 5 < v.min() and v.max() < 40  # highway, m/s
    assert 500 < n.min() and n.max() < 6500  # running engine, rpm
    # Smooth: a car does not change speed by more than ~4 m/s in a second, nor the engine by 1500 rpm.
    assert np.abs(np.diff(v.to_numpy())).max() < 4.0
    assert np.abs(np.diff(n.to_numpy())).max() < 1500
    assert rav4.meta.original_units == {"speed_mps": "km/h", "engine_speed_rpm": "rpm"}


def test_rav4_speed_agrees_with_mean_wheel_speed():
    res = decode_can_signals(RAV4, fmt="candump", dbc=TOYOTA_DBC, signals=["SPEED.SPEED"] + WHEELS)
    t_s, v_s = res["signals"][("SPEED", "SPEED")]
    wheels = [np.interp(t_s, *res["signals"][tuple(w.split("."))]) for w in WHEELS]
    mean_w = np.mean(wheels, axis=0)
    diff = v_s - mean_w
    assert len(t_s) > 2000
    assert abs(np.median(diff)) < 1.5  # km/h: calibration offset between ABS and speedometer
    assert np.percentile(np.abs(diff), 95) < 2.5


def test_vectorised_decode_matches_cantools():
    db = cantools.database.load_file(str(TOYOTA_DBC), strict=False)
    res = decode_can_signals(RAV4, fmt="candump", dbc=TOYOTA_DBC,
                             signals=["SPEED.SPEED", "ENGINE_RPM.RPM", "WHEEL_SPEEDS.WHEEL_SPEED_RL"])
    frames = {0xB4: [], 0x1C4: [], 0xAA: []}
    with open(RAV4) as fh:
        for line in fh:
            idstr, _, data = line.split()[2].partition("#")
            cid = int(idstr, 16)
            if cid in frames and len(frames[cid]) < 200:
                frames[cid].append(bytes.fromhex(data))
    for cid, (m, s) in {0xB4: ("SPEED", "SPEED"), 0x1C4: ("ENGINE_RPM", "RPM"), 0xAA: ("WHEEL_SPEEDS", "WHEEL_SPEED_RL")}.items():
        ref = [db.decode_message(cid, f)[s] for f in frames[cid]]
        np.testing.assert_allclose(res["signals"][(m, s)][1][: len(ref)], ref, atol=1e-9)


def test_prius_frames_decode_with_cantools():
    streams, meta = fabricate_streams(10)
    fr = can_frames(streams)
    db = cantools.database.load_file(str(PRIUS_DBC))
    k = int(np.flatnonzero(fr["id"] == 0x3CB)[0])
    dec = db.decode_message(0x3CB, bytes(fr["data"][k, : fr["dlc"][k]]))
    t = fr["t"][k]
    soc = streams["soc"]
    if t in soc.index:
        assert dec["SOC"] == pytest.approx(soc.loc[t] * 100)


def test_prius_candump_has_every_channel(tmp_path):
    streams, meta = fabricate_streams(20)
    p = write_streams(streams, meta, tmp_path / "d.candump", "candump")
    s, m = read_streams(p)
    assert set(s) == set(streams)
    assert m.synthetic and m.channel_sources["soc"] == "can0:BATTERY_STATE.SOC"


def test_jitter_sorted_and_noted(tmp_path):
    lines = ["(10.000) can0 0B4#00000000000A6600", "(10.020) can0 0B4#00000000000A6600",
             "(10.010) can0 0B4#00000000000A6600", "(10.030) can0 0B4#00000000000A6600"]
    p = tmp_path / "j.log"
    p.write_text("\n".join(lines) + "\n")
    s, m = read_streams(p)
    assert list(s["speed_mps"].index) == pytest.approx([0, 0.01, 0.02, 0.03])
    assert any("out of time order" in n for n in m.notes)
    p.write_text("(10.000) can0 0B4#00000000000A6600\n(5.000) can0 0B4#00000000000A6600\n")
    with pytest.raises(LogFormatError, match=r"line 2.*goes back"):
        read_streams(p, strict=True)


def test_user_signal_map(tmp_path):
    p = tmp_path / "w.log"
    p.write_text("".join(f"({i * 0.01:.3f}) can0 0AA#1A6F1A6F1A6F1A6F\n" for i in range(10)))
    s, _ = read_streams(p, dbc=TOYOTA_DBC, signal_map={"WHEEL_SPEEDS.WHEEL_SPEED_FL": "speed_mps"})
    assert s["speed_mps"].iloc[0] == pytest.approx((0x1A6F * 0.01 - 67.67) / 3.6)
    with pytest.raises(LogFormatError, match="not in the DBC"):
        read_streams(p, dbc=TOYOTA_DBC, signal_map={"NOPE.X": "speed_mps"})


def test_rav4_speed_is_the_four_wheel_mean_not_the_dashboard():
    """Speed comes from the wheels when all four are logged; checked against cantools' own decode."""
    s, m = read_streams(RAV4, dbc=TOYOTA_DBC)
    assert m.channel_sources["speed_mps"].startswith("mean of can0:WHEEL_SPEEDS.")
    assert any("four wheel speeds" in n for n in m.notes)
    db = cantools.database.load_file(str(TOYOTA_DBC), strict=False)
    msg = db.get_message_by_name("WHEEL_SPEEDS")
    t0, ts, mean = None, [], []
    with open(RAV4) as fh:
        for line in fh:
            stamp, _, frame = line.split()
            t = float(stamp[1:-1])
            t0 = t if t0 is None else t0
            idstr, _, data = frame.partition("#")
            if int(idstr, 16) == msg.frame_id:
                d = msg.decode(bytes.fromhex(data))
                ts.append(round(t - t0, 6))
                mean.append(np.mean([d[f"WHEEL_SPEED_{w}"] for w in ("FL", "FR", "RL", "RR")]) / 3.6)
    ref = pd.Series(mean, index=ts)
    got = s["speed_mps"]
    assert len(got) == len(ref) > 2000
    np.testing.assert_allclose(got.index.to_numpy(), ref.index.to_numpy(), atol=1e-6)
    rel = np.abs(got.to_numpy() - ref.to_numpy()) / np.maximum(ref.to_numpy(), 1.0)
    assert rel.max() < 1e-3  # 0.1 %
    # The dashboard signal (the fallback) reads about 2 % above the wheels on this car.
    res = decode_can_signals(RAV4, fmt="candump", dbc=TOYOTA_DBC, signals=["SPEED.SPEED"])
    dash = res["signals"][("SPEED", "SPEED")][1].mean() / 3.6
    assert 1.01 < dash / ref.mean() < 1.03


def test_dashboard_speed_is_the_fallback_without_wheels(tmp_path):
    p = tmp_path / "no_wheels.log"
    with open(RAV4) as fh, open(p, "w") as out:
        out.writelines(line for line in fh if " 0AA#" not in line)
    s, m = read_streams(p, dbc=TOYOTA_DBC)
    assert m.channel_sources["speed_mps"] == "can0:SPEED.SPEED"
    log = read_log(p, dbc=TOYOTA_DBC)
    assert "speed from: can0:SPEED.SPEED" in format_report(channel_report(log, s))
