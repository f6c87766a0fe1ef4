"""Demand Markov chain: estimation, ambient bands, validation on held-out drives, storage."""
import numpy as np
import pandas as pd
import pytest

from calib.drivelog import DriveLog, LogMeta
from calib.errors import IptmError
from calib.model.cycles import load_cycle
from calib.model.params import default_parameters
from optimize.causal.markov import DemandMarkov


@pytest.fixture(scope="module")
def ps():
    return default_parameters()


def _log_from_cycle(name, T_amb):
    """A log carrying a bundled cycle's speed at 10 Hz and an ambient reading (a stand-in for an ingested log)."""
    c = load_cycle(name)
    t = np.arange(0.0, c.t[-1] + 1e-9, 0.1)
    df = pd.DataFrame({"speed_mps": np.interp(t, c.t, c.v), "ambient_temp_degC": np.full(t.size, T_amb)},
                      index=pd.Index(t, name="time_s"))
    return DriveLog(df, LogMeta(source=f"{name}.csv"))


def test_estimate_rows_bands_and_roundtrip(ps, tmp_path):
    mk = DemandMarkov.estimate(ps, ["udds", _log_from_cycle("us06", -12.0)])
    assert mk.P.shape[0] == 2  # two ambient bands
    np.testing.assert_allclose(mk.P.sum(axis=2), 1.0)
    # the cycle counts in both bands, the cold log only in the cold band
    n_udds = load_cycle("udds").n_steps - 1
    assert mk.counts[1].sum() == pytest.approx(n_udds)
    assert mk.counts[0].sum() > n_udds + 500
    assert mk.band(-10.0) == 0 and mk.band(5.0) == 1
    assert np.all(np.diff(mk.values_W[0]) > 0)
    p = tmp_path / "markov.json"
    mk.save(p)
    back = DemandMarkov.load(p)
    np.testing.assert_array_equal(back.P, mk.P)
    assert back.sources == mk.sources


def test_validation_on_held_out_drives(ps):
    mk = DemandMarkov.estimate(ps, ["udds", "hwfet", "us06"])
    rows = mk.validate(ps, ["artemis_urban", "nycc"], T_amb=-10.0)
    assert [r["drive"] for r in rows] == ["artemis_urban", "nycc"]
    for r in rows:
        # the chain predicts the next bin better than the bins' frequencies alone
        assert r["loglik_per_step_markov"] > r["loglik_per_step_iid"]
        assert 0.0 <= r["tv_distance_vs_training"] <= 1.0
        assert 0.0 < r["stay_prob_model"] < 1.0


def test_bad_input_is_one_clear_error(ps):
    with pytest.raises(IptmError, match="no drives"):
        DemandMarkov.estimate(ps, [])
    with pytest.raises(IptmError, match="increase"):
        DemandMarkov.estimate(ps, ["udds"], edges_W=[0.0, -1.0])
