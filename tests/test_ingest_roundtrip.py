"""The same streams written as CSV, MCAP, candump, BLF (and ASC) ingest to the same canonical table."""
import json

import numpy as np
import pandas as pd
import pytest

from calib.ingest import (channel_report, format_report, read_canonical, read_log, read_streams, to_drivelog,
                          write_canonical)
from testcars.fabricate import QUANTUM, fabricate_streams
from calib.ingest.writers import write_streams
from iptm.cli import main

FORMATS = {"csv": "csv", "mcap": "mcap", "candump": "log", "blf": "blf", "asc": "asc"}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    d = tmp_path_factory.mktemp("rt")
    streams, meta = fabricate_streams(150, seed=3)
    paths = {f: write_streams(streams, meta, d / f"drive.{ext}", f) for f, ext in FORMATS.items()}
    return streams, meta, paths


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_gives_the_same_table(written, fmt):
    streams, meta, paths = written
    ref = to_drivelog(streams, meta).data  # the truth: streams straight to the grid
    log = read_log(paths[fmt])
    assert log.meta.synthetic, fmt
    assert list(log.data.columns) == list(ref.columns)
    np.testing.assert_allclose(log.data.index, ref.index)
    pd.testing.assert_frame_equal(log.data.isna(), ref.isna())
    for ch in ref.columns:
        # Within half a quantisation step (CAN scaling steps equal the sensor steps).
        np.testing.assert_allclose(log.data[ch], ref[ch], atol=QUANTUM[ch] / 2 + 1e-9, err_msg=f"{fmt} {ch}")


def test_long_gaps_stay_nan_short_ones_are_bridged(written):
    streams, meta, paths = written
    log = read_log(paths["csv"], max_gap_s=5.0)
    cool = log.data["coolant_temp_degC"]
    # Dropout 40..52 s (12 s > 5 s): nothing invented inside it.
    inside = (cool.index > 40.5) & (cool.index < 51.5)
    assert cool[inside].isna().all()
    assert cool[(cool.index < 39) | (cool.index > 53)].notna().all()
    # With a 15 s limit the same dropout is interpolated.
    log2 = read_log(paths["csv"], max_gap_s=15.0)
    assert log2.data["coolant_temp_degC"].notna().all()


def test_rate_is_configurable(written):
    _, _, paths = written
    log = read_log(paths["mcap"], rate_hz=2.0)
    assert log.dt == pytest.approx(0.5)
    assert log.data.index[0] == 0.0


def test_channel_report(written):
    streams, meta, paths = written
    s, m = read_streams(paths["candump"])
    log = to_drivelog(s, m)
    rep = channel_report(log, s)
    assert rep.loc["speed_mps", "rate_hz"] == pytest.approx(10.0, rel=0.01)
    assert rep.loc["coolant_temp_degC", "gaps"] == 1
    assert rep.loc["coolant_temp_degC", "longest_gap_s"] == pytest.approx(13.0, abs=1.1)
    assert (rep["present"] | rep["derivable"]).all()
    assert rep.loc["engine_power_W", "derivable"] and not rep.loc["engine_power_W", "present"]
    text = format_report(rep)
    assert "speed_mps" in text and "missing: none" in text
    sub = to_drivelog({"speed_mps": s["speed_mps"]}, m)
    rep2 = channel_report(sub)
    assert rep2.loc["speed_mps", "present"] and not rep2.loc["soc", "present"]
    assert "soc" in format_report(rep2).splitlines()[-1]


@pytest.mark.parametrize("ext", ["parquet", "csv"])
def test_canonical_table_roundtrip(written, tmp_path, ext):
    _, _, paths = written
    log = read_log(paths["blf"])
    out = write_canonical(log, tmp_path / f"c.{ext}")
    back = read_canonical(out)
    assert back.meta == log.meta
    pd.testing.assert_frame_equal(back.data, log.data, check_exact=False, rtol=1e-9, atol=1e-9)


def test_cli_ingest(written, tmp_path, capsys):
    _, _, paths = written
    rc = main(["ingest", str(paths["csv"]), str(paths["candump"]), "--out", str(tmp_path / "o"),
               "--json", str(tmp_path / "r.json")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "[SYNTHETIC]" in out and "speed_mps" in out
    rep = json.loads((tmp_path / "r.json").read_text())
    assert len(rep) == 2
    assert (tmp_path / "o" / "drive.csv.canonical.parquet").exists()
    mp = tmp_path / "map.toml"
    mp.write_text('[columns]\n"speed [km/h]" = "speed_mps"\n')
    assert main(["ingest", str(paths["csv"]), "--map", str(mp), "--out", str(tmp_path / "x.csv"), "--rate", "2"]) == 0
    bad = tmp_path / "bad.csv"
    bad.write_text("time [s],speed [wobbles]\n0,1\n")
    assert main(["ingest", str(bad), "--out", str(tmp_path / "y.parquet")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.csv" in err and "wobbles" in err


def test_mdf4_optional_extra(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    t = np.arange(0.0, 10.0, 0.1)
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(samples=36.0 * np.ones_like(t), timestamps=t, name="VehicleSpeed", unit="km/h"),
                asammdf.Signal(samples=np.full(10, 50.0), timestamps=np.arange(10.0), name="soc", unit="%")])
    p = tmp_path / "x.mf4"
    mdf.save(p, overwrite=True)
    mdf.close()
    log = read_log(p, column_map={"VehicleSpeed": "speed_mps"})
    assert log.meta.format == "mf4"
    np.testing.assert_allclose(log.data["speed_mps"], 10.0)
    np.testing.assert_allclose(log.data["soc"], 0.5)
