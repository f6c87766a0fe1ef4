"""CSV reader: header units, aliases, column maps, metadata comments."""
import numpy as np
import pytest

from calib.errors import LogFormatError
from calib.ingest import read_log, read_streams
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import write_streams


def _write(tmp_path, text, name="log.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_written_csv_has_human_headers_and_synthetic_first_line(tmp_path):
    streams, meta = fabricate_streams(30)
    p = write_streams(streams, meta, tmp_path / "d.csv", "csv")
    lines = p.read_text().splitlines()
    assert lines[0].startswith("#") and "SYNTHETIC" in lines[0]
    header = next(line for line in lines if not line.startswith("#"))
    for col in ("time [s]", "speed [km/h]", "coolant_temp [degC]", "fuel_rate [g/s]", "soc [%]"):
        assert col in header.split(",")
    s, m = read_streams(p)
    assert m.synthetic and m.vehicle_id == "prius-test" and m.format == "csv"
    assert m.original_units["speed_mps"] == "km/h"
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), streams["speed_mps"].to_numpy(), atol=1e-9)
    np.testing.assert_allclose(s["soc"].to_numpy(), streams["soc"].to_numpy(), atol=1e-12)


def test_units_converted_through_pint(tmp_path):
    p = _write(tmp_path, "time [ms],speed [mph],fuel_rate [L/h],ambient_temp [degF],soc [%],other\n"
                         "0,0,3.6,32,50,x\n1000,10,0,104,50.5,y\n2000,20,1.8,50,51,z\n")
    s, m = read_streams(p)
    np.testing.assert_allclose(s["speed_mps"].index, [0, 1, 2])
    np.testing.assert_allclose(s["speed_mps"], [0, 4.4704, 8.9408])
    np.testing.assert_allclose(s["fuel_rate_g_per_s"], [0.74, 0, 0.37])
    np.testing.assert_allclose(s["ambient_temp_degC"], [0, 40, 10], atol=1e-9)
    np.testing.assert_allclose(s["soc"], [0.5, 0.505, 0.51])
    assert any("ignored columns: other" in n for n in m.notes)
    assert not m.synthetic


def test_column_map_supplies_names_and_units(tmp_path):
    p = _write(tmp_path, "Zeit,Geschw,Kuehlmittel\n0,0,20\n1,36,21\n")
    cmap = {"Zeit": "time [s]", "Geschw": "speed_mps [km/h]", "Kuehlmittel": "coolant_temp_degC [degC]"}
    s, m = read_streams(p, column_map=cmap)
    np.testing.assert_allclose(s["speed_mps"], [0, 10])
    assert m.channel_sources["coolant_temp_degC"] == "Kuehlmittel"


def test_canonical_names_carry_their_unit(tmp_path):
    p = _write(tmp_path, "time_s,speed_mps,coolant_temp_degC\n0,1,20\n1,2,\n2,3,22\n")
    s, _ = read_streams(p)
    np.testing.assert_allclose(s["speed_mps"], [1, 2, 3])
    assert len(s["coolant_temp_degC"]) == 2  # empty cell = no sample


def test_missing_unit_is_an_error_unless_mapped(tmp_path):
    p = _write(tmp_path, "time [s],speed\n0,1\n1,2\n")
    with pytest.raises(LogFormatError, match=r"line 1, column 'speed'.*no unit"):
        read_streams(p)
    s, _ = read_streams(p, column_map={"speed": "speed_mps [km/h]"})
    np.testing.assert_allclose(s["speed_mps"], [1 / 3.6, 2 / 3.6])


def test_time_offset_is_removed_and_noted(tmp_path):
    p = _write(tmp_path, "time [s],speed [m/s]\n100,1\n101,2\n")
    log = read_log(p)
    assert log.data.index[0] == 0.0
    assert any("shifted" in n for n in log.meta.notes)


def test_non_numeric_cell_names_line_and_column(tmp_path):
    p = _write(tmp_path, "# comment\ntime [s],speed [m/s]\n0,1\n1,abc\n")
    with pytest.raises(LogFormatError, match=r"line 4, column 'speed \[m/s\]'.*not a number"):
        read_streams(p, strict=True)
