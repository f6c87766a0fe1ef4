"""The resampler against answers worked out by hand: bin means centred on each output time, interpolation
only across short gaps, nothing outside the samples."""
import numpy as np
import pandas as pd
import pytest

from calib.drivelog import LogMeta
from calib.ingest.resample import resample_stream, to_drivelog

# 10 Hz samples placed between bin edges (t = 0.05, 0.15, ...), so no sample sits on a bin boundary.
T10 = 0.05 + 0.1 * np.arange(100)  # 0.05 .. 9.95 s


def _stream(t, v):
    return pd.Series(np.asarray(v, float), index=pd.Index(np.asarray(t, float)))


def test_ramp_bin_means_are_centred_on_the_output_time():
    # v = t. The bin of output time g is [g - 0.5, g + 0.5): samples g - 0.45 ... g + 0.45, mean exactly g.
    # The first bin [-0.5, 0.5) holds 0.05 ... 0.45 only: mean 0.25.
    out = resample_stream(_stream(T10, T10), np.arange(10.0), 1.0, 5.0)
    np.testing.assert_allclose(out, [0.25, 1, 2, 3, 4, 5, 6, 7, 8, 9], atol=1e-12)


def test_step_lands_in_the_bin_around_its_time():
    # 0 before t = 3.45 s, 1 from then on: the bin [2.5, 3.5) holds the ten samples 2.55, .., 3.45, one of
    # them (3.45) at 1: mean 0.1; the bin [3.5, 4.5) is all ones.
    v = (T10 >= 3.44).astype(float)
    out = resample_stream(_stream(T10, v), np.arange(6.0), 1.0, 5.0)
    np.testing.assert_allclose(out, [0, 0, 0, 0.1, 1, 1], atol=1e-12)


@pytest.mark.parametrize("f_hz", [0.05, 0.2, 0.31])
def test_sine_bin_means(f_hz):
    # mean of sin(w (g + d)) over the ten symmetric offsets d = +-0.05, .., +-0.45 = sin(w g) mean(cos(w d))
    w = 2 * np.pi * f_hz
    grid = np.arange(1.0, 10.0)
    out = resample_stream(_stream(T10, np.sin(w * T10)), grid, 1.0, 5.0)
    d = 0.05 + 0.1 * np.arange(5)
    damp = np.mean(np.cos(w * d))
    np.testing.assert_allclose(out, np.sin(w * grid) * damp, atol=1e-12)


def test_half_rate_output_bins():
    # 2 Hz output from a 4 Hz ramp sampled at 0.125 + 0.25 k: the bin [g - 0.25, g + 0.25) holds g - 0.125
    # and g + 0.125, mean g (and 3 v for v = 3 t)
    t4 = 0.125 + 0.25 * np.arange(40)
    grid = 0.5 * np.arange(1, 20)
    out = resample_stream(_stream(t4, 3 * t4), grid, 0.5, 5.0)
    np.testing.assert_allclose(out, 3 * grid, atol=1e-12)


def test_empty_bins_interpolate_within_short_gaps_only():
    t = [0.0, 3.0, 10.0]
    v = [0.0, 6.0, 20.0]
    out = resample_stream(_stream(t, v), np.arange(12.0), 1.0, 5.0)
    # 1, 2 s: empty bins inside a 3 s gap -> linear between (0, 0) and (3, 6);
    # 4 .. 9 s: inside a 7 s gap (> 5 s) -> NaN; 10 s: its own sample; 11 s: after the last sample -> NaN
    np.testing.assert_allclose(out[:4], [0.0, 2.0, 4.0, 6.0])
    assert np.isnan(out[4:10]).all()
    assert out[10] == 20.0 and np.isnan(out[11])


def test_gap_exactly_at_the_limit_is_interpolated():
    out = resample_stream(_stream([0.0, 5.0], [0.0, 10.0]), np.arange(6.0), 1.0, 5.0)
    np.testing.assert_allclose(out, [0, 2, 4, 6, 8, 10])


def test_to_drivelog_uses_the_centred_bins_and_notes_it():
    streams = {"speed_mps": _stream(T10, T10), "soc": _stream([0.0, 4.0, 9.0], [0.5, 0.54, 0.59])}
    log = to_drivelog(streams, LogMeta(source="hand", format="csv"), rate_hz=1.0, max_gap_s=5.0)
    assert list(log.data.index) == list(np.arange(10.0))  # up to the last sample (9.95 s)
    np.testing.assert_allclose(log.data["speed_mps"], [0.25, 1, 2, 3, 4, 5, 6, 7, 8, 9], atol=1e-12)
    # 1 Hz SOC: own samples at 0, 4, 9; interpolated between them
    np.testing.assert_allclose(log.data["soc"], [0.5, 0.51, 0.52, 0.53, 0.54, 0.55, 0.56, 0.57, 0.58, 0.59],
                               atol=1e-12)
    assert "resampled to 1 Hz" in log.meta.notes[-1]


def test_default_gap_limit_is_five_seconds():
    meta = LogMeta(source="hand", format="csv")
    short = to_drivelog({"soc": _stream([0.0, 5.0], [0.5, 0.55])}, meta)
    np.testing.assert_allclose(short.data["soc"], [0.5, 0.51, 0.52, 0.53, 0.54, 0.55])
    long = to_drivelog({"soc": _stream([0.0, 5.5], [0.5, 0.55])}, meta)
    assert np.isnan(long.data["soc"].to_numpy()[1:5]).all()


def test_single_sample_stream_fills_its_own_bin_only():
    out = resample_stream(_stream([2.2], [7.0]), np.arange(5.0), 1.0, 5.0)
    assert out[2] == 7.0 and np.isnan(out[[0, 1, 3, 4]]).all()


@pytest.mark.parametrize("rate", [0.0, -1.0, np.inf, np.nan])
def test_bad_rate_is_refused(rate):
    from calib.errors import IptmError

    with pytest.raises(IptmError, match="resampling rate"):
        to_drivelog({"soc": _stream([0.0, 1.0], [0.5, 0.5])}, LogMeta(source="hand"), rate_hz=rate)


@pytest.mark.parametrize("gap", [-1.0, -1e-9, np.inf, np.nan])
def test_negative_or_non_finite_gap_limit_is_refused(gap):
    """A gap limit must be a finite number of seconds >= 0: a negative finite one is refused as clearly as
    an infinite or NaN one (0 s is allowed: see the row-limit test)."""
    from calib.errors import IptmError

    with pytest.raises(IptmError, match=f"max gap must be a non-negative number of seconds, got {gap}"):
        to_drivelog({"soc": _stream([0.0, 1.0], [0.5, 0.5])}, LogMeta(source="hand"), max_gap_s=gap)


@pytest.mark.parametrize("rate", [1.0, 2.0])
def test_streams_without_samples_give_the_single_instant_zero(rate):
    """No stream holds a sample (none given, or only empty ones): the time base is the one instant 0 s and
    no channel gets a column."""
    meta = LogMeta(source="hand")
    for streams in ({}, {"soc": pd.Series([], dtype=float)}):
        log = to_drivelog(streams, meta, rate_hz=rate)
        assert log.data.index.tolist() == [0.0] and list(log.data.columns) == []


def test_a_log_longer_than_the_row_limit_is_refused():
    """2,000,000 rows is the limit: at 2 Hz a last sample a quarter second beyond 1,000,000 s is refused with
    the number of rows; exactly at it is a log of 2,000,001 rows (times 0, 0.5, ... 1,000,000 s)."""
    from calib.errors import LogFormatError

    meta = LogMeta(source="long.csv", format="test")
    s = pd.Series([1.0, 2.0], index=[0.0, 1_000_000.25])
    with pytest.raises(LogFormatError, match="2e\\+06 rows at 2 Hz"):
        to_drivelog({"speed_mps": s}, meta, rate_hz=2.0)
    log = to_drivelog({"speed_mps": pd.Series([1.0, 2.0], index=[0.0, 1_000_000.0])}, meta, rate_hz=2.0,
                      max_gap_s=0.0)
    assert len(log.data) == 2_000_001 and log.data.index[-1] == 1_000_000.0
