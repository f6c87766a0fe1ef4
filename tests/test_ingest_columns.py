"""CSV column recognition beyond the exact spellings, ``iptm ingest --list-channels``, where ``iptm ingest``
writes by default, and the channel report as a reader sees it."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from calib.drivelog import DriveLog, LogMeta
from calib.ingest import channel_report, display_report, format_report
from calib.ingest.common import aliases_of, suggest_channel
from calib.ingest.csvlog import read_csv_streams
from iptm.cli import main

CSV = """time [s],speed [km/h],coolant [degF],engine [rpm],temp [degC],odometer [km]
0,0,50,800,1,0
1,10,59,810,1,0
2,20,68,820,1,0
"""


def test_lookalike_columns(tmp_path):
    f = tmp_path / "drive.csv"
    f.write_text(CSV)
    streams, meta = read_csv_streams(f)
    # `coolant [degF]` is read (an accepted spelling now) and converted
    assert streams["coolant_temp_degC"].tolist() == pytest.approx([10.0, 15.0, 20.0])
    notes = "\n".join(meta.notes)
    # `engine [rpm]` resembles one channel only through a generic word: a warning naming the accepted names
    assert "engine_speed_rpm" not in streams
    assert "'engine [rpm]' was not used: it looks like engine_speed_rpm (accepted names: engine_speed_rpm" in notes
    # `temp [degC]` could be any temperature: a warning, nothing guessed
    assert "'temp [degC]' was not used: it could be any of" in notes and "--list-channels" in notes
    # an unrelated column is only listed as ignored
    assert "odometer" in notes and "'odometer [km]' was not used" not in notes


def test_suggest_channel_uses_the_unit():
    assert suggest_channel("colant_temperatur", "degF")[0] == "coolant_temp_degC"  # a misspelling
    assert suggest_channel("cabin_air", "degC")[0] == "cabin_temp_degC"
    assert suggest_channel("coolant_pressure", "kPa") == (None, [])  # unit does not fit: not a look-alike
    assert suggest_channel("odometer", "km") == (None, [])
    assert "coolant" in aliases_of("coolant_temp_degC")


def test_lookalike_yields_to_exact_name(tmp_path):
    f = tmp_path / "d.csv"
    f.write_text("time [s],coolant_temp [degC],coolant_temperatur [degC]\n0,1,5\n1,2,6\n")
    streams, meta = read_csv_streams(f)
    assert streams["coolant_temp_degC"].tolist() == [1.0, 2.0]
    assert any("which another column already gives" in n for n in meta.notes)


def test_list_channels(capsys):
    assert main(["ingest", "--list-channels"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("coolant_temp_degC"))
    assert "coolant_temp" in line and "ect" in line and "degC" in line
    assert main(["ingest"]) == 2
    assert "--list-channels" in capsys.readouterr().err


def test_ingest_default_output_leaves_log_folder_alone(tmp_path, monkeypatch, capsys):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "drive.csv").write_text(CSV)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["ingest", str(logs / "drive.csv")]) == 0
    assert sorted(p.name for p in logs.iterdir()) == ["drive.csv"]
    assert (work / ".iptm-cache" / "canonical" / "drive.csv.canonical.parquet").is_file()
    err = capsys.readouterr().err
    assert "warning: column 'engine [rpm]' was not used" in err


def test_display_report_rounds_artefacts_and_uses_reader_units():
    t = np.arange(5.0)
    data = pd.DataFrame({"speed_mps": [0.0005556, 5.0, 10.0, 20.0, 15.0],
                         "engine_speed_rpm": [0.078, 1000.0, 4000.0, 2000.0, 0.0],
                         "soc": [0.55, 0.56, 0.6, 0.65, 0.6]}, index=pd.Index(t, name="time_s"))
    rep = channel_report(DriveLog(data=data, meta=LogMeta(source="x.csv", format="csv")))
    d = display_report(rep).set_index("channel")
    assert d.loc["speed_mps", "min"] == "0.0 (0.0)" and d.loc["speed_mps", "max"] == "20.0 (72.0)"
    assert d.loc["speed_mps", "unit"] == "m/s (km/h)"
    assert d.loc["engine_speed_rpm", "min"] == "0" and d.loc["engine_speed_rpm", "max"] == "4000"
    assert d.loc["soc", "unit"] == "%" and d.loc["soc", "min"] == "55.0" and d.loc["soc", "max"] == "65.0"
    text = format_report(rep)
    assert "0.0005556" not in text and "dimensionless" not in text
