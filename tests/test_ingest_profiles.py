"""Profiles for real test-data formats: Argonne D3 dynamometer files and the Vehicle Energy Dataset CSV.

The files are written here in each format's layout (column names, delimiters, units, rates) with
values whose canonical conversion is known, so every mapping and unit is checked.
"""
from __future__ import annotations

import numpy as np
import pytest

from calib.errors import LogFormatError
from calib.ingest import read_log, read_streams
from calib.ingest.profiles import detect_profile

D3_COLS = ["Time[s]_RawFacilities", "Dyno_Spd[mph]", "Eng_FuelFlow_Direct2[gps]",
           "HVBatt_SOC_high_precision_PCAN__per", "engine_coolant_temp_PCAN__C", "Cabin_Temp[C]",
           "HVAC_Power_Hioki_P3[W]", "Cell_Temp[C]", "Dyno_Tractive_Force[N]"]


def write_d3(path, n=600, t0=-2.0):
    """A 60 s D3-style file at 10 Hz starting 2 s before the test (negative times)."""
    t = t0 + np.arange(n) / 10.0
    rows = []
    for k, tk in enumerate(t):
        rows.append([f"{tk:.1f}", f"{20 + 5 * np.sin(tk / 10):.3f}", f"{0.5 + 0.001 * k:.4f}", f"{55 + 0.001 * k:.3f}",
                     f"{-6.7 + 0.1 * tk:.2f}", f"{-5 + 0.05 * tk:.2f}", "350.0", "-6.7", "120.5"])
    path.write_text("\t".join(D3_COLS) + "\n" + "\n".join("\t".join(r) for r in rows) + "\n")
    return t


VED_HEAD = ("DayNum,VehId,Trip,Timestamp(ms),Latitude[deg],Longitude[deg],Vehicle Speed[km/h],MAF[g/sec],"
            "Engine RPM[RPM],Absolute Load[%],OAT[DegC],Fuel Rate[L/hr],Air Conditioning Power[kW],"
            "Air Conditioning Power[Watts],Heater Power[Watts],HV Battery Current[A],HV Battery SOC[%],"
            "HV Battery Voltage[V],Short Term Fuel Trim Bank 1[%],Short Term Fuel Trim Bank 2[%],"
            "Long Term Fuel Trim Bank 1[%],Long Term Fuel Trim Bank 2[%]")


def write_ved(path, trips=((10, 1), (10, 2), (455, 1)), n=120, seed=0):
    """Several vehicles and trips, irregular ~1 Hz timestamps with a 20 s gap, empty cells."""
    rng = np.random.default_rng(seed)
    lines = [VED_HEAD]
    for veh, trip in trips:
        ts = np.cumsum(rng.uniform(0.7, 1.4, n) * 1000).round()
        ts[n // 2:] += 20000  # a gap
        for k, tk in enumerate(ts):
            fuel = "" if k % 7 == 3 else f"{1.8 + 0.01 * veh:.3f}"
            lines.append(",".join([f"{1.2 + tk / 8.64e7:.9f}", str(veh), str(trip), f"{tk:.0f}", "42.27", "-83.7",
                                   f"{36.0 + trip:.1f}", "3.1", "1500", "30", "-4", fuel, "", "", "0" if k % 5 else "1200",
                                   f"{-10.0 + trip:.2f}", f"{55.0 + 0.01 * k:.2f}", "220.5", "", "", "", ""]))
    path.write_text("\n".join(lines) + "\n")


def test_d3_profile_maps_units_and_notes(tmp_path):
    f = tmp_path / "62202013 Test Data.txt"
    write_d3(f)
    assert detect_profile(f) == "d3"
    streams, meta = read_streams(f)  # detected without --profile
    assert meta.format == "csv/d3"
    s = streams["speed_mps"]
    assert s.index[0] == pytest.approx(0.0)  # shifted from -2 s
    assert s.iloc[0] == pytest.approx((20 + 5 * np.sin(-0.2)) * 0.44704, rel=1e-3)
    assert streams["soc"].iloc[0] == pytest.approx(0.55)
    assert streams["fuel_rate_g_per_s"].iloc[0] == pytest.approx(0.5)
    assert streams["ambient_temp_degC"].iloc[0] == pytest.approx(-6.7)
    assert "coolant_temp_degC" in streams and "cabin_temp_degC" in streams
    assert "heater_power_W" not in streams  # HVAC electrical power is not heat from the coolant
    notes = " | ".join(meta.notes)
    assert "HVAC_Power_Hioki_P3[W]" in notes and "not heat" in notes
    assert "Dyno_Tractive_Force[N]" in notes  # ignored columns listed
    assert "shifted" in notes
    log = read_log(f, rate_hz=10.0)
    assert log.dt == pytest.approx(0.1)
    assert len(log.data) == 600


def test_d3_user_map_adds_a_channel(tmp_path):
    f = tmp_path / "d3.txt"
    write_d3(f, n=50)
    streams, meta = read_streams(f, profile="d3", column_map={"HVAC_Power_Hioki_P3[W]": "heater_power_W [W]"})
    assert streams["heater_power_W"].iloc[0] == pytest.approx(350.0)


def test_d3_rejects_time_going_backwards(tmp_path):
    f = tmp_path / "d3.txt"
    write_d3(f, n=60)
    lines = f.read_text().splitlines()
    lines[10], lines[40] = lines[40], lines[10]  # 3 s apart: the clock truly runs backwards
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match=r"line 12.*backwards by 2\.9"):
        read_streams(f, profile="d3")


def test_d3_jitter_is_sorted(tmp_path):
    f = tmp_path / "d3.txt"
    write_d3(f, n=60)
    ref, _ = read_streams(f, profile="d3")
    lines = f.read_text().splitlines()
    lines[10], lines[11] = lines[11], lines[10]  # 0.1 s apart: clock jitter, not damage
    f.write_text("\n".join(lines) + "\n")
    streams, _ = read_streams(f, profile="d3")
    for ch, s in ref.items():
        assert streams[ch].equals(s), ch


def test_ved_needs_a_selection_when_the_file_holds_many_trips(tmp_path):
    f = tmp_path / "VED_171101_week.csv"
    write_ved(f)
    assert detect_profile(f) == "ved"
    with pytest.raises(LogFormatError, match="--vehicle and --trip") as ei:
        read_streams(f)
    assert "10/1" in str(ei.value) and "455/1" in str(ei.value)
    with pytest.raises(LogFormatError, match="no vehicle '999'"):
        read_streams(f, vehicle=999, trip=1)


def test_ved_reads_one_trip_with_units_and_gaps(tmp_path):
    f = tmp_path / "VED.csv"
    write_ved(f)
    streams, meta = read_streams(f, vehicle="10", trip="2")
    assert meta.vehicle_id == "10" and any("trip 2" in n for n in meta.notes)
    assert streams["speed_mps"].iloc[0] == pytest.approx(38.0 / 3.6)
    assert streams["bat_current_A"].iloc[0] == pytest.approx(-8.0)
    assert streams["soc"].iloc[0] == pytest.approx(0.55)
    # L/h -> g/s through the gasoline density (0.74 kg/L)
    assert streams["fuel_rate_g_per_s"].iloc[0] == pytest.approx(1.9 * 0.74 / 3.6, rel=1e-6)
    n = len(streams["speed_mps"])
    assert n == 120 and len(streams["fuel_rate_g_per_s"]) < n  # empty cells are missing samples
    log = read_log(f, vehicle=10, trip=2, max_gap_s=5.0)
    gap = log.data["speed_mps"].isna()
    assert gap.sum() >= 15  # the 20 s gap is not interpolated
    only = tmp_path / "one_trip.csv"
    write_ved(only, trips=((7, 3),), n=30)
    streams, meta = read_streams(only)  # one trip: no selection needed
    assert meta.vehicle_id == "7"


def test_profile_on_a_non_matching_file_names_the_missing_columns(tmp_path):
    f = tmp_path / "x.csv"
    f.write_text("time [s],speed [km/h]\n0,1\n1,2\n")
    assert detect_profile(f) is None
    with pytest.raises(LogFormatError, match="VehId"):
        read_streams(f, profile="ved")


def test_cli_ingest_profile(tmp_path, capsys):
    from iptm.cli import main

    f = tmp_path / "VED.csv"
    write_ved(f)
    out = tmp_path / "out.parquet"
    assert main(["ingest", str(f), "--profile", "ved", "--vehicle", "455", "--trip", "1", "--out", str(out)]) == 0
    assert out.exists()
    assert "vehicle 455, trip 1" in capsys.readouterr().out
