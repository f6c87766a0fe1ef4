"""OBD-II service 01 responses in candump logs: values of a known drive polled the way OBD tools poll.

The responses are encoded here with the SAE J1979 formulas written out by hand (not through our DBC), so
a wrong scaling in ``obd2_mode01.dbc`` fails these tests.
"""
from pathlib import Path

import cantools
import numpy as np
import pytest

from calib.errors import LogFormatError
from calib.ingest import read_log, read_streams
from calib.ingest.common import AFR_STOICH
from testcars.fabricate import fabricate_streams
from calib.ingest.obd import OBD2_DBC, PIDS, classify, decode_obd
from calib.ingest.writers import can_frames
from calib.units import GASOLINE_DENSITY_KG_PER_L

#: PID -> the drive quantity it reports and its SAE J1979 encoding (value -> data bytes).
LEVEL = 63.0  # fuel tank level, %


def _encode(pid, x):
    if pid in (0x05, 0x46):
        return [int(round(x + 40))]
    if pid == 0x0C:
        r = int(round(x * 4))
        return [r >> 8, r & 0xFF]
    if pid == 0x0D:
        return [int(round(x * 3.6))]  # m/s -> km/h
    if pid == 0x10:
        r = int(round(x * 100))
        return [r >> 8, r & 0xFF]
    if pid in (0x2F, 0x5B):
        return [int(round(x * 255 / 100))]
    if pid == 0x5E:
        r = int(round(x / GASOLINE_DENSITY_KG_PER_L * 3.6 * 20))  # g/s -> L/h, 0.05 L/h per bit
        return [r >> 8, r & 0xFF]
    raise KeyError(pid)


#: Half the quantisation step of each PID in the channel's unit: the largest honest decoding error.
HALF_STEP = {0x05: 0.5, 0x46: 0.5, 0x0C: 0.125, 0x0D: 0.5 / 3.6, 0x5B: 0.5 / 255,
             0x5E: 0.025 * GASOLINE_DENSITY_KG_PER_L / 3.6}
CHANNEL_OF = {0x05: "coolant_temp_degC", 0x0C: "engine_speed_rpm", 0x0D: "speed_mps", 0x46: "ambient_temp_degC",
              0x5B: "soc", 0x5E: "fuel_rate_g_per_s"}


def _truth(streams, pid, t):
    """The drive's value for ``pid`` at time ``t`` (its channel's unit; % for the tank level, g/s for MAF)."""
    if pid == 0x2F:
        return LEVEL
    if pid == 0x10:
        fuel = streams["fuel_rate_g_per_s"]
        return float(np.interp(t, fuel.index.to_numpy(), fuel.to_numpy())) * AFR_STOICH
    s = streams[CHANNEL_OF[pid]]
    x = float(np.interp(t, s.index.to_numpy(), s.to_numpy()))
    return x * 100 if pid == 0x5B else x


def _line(t, iface, can_id, data, extended=False):
    ident = f"{can_id:08X}" if extended else f"{can_id:03X}"
    return (t, f"({t:.6f}) {iface} {ident}#{bytes(data).hex().upper()}\n")


def obd_polling(streams, pids, t_end, seed=1, t0=1_700_000_000.0, ecu=None, iface="can0"):
    """Request/response lines of a tester polling ``pids`` in turn, each PID every 5-15 s.

    Returns (lines, written): ``written[pid]`` = list of (t from log start, true value, decoded-unit value).
    ``ecu`` maps a PID to the response ID that answers it (default 0x7E8).
    """
    rng = np.random.default_rng(seed)
    lines, written = [], {p: [] for p in pids}
    t, k = 0.5, 0
    while t < t_end:
        pid = pids[k % len(pids)]
        lines.append(_line(t0 + t, iface, 0x7DF, [0x02, 0x01, pid, 0x55, 0x55, 0x55, 0x55, 0x55]))
        tr = round(t + rng.uniform(0.01, 0.05), 6)
        x = _truth(streams, pid, tr)
        body = [0x41, pid] + _encode(pid, x)
        rid = (ecu or {}).get(pid, 0x7E8)
        lines.append(_line(t0 + tr, iface, rid, [len(body)] + body + [0x55] * (7 - len(body))))
        written[pid].append((tr, x))
        k += 1
        t += rng.uniform(0.7, 1.8)  # 8 PIDs in turn: each one every ~6-14 s
    return lines, written


def dbc_lines(streams, t0=1_700_000_000.0, iface="can0"):
    """The Prius DBC frames of ``streams`` (battery channels), as candump lines."""
    fr = can_frames(streams)
    return [_line(t0 + fr["t"][k], iface, int(fr["id"][k]), fr["data"][k, : fr["dlc"][k]]) for k in range(len(fr["t"]))]


def write_log(path, lines):
    lines = sorted(lines, key=lambda x: x[0])
    Path(path).write_text("".join(text for _, text in lines))
    return path


ALL = [0x05, 0x0C, 0x0D, 0x10, 0x2F, 0x46, 0x5B, 0x5E]


@pytest.fixture(scope="module")
def drive():
    streams, _ = fabricate_streams(420, dropout=None)
    return streams


def test_polled_pids_decode_to_the_drive_within_their_quantisation(tmp_path, drive):
    lines, written = obd_polling(drive, ALL, 420, ecu={0x5B: 0x7EA})
    battery = {c: drive[c] for c in ("bat_current_A", "bat_voltage_V")}
    both = lines + dbc_lines(battery)
    p = write_log(tmp_path / "obd.log", both)
    start = min(x[0] for x in both) - 1_700_000_000.0  # the log's clock starts at its first frame
    s, m = read_streams(p)
    assert set(s) == {"bat_current_A", "bat_voltage_V", "coolant_temp_degC", "engine_speed_rpm", "speed_mps",
                      "ambient_temp_degC", "soc", "fuel_rate_g_per_s"}
    for pid, ch in CHANNEL_OF.items():
        t_w = np.array([w[0] for w in written[pid]])
        x_w = np.array([w[1] for w in written[pid]])
        x_w = x_w / 100 if pid == 0x5B else x_w
        got = s[ch]
        # Every response is one sample, at the response's time; polled every 5-15 s.
        assert len(got) == len(t_w) and 28 <= len(t_w) <= 60, ch
        np.testing.assert_allclose(got.index.to_numpy(), t_w - start, atol=2e-6)
        assert np.abs(got.to_numpy() - x_w).max() <= HALF_STEP[pid] * (1 + 1e-9), ch
        assert m.channel_counts[ch]["read"] == m.channel_counts[ch]["kept"] == len(t_w)
        assert 5 <= np.diff(t_w).min() and np.diff(t_w).max() <= 15
    assert m.channel_sources["soc"] == "can0:OBD-II PID 0x5B HYBRID_BATTERY_REMAINING (0x7EA)"
    assert m.channel_sources["speed_mps"] == "can0:OBD-II PID 0x0D VEHICLE_SPEED (0x7E8)"
    assert m.channel_sources["bat_current_A"] == "can0:HV_BATTERY.BAT_CURRENT"
    # The battery channels from the DBC keep every sample written.
    assert len(s["bat_current_A"]) == len(drive["bat_current_A"])
    notes = "\n".join(m.notes)
    assert "engine ECU's own computed fuel rate" in notes  # 0x5E is not a flow meter: said so
    assert "PID 0x10 MAF (0x7E8) (mass air flow)" in notes and "not used: fuel comes from" in notes
    assert "PID 0x2F FUEL_LEVEL" in notes and "not a canonical channel" in notes
    n_req = len(lines) // 2
    assert f"{n_req:,} requests (no data)" in notes
    assert "fuel_rate_g_per_s" not in m.estimated


def test_maf_without_fuel_rate_gives_a_labelled_estimate(tmp_path, drive):
    lines, written = obd_polling(drive, [0x05, 0x0C, 0x10], 300)
    s, m = read_streams(write_log(tmp_path / "maf.log", lines))
    fuel = s["fuel_rate_g_per_s"]
    t_w = np.array([w[0] for w in written[0x10]])
    maf = np.array([w[1] for w in written[0x10]])
    assert len(fuel) == len(t_w)
    # MAF in 0.01 g/s steps, fuel = MAF / AFR: the drive's fuel rate within 0.005 / AFR.
    np.testing.assert_allclose(fuel.to_numpy(), maf / AFR_STOICH, atol=0.005 / AFR_STOICH + 1e-12)
    assert "fuel_rate_g_per_s" in m.estimated and "(estimate)" in m.channel_sources["fuel_rate_g_per_s"]
    assert "OBD-II PID 0x10 MAF" in m.channel_sources["fuel_rate_g_per_s"]
    assert any("ESTIMATE" in n for n in m.notes)
    # An OBD-only log (no DBC frame) is read and says so.
    assert any("only OBD-II responses decoded" in n for n in m.notes)


def test_vectorised_decode_equals_cantools(tmp_path, drive):
    lines, _ = obd_polling(drive, ALL, 200, seed=3)
    db = cantools.database.load_file(str(OBD2_DBC))
    msg = db.get_message_by_name("OBD2_MODE01_RESPONSE")
    frames = [bytes.fromhex(text.split("#")[1]) for _, text in lines if " 7E8#" in text]
    t = np.arange(len(frames), dtype=float)
    data = np.frombuffer(b"".join(frames), dtype=np.uint8).reshape(-1, 8)
    res = decode_obd({(False, 0x7E8): (t, data, np.full(len(t), 8))})
    for pid, (tt, vv, _) in res.series.items():
        ref = [msg.decode(frames[int(k)])[PIDS[pid][0]] for k in tt]
        np.testing.assert_allclose(vv, ref, rtol=1e-12)
    assert res.n_decoded == len(frames)


def test_what_is_not_decoded_is_named(tmp_path):
    t0 = 100.0
    L = []
    for i in range(20):
        t = t0 + i
        L.append(_line(t, "can0", 0x7E8, [0x03, 0x41, 0x0D, 40 + i, 0x55, 0x55, 0x55, 0x55]))  # 40.. km/h
        if i % 4 == 0:  # a second ECU answers the same PID now and then, from another sensor
            L.append(_line(t + 0.01, "can0", 0x7E9, [0x03, 0x41, 0x0D, 99, 0, 0, 0, 0]))
    L.append(_line(t0 + 0.5, "can0", 0x7E8, [0x06, 0x41, 0x05, 0x7B, 0x46, 0x28, 0x55, 0x55]))  # two PIDs: 83, 0 degC
    L.append(_line(t0 + 0.6, "can0", 0x7E8, [0x03, 0x7F, 0x01, 0x12, 0, 0, 0, 0]))  # negative response
    L.append(_line(t0 + 0.7, "can0", 0x7E8, [0x03, 0x41, 0x0F, 0x50, 0, 0, 0, 0]))  # intake air temp: no channel
    L.append(_line(t0 + 0.8, "can0", 0x7E8, [0x10, 0x14, 0x49, 0x02, 0x01, 0x31, 0x4E, 0x34]))  # VIN, ISO-TP
    L.append(_line(t0 + 0.81, "can0", 0x7E8, [0x21, 0x41, 0x4C, 0x33, 0x41, 0x50, 0x37, 0x44]))
    L.append(_line(t0 + 0.82, "can0", 0x7E8, [0x22, 0x43, 0x31, 0x32, 0x33, 0x34, 0x35, 0x36]))
    for t in (t0 + 0.9, t0 + 1.9):  # 29-bit responses
        L.append(_line(t, "can0", 0x18DAF110, [0x03, 0x41, 0x46, 0x25, 0, 0, 0, 0], extended=True))
    s, m = read_streams(write_log(tmp_path / "odd.log", L))
    notes = "\n".join(m.notes)
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), (40 + np.arange(20)) / 3.6)
    assert "PID 0x0D VEHICLE_SPEED: the answers of 0x7E8 (20) are used; also answered by 0x7E9 (5), not merged" in notes
    assert s["coolant_temp_degC"].tolist() == [83.0]
    assert s["ambient_temp_degC"].tolist() == [-3.0, -3.0]
    assert m.channel_sources["ambient_temp_degC"] == "can0:OBD-II PID 0x46 AMBIENT_TEMP (0x18DAF110)"
    assert "also answered by 0x7E8 (1)" in notes
    assert "1 negative responses" in notes
    assert "PIDs not decoded (not in obd2_mode01.dbc): 0x0F (1)" in notes
    assert "3 multi-frame (ISO-TP) response frames (1 responses) skipped" in notes


def test_dbc_channel_wins_over_the_same_obd_pid(tmp_path, drive):
    lines, written = obd_polling(drive, [0x0D, 0x05], 120)
    p = write_log(tmp_path / "both.log", lines + dbc_lines({"speed_mps": drive["speed_mps"]}))
    s, m = read_streams(p)
    assert m.channel_sources["speed_mps"] == "can0:SPEED.SPEED"
    assert len(s["speed_mps"]) == len(drive["speed_mps"])  # no OBD sample merged in
    assert any("PID 0x0D" in n and "not used: speed_mps comes from can0:SPEED.SPEED" in n for n in m.notes)
    assert m.channel_sources["coolant_temp_degC"].startswith("can0:OBD-II PID 0x05")


def test_obd_on_another_bus_and_bus_choice(tmp_path, drive):
    lines, _ = obd_polling(drive, [0x05], 60, iface="can1")
    p = write_log(tmp_path / "b.log", lines + dbc_lines({"speed_mps": drive["speed_mps"]}))
    s, m = read_streams(p)
    assert "coolant_temp_degC" in s and m.channel_sources["coolant_temp_degC"].startswith("can1:")
    s, m = read_streams(p, bus="can0")
    assert "coolant_temp_degC" not in s
    assert any(n.startswith("bus can1:") and "OBD-II response frames not decoded; pass --bus can1" in n
               for n in m.notes)
    with pytest.raises(LogFormatError, match=r"bus 'can7'.*can0 \(.*can1 \("):
        read_streams(p, bus="can7")


def test_classify_ids():
    assert classify(0x7E8, False) == classify(0x18DAF117, True) == 2
    assert classify(0x7DF, False) == classify(0x7E0, False) == classify(0x18DB33F1, True) == 4
    assert classify(0x18DA10F1, True) == 4
    assert classify(0x7E8, True) == classify(0x0B4, False) == classify(0x7F0, False) == 0


def test_parked_obd_log_reads_as_a_drivelog(tmp_path, drive):
    lines, _ = obd_polling(drive, ALL, 420)
    log = read_log(write_log(tmp_path / "p.log", lines))
    assert log.meta.start_time.startswith("2023-11-14")
    assert {"coolant_temp_degC", "engine_speed_rpm", "fuel_rate_g_per_s"} <= set(log.channels())
