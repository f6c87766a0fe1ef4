"""The ECMS tuned on the drive: the search keeps the band, takes the least valued fuel, and can only improve
on a setting it tries."""
from dataclasses import replace

import numpy as np
import pytest

from calib.errors import IptmError
from calib.model.params import default_parameters
from optimize.causal.compare import _corrected
from optimize.causal.ecms import ECMSParams
from optimize.causal.hindsight import _sim, tune_ecms_on_drive
from optimize.formulations.scenario import DPScenario

SCEN = replace(DPScenario(), cycle="nycc", T_amb=-10.0, duration_s=240.0)


@pytest.fixture(scope="module")
def ps():
    return default_parameters()


def test_adaptive_search_is_no_worse_than_the_committed_setting(ps):
    mp = ps.model_params()
    committed = ECMSParams()
    sim = _sim(ps, mp, SCEN.load_cycle(), SCEN, replace(committed, Q_heat_W=SCEN.Q_heat, soc_target=SCEN.soc0))
    s = sim.summary()
    assert abs(s["soc_final"] - s["soc_initial"]) <= 0.01  # so the committed setting is a candidate
    h = tune_ecms_on_drive(ps, SCEN, search="adaptive", s_grid=(0.4, committed.s0, 0.9), mu_grid=(committed.mu0, 0.5))
    assert len(h.tried) == 6
    assert h.best is not None and abs(h.best["dsoc"]) <= 0.01
    assert h.best["fuel_valued_g"] <= _corrected(sim, SCEN, "corrected")[0] + 1e-9
    in_band = [r for r in h.tried if abs(r["dsoc"]) <= 0.01]
    assert all(r["fuel_valued_g"] >= h.best["fuel_valued_g"] for r in in_band)
    assert all(np.isnan(r["fuel_valued_g"]) for r in h.tried if abs(r["dsoc"]) > 0.01)


def test_constant_search_refines_where_the_final_soc_crosses_the_band(ps):
    h = tune_ecms_on_drive(ps, SCEN, search="constant", s_grid=(0.2, 0.6, 1.4), mu_grid=(0.0,))
    coarse, fine = h.tried[:3], h.tried[3:]
    assert len(fine) == 9
    d = [r["dsoc"] for r in coarse]
    assert d == sorted(d)  # a dearer battery ends higher
    lo = max([r["s"] for r in coarse if r["dsoc"] < -0.01], default=0.2)
    hi = min([r["s"] for r in coarse if r["dsoc"] > 0.01 and r["s"] > lo], default=1.4)
    assert all(lo < r["s"] < hi for r in fine)
    assert h.best is None or abs(h.best["dsoc"]) <= 0.01


def test_unknown_search_is_refused(ps):
    with pytest.raises(IptmError, match="search 'oracle'"):
        tune_ecms_on_drive(ps, SCEN, search="oracle")
