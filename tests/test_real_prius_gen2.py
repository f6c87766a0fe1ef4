"""A REAL Prius log (2nd generation, parked cold start at -1 degC; tests/data/real_prius_gen2/README.md):
ingested from candump text with a Gen2 DBC and OBD-II responses, every channel accounted for."""
from pathlib import Path

import numpy as np
import pytest

from calib.ingest import channel_report, read_log, read_streams

DATA = Path(__file__).parent / "data" / "real_prius_gen2"
LOG, DBC = DATA / "coldstart_2026-02-21.log", DATA / "prius_gen2.dbc"


@pytest.fixture(scope="module")
def real():
    streams, meta = read_streams(LOG, dbc=DBC)
    return streams, meta, read_log(LOG, dbc=DBC)


def test_what_the_real_log_holds(real):
    streams, meta, log = real
    assert not meta.synthetic
    # the frames in the file, by ID: 307 coolant (0x039), 463 current/voltage (0x03B), 49 SOC (0x3CB)
    c = meta.channel_counts
    assert c["coolant_temp_degC"]["read"] == 307 and c["bat_current_A"]["read"] == 463
    assert c["soc"]["read"] == 49
    for ch, cc in c.items():  # every sample read is kept or merged with one at the same gateway time
        assert cc["read"] == cc["kept"] + cc["merged"], ch
    T = streams["coolant_temp_degC"]
    assert T.iloc[0] == -2.0 and T.max() == 47.0
    assert streams["ambient_temp_degC"].unique().tolist() == [-1.0]
    assert streams["engine_speed_rpm"].max() > 1200  # fast idle, from OBD PID 0x0C
    assert streams["soc"].min() == pytest.approx(0.55) and streams["soc"].max() == pytest.approx(0.70)
    assert "ESTIMATE" in meta.estimated["fuel_rate_g_per_s"]


def test_polled_channels_keep_their_true_rate(real):
    streams, _meta, log = real
    rep = channel_report(log, streams)
    assert rep.loc["engine_speed_rpm", "rate_hz"] < 0.2  # polled about every 10 s
    # on the 1-Hz table: interpolated between readings 9 s apart (14.3 and 23.2 s), not across the 28-s
    # silence between 206.6 and 234.8 s (more than 2.5 of its median intervals)
    rpm = log.data["engine_speed_rpm"]
    assert np.isfinite(rpm.loc[15.0:23.0]).all()
    assert np.isnan(rpm.loc[208.0:234.0]).all()


def test_what_a_calibration_makes_of_the_real_cold_start():
    """The engine-thermal fit on a real parked warm-up: no heater, cabin or torque channel (heater heat
    estimated as an unknown input), fuel estimated from MAF, engine power from the power balance. The
    gateway forwarded the speed frames in irregular batches (gaps up to 17 s), so the log is read with gaps up
    to 20 s bridged (a user's declaration, like ``iptm calibrate --max-gap 20``); one 70-s run then has every
    input. What it makes of it is stated in docs/test_cars.md."""
    from calib.fit.driver import calibrate

    log = read_log(LOG, dbc=DBC, max_gap_s=20.0)
    res = calibrate([log], heater="estimate", progress=False, diagnose=False)
    th = res.fits["thermal"]
    assert th.logs and th.metrics["rmse_degC"] < 1.0
    c = th.estimates["C_eng_J_per_K"]
    assert c.status == "estimated" and c.informed > 0.3
    assert 30e3 < c.value < 80e3  # a 1.5-L engine's block and coolant: below the 2017 car's 80 kJ/K prior
    assert any("ESTIMATE" in w for w in res.data_warnings)
    assert "estimated" in th.used[log.label()]["heater heat"]
