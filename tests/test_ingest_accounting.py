"""Per-channel sample accounting, physical ranges, resampling that no value can poison, content-keyed caches."""
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib.drivelog import CHANNELS, RANGES, DriveLog, LogMeta
from calib.errors import ChannelLossWarning
from calib.ingest import channel_report, format_report, input_digest, loss_text, read_streams, to_drivelog
from calib.ingest.common import AFR_STOICH, fuel_from_maf, make_series
from calib.ingest.resample import resample_stream

ROOT = Path(__file__).resolve().parents[1]


def test_every_channel_has_a_range():
    assert set(RANGES) == set(CHANNELS)
    assert all(lo < hi for lo, hi in RANGES.values())


def test_make_series_accounts_every_sample():
    meta = LogMeta(source="x")
    t = [0.0, 1.0, 1.0, 2.0, 3.0, 4.0, 5.0, np.nan]
    v = [10.0, 11.0, 13.0, np.inf, -323.0, np.nan, 20.0, 30.0]
    s = make_series(t, v, "coolant_temp_degC", meta)
    c = meta.channel_counts["coolant_temp_degC"]
    assert c["read"] == 8
    assert c["nonfinite"] == 3  # inf, NaN value, NaN time
    assert c["out_of_range"] == 1 and c["out_of_range_times_s"] == [3.0]
    assert c["merged"] == 1  # two samples at 1.0 s became their mean
    assert c["kept"] == 3 == len(s)
    assert s.loc[1.0] == pytest.approx(12.0)
    assert c["read"] == c["nonfinite"] + c["out_of_range"] + c["merged"] + c["kept"]


def test_absent_cells_are_not_counted_as_read():
    meta = LogMeta(source="x")
    v = np.array([1.0, np.nan, 2.0, np.nan])
    make_series([0, 1, 2, 3], v, "speed_mps", meta, absent=np.isnan(v))
    c = meta.channel_counts["speed_mps"]
    assert (c["read"], c["nonfinite"], c["kept"]) == (2, 0, 2)


def test_loss_over_one_percent_is_named():
    meta = LogMeta(source="x")
    v = np.full(100, 0.5)
    v[[10, 20]] = 1e17
    make_series(np.arange(100.0), v, "fuel_rate_g_per_s", meta)
    make_series(np.arange(100.0), np.full(100, 50.0), "soc", meta)  # 5000 %: every sample impossible
    txt = loss_text(meta)
    assert "fuel_rate_g_per_s lost 2 of 100" in txt and "10.0, 20.0" in txt
    assert "soc lost 100 of 100" in txt
    assert meta.lossy_channels() == ["fuel_rate_g_per_s", "soc"]
    meta2 = LogMeta(source="y")
    v = np.full(1000, 0.5)
    v[5] = -7.0
    make_series(np.arange(1000.0), v, "fuel_rate_g_per_s", meta2)  # 0.1 %: counted, not loud
    assert loss_text(meta2) == "" and meta2.channel_counts["fuel_rate_g_per_s"]["out_of_range"] == 1


def test_a_spike_changes_only_its_own_bin():
    t = np.arange(0.0, 900.0, 0.1)
    v = 0.25 + 0.1 * np.sin(t / 7.0)
    ref = resample_stream(pd.Series(v, index=t), np.arange(900.0), 1.0, 5.0)
    for big in (1e12, 1e17, 1e300):
        w = v.copy()
        w[4000] = big
        out = resample_stream(pd.Series(w, index=t), np.arange(900.0), 1.0, 5.0)
        changed = np.flatnonzero(out != ref)
        assert list(changed) == [400], big
    # a sum over a running total would lose the small values after a 1e17: the total stays exact here
    w = v.copy()
    w[4000] = 1e17
    out = resample_stream(pd.Series(w, index=t), np.arange(900.0), 1.0, 5.0)
    keep = np.arange(900) != 400
    assert out[keep].sum() == pytest.approx(ref[keep].sum(), rel=1e-12)


def test_slowly_polled_channel_is_interpolated_between_its_own_samples_only():
    t_fast = np.arange(0.0, 600.0, 0.1)
    t_slow = np.arange(0.0, 600.0, 10.0)  # an OBD PID read every 10 s
    keep = (t_slow < 200) | (t_slow > 300)  # then a 110-s dropout
    streams = {"speed_mps": pd.Series(np.ones_like(t_fast), index=t_fast),
               "coolant_temp_degC": pd.Series(t_slow[keep] / 10.0, index=t_slow[keep])}
    log = to_drivelog(streams, LogMeta(source="x"), max_gap_s=5.0)
    c = log.data["coolant_temp_degC"]
    assert c.loc[15.0] == pytest.approx(1.5)  # between two readings 10 s apart
    assert c.loc[250.0] != c.loc[250.0]  # inside the dropout: NaN
    assert np.isnan(c.loc[201.0:299.0]).all()
    rep = channel_report(log, streams)
    assert rep.loc["coolant_temp_degC", "rate_hz"] == pytest.approx(0.1)
    assert "0.10" in format_report(rep)


def test_fuel_from_maf_is_labelled_an_estimate():
    meta = LogMeta(source="x")
    s = fuel_from_maf([0.0, 1.0], [14.7, 29.4], meta, "PID 0x10 MAF")
    assert s.to_list() == pytest.approx([1.0 * 14.7 / AFR_STOICH, 2.0 * 14.7 / AFR_STOICH])
    assert "ESTIMATE" in meta.estimated["fuel_rate_g_per_s"]
    log = DriveLog(data=pd.DataFrame({"fuel_rate_g_per_s": s.to_numpy()}, index=[0.0, 1.0]), meta=meta)
    assert "[ESTIMATED fuel_rate_g_per_s]" in log.label()
    assert "ESTIMATED fuel_rate_g_per_s" in format_report(channel_report(log))


def test_report_does_not_name_a_speed_source_without_speed():
    meta = LogMeta(source="x", channel_sources={"speed_mps": "speed [km/h]"})
    log = DriveLog(data=pd.DataFrame({"fuel_rate_g_per_s": [0.5, 0.8]}, index=[0.0, 1.0]), meta=meta)
    txt = format_report(channel_report(log))
    assert "speed from" not in txt and "missing: speed_mps" in txt


def test_docs_range_table_matches_the_code():
    text = (ROOT / "docs" / "logs.md").read_text()
    rows = dict(re.findall(r"^\| `(\w+)` \| [^|]+ \| ([^|]+) \|", text, flags=re.M))
    assert set(rows) == set(RANGES)
    for ch, (lo, hi) in RANGES.items():
        assert rows[ch].strip() == f"{lo:g} to {hi:g}", ch


def test_ingest_key_follows_the_dbc_content(tmp_path):
    log = tmp_path / "a.log"
    log.write_text("(0.0) can0 0B4#0000000000000000\n")
    dbc = tmp_path / "x.dbc"
    src = (ROOT / "calib" / "data" / "can" / "prius_iptm.dbc").read_text()
    dbc.write_text(src)
    k1 = input_digest(log, dbc=dbc)
    dbc.write_text(src.replace("SPEED", "SPEEDX", 1))
    assert input_digest(log, dbc=dbc) != k1
    assert input_digest(log, dbc=dbc, maps={"signals": {"A.B": "soc"}}) != input_digest(log, dbc=dbc)


def test_loss_warning_from_the_reader(tmp_path):
    f = tmp_path / "spike.csv"
    rows = "\n".join(f"{i},{10 + i % 3},{1e17 if i in (3, 7) else 0.5}" for i in range(100))
    f.write_text("time [s],speed [km/h],fuel_rate [g/s]\n" + rows + "\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        streams, meta = read_streams(f)
    msgs = [str(w.message) for w in caught if issubclass(w.category, ChannelLossWarning)]
    assert len(msgs) == 1 and "fuel_rate_g_per_s lost 2 of 100" in msgs[0]
    assert len(streams["fuel_rate_g_per_s"]) == 98 and len(streams["speed_mps"]) == 100
    log = to_drivelog(streams, meta)
    assert "[LOST SAMPLES]" in log.label()
    # the two dropped samples are bridged from their neighbours (2-s gaps), nothing else moved
    assert log.data["fuel_rate_g_per_s"].sum() == pytest.approx(0.5 * 100)
