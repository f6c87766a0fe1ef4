"""CSV logs written the way real loggers and OBD apps write them, each built from a known drive.

The known drive is the bundled ``logs/winter_warm_restart.csv`` (its first three minutes, 14 channels at
their own rates) as :func:`calib.ingest.read_streams` reads it. Each test writes it again in another shape
(one row per channel at shared times, a long table, ms/us/ns clocks, dates, Unix time, Torque Pro and Car
Scanner exports, a clock that steps back) and checks that every channel comes back with the samples and
values that were written, or that the loss is named.
"""
import datetime as dt
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib.drivelog import CHANNELS
from calib.errors import ChannelLossWarning, LogDamageWarning, LogFormatError
from calib.ingest import read_streams
from calib.ingest.common import AFR_STOICH, HUMAN_NAME
from calib.ingest.writers import CSV_UNITS
from calib.units import convert

LOGS = Path(__file__).resolve().parents[1] / "logs"
T_END = 180.0
BASE = dt.datetime(2026, 1, 5, 7, 31, 2, 250000)
CHANNELS_UNIT = {ch: unit for ch, (unit, _) in CHANNELS.items()}


@pytest.fixture(scope="module")
def drive():
    """The known drive: channel -> samples (canonical units) of the first three minutes."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogDamageWarning)
        streams, _ = read_streams(LOGS / "winter_warm_restart.csv")
    out = {ch: s[s.index <= T_END] for ch, s in streams.items()}
    assert len(out) == 14 and all(len(s) > 50 for s in out.values())
    return out


def _read(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogDamageWarning)  # an intact file must not be reported as damaged
        return read_streams(path, **kw)


def _same(streams, expected, rtol=0.0):
    """Every channel holds exactly the expected samples (times to the microsecond streams are kept at)."""
    assert set(streams) == set(expected)
    for ch, e in expected.items():
        s = streams[ch]
        assert len(s) == len(e), (ch, len(s), len(e))
        np.testing.assert_allclose(s.index.to_numpy(), e.index.to_numpy(), rtol=0, atol=1.01e-6, err_msg=ch)
        np.testing.assert_allclose(s.to_numpy(), e.to_numpy(), rtol=rtol, atol=0, err_msg=ch)


def _quantised(drive, step):
    """The drive with sample times rounded to ``step`` s (samples of a channel meeting at one time averaged)."""
    out = {}
    for ch, s in drive.items():
        t = np.round(np.round(s.index.to_numpy() / step) * step, 6)
        out[ch] = pd.Series(s.to_numpy(), index=t).groupby(level=0).mean()
    return out


def _wide_text(drive, time_header, fmt_time, sep=","):
    """One row per distinct time, canonical column names (their unit is in the name), empty cells."""
    df = pd.DataFrame(drive).sort_index()
    lines = [sep.join([time_header] + list(df.columns))]
    for t, row in zip(df.index, df.to_numpy()):
        lines.append(sep.join([fmt_time(t)] + ["" if np.isnan(v) else repr(float(v)) for v in row]))
    return "\n".join(lines) + "\n"


def _rows(drive):
    """Every sample as (time, channel, value), in time order."""
    rows = [(float(t), ch, float(v)) for ch, s in drive.items() for t, v in zip(s.index, s.to_numpy())]
    return sorted(rows, key=lambda r: (r[0], r[1]))


# ----------------------------------------------------------------------------------------------------
# rows sharing a time
# ----------------------------------------------------------------------------------------------------
def test_channel_per_row_at_one_instant_keeps_every_channel(tmp_path):
    """The example in the field report: each channel on its own row at the same instant."""
    p = tmp_path / "perrow.csv"
    p.write_text("time [s],speed [km/h],fuel_rate [g/s]\n0.0,10,\n0.0,,0.5\n1.0,13,\n1.0,,0.8\n")
    streams, meta = _read(p)
    np.testing.assert_allclose(streams["speed_mps"].to_numpy(), [10 / 3.6, 13 / 3.6])
    np.testing.assert_allclose(streams["fuel_rate_g_per_s"].to_numpy(), [0.5, 0.8])
    assert streams["speed_mps"].index.tolist() == [0.0, 1.0]
    assert not meta.damage
    assert meta.channel_counts["speed_mps"]["kept"] == 2 and meta.channel_counts["fuel_rate_g_per_s"]["kept"] == 2


def test_drive_written_channel_per_row_on_a_01s_clock(tmp_path, drive):
    """Every sample on its own row, time rounded to 0.1 s: rows share times; nothing is lost, a channel
    sampled twice within one 0.1 s step becomes the mean of the two and the merge is counted."""
    rows = [(round(t, 1), ch, v) for t, ch, v in _rows(drive)]
    rows.sort(key=lambda r: r[0])  # within one time the channels stay in any order
    chans = list(drive)
    lines = ["time [s]," + ",".join(chans)]
    for t, ch, v in rows:
        cells = [""] * len(chans)
        cells[chans.index(ch)] = repr(float(v))
        lines.append(f"{t:.1f}," + ",".join(cells))
    p = tmp_path / "rounded.csv"
    p.write_text("\n".join(lines) + "\n")
    streams, meta = _read(p)
    expected = _quantised(drive, 0.1)
    _same(streams, expected, rtol=1e-12)
    for ch in drive:
        c = meta.channel_counts[ch]
        assert c["read"] == len(drive[ch]) and c["merged"] == len(drive[ch]) - len(expected[ch]), (ch, c)
    assert sum(len(s) for s in streams.values()) > 0.99 * len(rows)


@pytest.mark.parametrize("unit,scale", [("s", 1.0), ("ms", 1e3), ("us", 1e6), ("ns", 1e9)])
def test_clock_in_s_ms_us_ns_reads_the_same_drive(tmp_path, drive, unit, scale):
    if unit in ("us", "ns"):
        fmt = lambda t: str(int(round(t * scale)))  # noqa: E731 - integer ticks, as such clocks are written
    else:
        fmt = lambda t: repr(t * scale)  # noqa: E731
    p = tmp_path / f"clock_{unit}.csv"
    p.write_text(_wide_text(drive, f"time [{unit}]", fmt))
    streams, meta = _read(p)
    _same(streams, drive)
    assert not meta.start_time  # a clock from the start of the log is not a date


# ----------------------------------------------------------------------------------------------------
# long format
# ----------------------------------------------------------------------------------------------------
def test_long_table_with_a_unit_per_row(tmp_path, drive):
    """``time, signal, value, unit``: human names, the logger's units, coolant in degF for half the drive."""
    lines = ["time [s],signal,value,unit"]
    for t, ch, v in _rows(drive):
        unit = CSV_UNITS[ch]
        if ch == "coolant_temp_degC" and t > T_END / 2:
            unit = "degF"
        lines.append(f"{t!r},{HUMAN_NAME[ch]},{float(convert(v, CHANNELS_UNIT[ch], unit))!r},{unit}")
    p = tmp_path / "long.csv"
    p.write_text("\n".join(lines) + "\n")
    streams, meta = _read(p)
    _same(streams, drive, rtol=1e-12)
    assert meta.format == "csv/long"
    assert any("coolant_temp" in n and "2 units" in n for n in meta.notes)
    assert meta.channel_counts["soc"]["kept"] == len(drive["soc"])


def test_long_table_in_ms_with_units_from_the_column_map(tmp_path, drive):
    sub = {ch: drive[ch] for ch in ("speed_mps", "coolant_temp_degC", "bat_current_A")}
    names = {"speed_mps": "VehSpd", "coolant_temp_degC": "ECT", "bat_current_A": "HV_I"}
    units = {"speed_mps": "km/h", "coolant_temp_degC": "degC", "bat_current_A": "A"}
    lines = ["ts [ms];name;value"]
    for t, ch, v in _rows(sub):
        lines.append(f"{t * 1000!r};{names[ch]};{float(convert(v, CHANNELS_UNIT[ch], units[ch]))!r}")
    lines.append(f"{T_END * 1000};GPS_Lat;48.1")
    p = tmp_path / "long_ms.csv"
    p.write_text("\n".join(lines) + "\n")
    cmap = {"ts [ms]": "time [ms]", **{names[ch]: f"{ch} [{units[ch]}]" for ch in sub}}
    streams, meta = _read(p, column_map=cmap)
    t0 = min(s.index[0] for s in sub.values())  # the log starts at its first row
    _same(streams, {ch: pd.Series(s.to_numpy(), index=s.index - t0) for ch, s in sub.items()}, rtol=1e-12)
    assert any("ignored signals: GPS_Lat" in n for n in meta.notes)
    with pytest.raises(LogFormatError, match="'VehSpd'.*no unit|no unit for signal 'VehSpd'"):
        read_streams(p, column_map={"ts [ms]": "time [ms]", "VehSpd": "speed_mps"})


# ----------------------------------------------------------------------------------------------------
# absolute clocks
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout,zone", [("%Y-%m-%dT%H:%M:%S.%f", ""), ("%Y-%m-%d %H:%M:%S.%f", "+01:00")])
def test_iso_datetimes(tmp_path, drive, layout, zone):
    stamp = lambda t: (BASE + dt.timedelta(seconds=round(t, 3))).strftime(layout)[:-3] + zone  # noqa: E731
    p = tmp_path / "iso.csv"
    p.write_text(_wide_text(drive, "timestamp", stamp))
    streams, meta = _read(p)
    _same(streams, _quantised(drive, 1e-3))
    start = pd.Timestamp(BASE.isoformat() + zone)
    assert pd.Timestamp(meta.start_time) == start
    assert (pd.Timestamp(meta.start_time).tzinfo is not None) == bool(zone)
    assert any("dates and times" in n and ("UTC" if zone else "local time") in n for n in meta.notes)


def test_epoch_milliseconds_without_a_unit(tmp_path, drive):
    epoch_ms = int(pd.Timestamp(BASE, tz="UTC").timestamp() * 1000)
    p = tmp_path / "epoch.csv"
    p.write_text(_wide_text(drive, "timestamp", lambda t: str(epoch_ms + int(round(t * 1000)))))
    streams, meta = _read(p)
    _same(streams, _quantised(drive, 1e-3))
    assert pd.Timestamp(meta.start_time) == pd.Timestamp(BASE, tz="UTC")
    assert any("Unix time in ms" in n for n in meta.notes)


def test_epoch_seconds_with_a_unit_set_the_start_time(tmp_path, drive):
    epoch = pd.Timestamp(BASE, tz="UTC").timestamp()
    p = tmp_path / "epoch_s.csv"
    p.write_text(_wide_text(drive, "time [s]", lambda t: f"{epoch + round(t, 3):.3f}"))
    streams, meta = _read(p)
    _same(streams, _quantised(drive, 1e-3))
    assert pd.Timestamp(meta.start_time) == pd.Timestamp(BASE, tz="UTC")


def test_plain_numbers_without_a_unit_are_refused(tmp_path):
    p = tmp_path / "nounit.csv"
    p.write_text("time,speed [km/h]\n0,1\n1000,2\n")
    with pytest.raises(LogFormatError, match="no unit for time column 'time'.*time \\[ms\\]"):
        read_streams(p)


# ----------------------------------------------------------------------------------------------------
# OBD apps
# ----------------------------------------------------------------------------------------------------
#: PIDs polled in turn, one every 0.5 s (each PID about every 3 s, as a phone app over Bluetooth does).
_POLLED = ("engine_speed_rpm", "speed_mps", "coolant_temp_degC", "maf", "ambient_temp_degC", "volt12", "load")


def _polled(drive):
    """[(t, pid, value in canonical units)]: the drive as an app polling one PID every 0.5 s sees it."""
    fuel = drive["fuel_rate_g_per_s"]
    out = []
    for k, t in enumerate(np.arange(0.0, T_END, 0.5)):
        pid = _POLLED[k % len(_POLLED)]
        if pid == "maf":
            v = float(fuel.iloc[np.searchsorted(fuel.index, t)]) * AFR_STOICH
        elif pid in ("volt12", "load"):
            v = 13.8 if pid == "volt12" else 25.0
        else:
            s = drive[pid]
            v = float(s.iloc[min(np.searchsorted(s.index, t), len(s) - 1)])
        out.append((float(t), pid, v))
    return out


def _expected_polled(polled):
    exp = {}
    for t, pid, v in polled:
        if pid in ("volt12", "load"):
            continue
        ch = "fuel_rate_g_per_s" if pid == "maf" else pid
        exp.setdefault(ch, []).append((t, v / AFR_STOICH if pid == "maf" else v))
    return {ch: pd.Series([v for _, v in tv], index=[t for t, _ in tv]) for ch, tv in exp.items()}


def test_torque_pro_export(tmp_path, drive):
    polled = _polled(drive)
    cols = {"engine_speed_rpm": "Engine RPM(rpm)", "speed_mps": "Speed (OBD)(km/h)",
            "coolant_temp_degC": "Engine Coolant Temperature(°C)", "maf": "Mass Air Flow Rate(g/s)",
            "ambient_temp_degC": "Ambient air temp(°C)", "volt12": "Voltage (Control Module)(V)",
            "load": "Engine Load(%)"}
    scale = {"speed_mps": 3.6}
    header = "GPS Time, Device Time, Longitude, Latitude,GPS Speed (Meters/second)," + ",".join(cols.values())
    lines = [header]
    for i, (t, pid, v) in enumerate(polled):
        when = BASE + dt.timedelta(seconds=t)
        gps = "-" if i < 20 else when.strftime("%a %b %d %H:%M:%S GMT+01:00 %Y")
        cells = ["-"] * len(cols)
        cells[list(cols).index(pid)] = repr(v * scale.get(pid, 1.0))
        lines.append(", ".join([gps, when.strftime("%d-%b-%Y %H:%M:%S.%f")[:-3], "-", "-", "-"]) + ","
                     + ",".join(cells))
    lines.insert(120, header)  # logging resumed into the same file: Torque writes its header again
    p = tmp_path / "trackLog.csv"
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    streams, meta = _read(p)
    _same(streams, _expected_polled(polled), rtol=1e-12)
    assert meta.format == "csv/torque"
    assert pd.Timestamp(meta.start_time) == pd.Timestamp(BASE)
    assert "fuel_rate_g_per_s" in meta.estimated and "ESTIMATE" in meta.estimated["fuel_rate_g_per_s"]
    assert "bat_voltage_V" not in streams
    assert any("Voltage (Control Module)" in n and "12-V" in n for n in meta.notes)
    assert any("GPS Time" in n for n in meta.notes)
    assert any("repeating the header" in n for n in meta.notes)


def test_car_scanner_export(tmp_path, drive):
    polled = _polled(drive)
    pids = {"engine_speed_rpm": ("Engine RPM", "rpm", 1.0), "speed_mps": ("Vehicle speed", "km/h", 3.6),
            "coolant_temp_degC": ("Engine coolant temperature", "\u2103", 1.0),
            "maf": ("MAF air flow rate", "g/sec", 1.0), "ambient_temp_degC": ("Ambient air temperature", "°C", 1.0),
            "volt12": ("Control module voltage", "V", 1.0), "load": ("Calculated engine load value", "%", 1.0)}
    lines = ['"SECONDS";"PID";"VALUE";"UNITS";"LATITUDE";"LONGTITUDE";']
    for t, pid, v in polled:
        name, unit, k = pids[pid]
        lines.append(f'"{30189.243321 + t:.6f}";"{name}";"{v * k!r}";"{unit}";"48.1";"11.5";')
        if pid == "speed_mps":
            lines.append(f'"{30189.243321 + t:.6f}";"Speed (GPS)";"{v * 3.6 + 1:.1f}";"km/h";"48.1";"11.5";')
    p = tmp_path / "2026-01-05 07-31-02.csv"
    p.write_bytes("\ufeff".encode() + ("\r\n".join(lines) + "\r\n").encode("utf-8"))
    streams, meta = _read(p)
    _same(streams, _expected_polled(polled), rtol=1e-12)
    assert meta.format == "csv/carscanner" and meta.start_time is None
    assert "fuel_rate_g_per_s" in meta.estimated
    assert any("Speed (GPS)" in n for n in meta.notes) and any("Control module voltage" in n for n in meta.notes)
    assert any("time shifted by -30189.2" in n for n in meta.notes)


# ----------------------------------------------------------------------------------------------------
# time out of order
# ----------------------------------------------------------------------------------------------------
def _wide_lines(drive):
    return _wide_text(drive, "time [s]", repr).splitlines()


def test_clock_jitter_is_sorted_not_lost(tmp_path, drive):
    lines = _wide_lines(drive)
    for k in (100, 2000, 5000):  # rows a few ms apart written in the wrong order
        lines[k], lines[k + 1] = lines[k + 1], lines[k]
    p = tmp_path / "jitter.csv"
    p.write_text("\n".join(lines) + "\n")
    streams, meta = _read(p, strict=True)
    _same(streams, drive)
    assert any("3 row(s) stepped back" in n for n in meta.notes)


@pytest.mark.parametrize("shift,what", [(-5.0, r"goes backwards by 4\.9\d\d s"), (500.0, "jumps ahead by")])
def test_time_far_out_of_order_is_named_damage(tmp_path, drive, shift, what):
    lines = _wide_lines(drive)
    k = len(lines) // 2
    cells = lines[k].split(",")
    t_bad = float(cells[0])
    cells[0] = repr(t_bad + shift)
    lines[k] = ",".join(cells)
    p = tmp_path / "backstep.csv"
    p.write_text("\n".join(lines) + "\n")
    with pytest.warns(LogDamageWarning, match=f"line {k + 1}"):
        streams, meta = read_streams(p)
    assert meta.damage["pieces_lost"] == 1 and meta.damage["where"] == [f"line {k + 1}"]
    assert "time out of order" in meta.damage["summary"]
    # Exactly the samples of that one row are lost.
    lost = {ch for ch, v in zip(drive, cells[1:]) if v}
    expected = {ch: (s[np.abs(s.index - t_bad) > 1e-9] if ch in lost else s) for ch, s in drive.items()}
    _same(streams, expected)
    with pytest.raises(LogFormatError, match=f"line {k + 1}.*{what}"):
        read_streams(p, strict=True)


# ----------------------------------------------------------------------------------------------------
# cells
# ----------------------------------------------------------------------------------------------------
def test_semicolons_and_decimal_commas(tmp_path):
    p = tmp_path / "de.csv"
    p.write_text("Zeit [s];speed [km/h];coolant_temp [degC]\n0;10,5;-3,25\n0,5;12;\n1;13,25;-3\n")
    streams, meta = _read(p, column_map={"Zeit [s]": "time [s]"})
    np.testing.assert_allclose(streams["speed_mps"].to_numpy() * 3.6, [10.5, 12, 13.25])
    np.testing.assert_allclose(streams["coolant_temp_degC"].to_numpy(), [-3.25, -3])
    assert streams["speed_mps"].index.tolist() == [0.0, 0.5, 1.0]
    assert any("decimal commas" in n for n in meta.notes)


def test_missing_markers_and_non_finite_readings(tmp_path):
    p = tmp_path / "cells.csv"
    p.write_text("time [s],speed [m/s],soc [%]\n0,1,NaN\n1,inf,50\n2,NA,\n3,1e400,51\n4,2,null\n")
    with pytest.warns(ChannelLossWarning, match="speed_mps lost 2 of 4"):
        streams, meta = _read(p)
    assert streams["speed_mps"].tolist() == [1.0, 2.0]
    np.testing.assert_allclose(streams["soc"].to_numpy(), [0.5, 0.51])
    c = meta.channel_counts["speed_mps"]
    assert (c["read"], c["nonfinite"], c["kept"]) == (4, 2, 2)  # NA is no sample, inf and 1e400 are readings
    assert meta.channel_counts["soc"]["read"] == 2


# ----------------------------------------------------------------------------------------------------
# property: any interleaving of channel rows at shared, jittered times reads back every sample
# ----------------------------------------------------------------------------------------------------
@st.composite
def channel_rows(draw):
    n = draw(st.integers(2, 40))
    times = np.cumsum(draw(st.lists(st.sampled_from([0.0, 0.0, 0.1, 0.25, 1.0]), min_size=n, max_size=n)))
    rows = []
    for t in times:
        ch = draw(st.sampled_from(["speed", "soc", "coolant_temp"]))
        rows.append([float(t), ch, draw(st.integers(0, 90))])
    for _ in range(draw(st.integers(0, 3))):  # clock jitter: neighbours swapped, never more than 1 s apart
        i = draw(st.integers(0, n - 2))
        if abs(rows[i][0] - rows[i + 1][0]) < 1.0:
            rows[i], rows[i + 1] = rows[i + 1], rows[i]
    return rows


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=channel_rows())
def test_interleaved_channel_rows_read_back_every_sample(tmp_path, rows):
    cols = {"speed": ("speed [m/s]", "speed_mps", 1.0), "soc": ("soc [%]", "soc", 0.01),
            "coolant_temp": ("coolant_temp [degC]", "coolant_temp_degC", 1.0)}
    lines = ["time [s]," + ",".join(c[0] for c in cols.values())]
    for t, ch, v in rows:
        lines.append(f"{t!r}," + ",".join(str(v) if k == ch else "" for k in cols))
    p = tmp_path / "prop.csv"
    p.write_text("\n".join(lines) + "\n")
    streams, meta = _read(p, strict=True)
    t0 = min(t for t, _, _ in rows)
    for k, (_, ch, scale) in cols.items():
        mine = [(round(t - t0, 6), v * scale) for t, c, v in rows if c == k]
        if not mine:
            assert ch not in streams
            continue
        exp = pd.Series([v for _, v in mine], index=[t for t, _ in mine]).groupby(level=0).mean()
        np.testing.assert_allclose(streams[ch].index.to_numpy(), exp.index.to_numpy(), atol=1e-9)
        np.testing.assert_allclose(streams[ch].to_numpy(), exp.to_numpy(), rtol=1e-12)
        assert meta.channel_counts[ch]["read"] == len(mine)



def test_ved_trip_without_fuel_rate_gets_the_labelled_maf_estimate(tmp_path):
    head = "DayNum,VehId,Trip,Timestamp(ms),Vehicle Speed[km/h],MAF[g/sec],Engine RPM[RPM],Fuel Rate[L/hr]"
    maf = [2.0, 3.5, 14.7, 0.0, 7.35]
    lines = [head] + [f"1.2,8,3,{1000 * k},{10 + k},{m},1200," for k, m in enumerate(maf)]
    p = tmp_path / "VED_8.csv"
    p.write_text("\n".join(lines) + "\n")
    streams, meta = _read(p)
    np.testing.assert_allclose(streams["fuel_rate_g_per_s"].to_numpy(), np.array(maf) / AFR_STOICH)
    assert "ESTIMATE" in meta.estimated["fuel_rate_g_per_s"]


def test_app_named_as_a_profile(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("GPS Time, Device Time, Longitude,Engine RPM(rpm)\n"
                 "-,05-Jan-2026 07:31:02.250,-,800\n-,05-Jan-2026 07:31:03.250,-,-\n-,05-Jan-2026 07:31:04.750,-,900\n")
    streams, meta = read_streams(p, profile="torque")
    assert streams["engine_speed_rpm"].index.tolist() == [0.0, 2.5]
    assert meta.channel_counts["engine_speed_rpm"]["read"] == 2  # '-' is no reading
    with pytest.raises(LogFormatError, match="unknown profile.*torque, carscanner"):
        read_streams(p, profile="obdlink")
