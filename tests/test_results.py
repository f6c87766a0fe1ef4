"""Results save and load themselves (docs/results.md): what is loaded is what was saved."""
import json

import numpy as np
import pandas as pd
import pytest

from calib.errors import ResultFileError
from calib.model.simulate import SimResult, simulate


def _plain(o):
    """JSON-like with every number a float (a bound written 0 reads back 0.0), arrays and tuples as lists."""
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [_plain(v) for v in (o.tolist() if isinstance(o, np.ndarray) else o)]
    if isinstance(o, (int, float, np.number)) and not isinstance(o, (bool, np.bool_)):
        return repr(float(o))
    return o


def _same(a, b):
    """Equal as JSON-like structures: numbers exactly (NaN equal to NaN), arrays as lists."""
    assert json.dumps(_plain(a), sort_keys=True, indent=0) == json.dumps(_plain(b), sort_keys=True, indent=0)


@pytest.fixture(scope="module")
def sim():
    from calib.model.params import default_parameters

    return simulate(default_parameters().with_values(C_eng_J_per_K=70e3), "nycc", T_amb=-5.0)


def test_simulation_round_trip(sim, tmp_path):
    path = sim.save(tmp_path / "sim")
    back = SimResult.load(path)
    pd.testing.assert_frame_equal(back.to_pandas(), sim.to_pandas(), check_exact=True)
    assert back.info == sim.info and back.mp.C_eng == 70e3
    for f in sim.mp._fields:
        assert np.array_equal(np.asarray(getattr(back.mp, f)), np.asarray(getattr(sim.mp, f))), f
    assert back.summary() == sim.summary()
    doc = json.loads((path / "result.json").read_text())
    assert (doc["format"], doc["version"], doc["kind"]) == ("iptm-result", 1, "simulation")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]  # no temporary left behind


def test_saving_again_replaces_a_result_but_never_another_folder(sim, tmp_path):
    path = sim.save(tmp_path / "sim")
    sim.save(path)  # a result is replaced whole
    assert SimResult.load(path).fuel_g == sim.fuel_g
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(ResultFileError, match="not a saved result"):
        sim.save(other)
    assert (other / "notes.txt").read_text() == "keep me"


def test_loading_what_is_not_a_result_says_so(sim, tmp_path):
    with pytest.raises(ResultFileError, match="not a saved result"):
        SimResult.load(tmp_path)
    path = sim.save(tmp_path / "sim")
    doc = json.loads((path / "result.json").read_text())
    (path / "result.json").write_text(json.dumps({**doc, "version": 99}))
    with pytest.raises(ResultFileError, match="format version 99"):
        SimResult.load(path)
    (path / "result.json").write_text(json.dumps({**doc, "kind": "calibration"}))
    with pytest.raises(ResultFileError, match="holds a 'calibration' result"):
        SimResult.load(path)
    (path / "result.json").write_text("{not json")
    with pytest.raises(ResultFileError, match="unreadable"):
        SimResult.load(path)
    path = sim.save(tmp_path / "sim2")
    (path / "arrays.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ResultFileError, match="arrays.npz"):
        SimResult.load(path)


def test_calibration_round_trip(tmp_path):
    from calib.fit.driver import CalibrationResult, calibrate
    from calib.ingest import to_drivelog
    from calib.model.params import ParameterSet
    from calib.synth import Scenario, draw_truth, synthesise

    truth = draw_truth(3)
    log = to_drivelog(*synthesise(Scenario("fit_cold", "nycc", -10.0, 0.6, -10.0, -10.0, T_bat=-5.0,
                                           with_bay_temp=True), truth, seed=3)[1:])
    res = calibrate([log], progress=False)
    path = res.save(tmp_path / "cal")
    back = CalibrationResult.load(path)
    _same(res.to_dict(), back.to_dict())
    assert back.report() == res.report()
    pd.testing.assert_frame_equal(back.to_pandas(), res.to_pandas())
    for n in res.params.names():
        assert back.params[n] == res.params[n]
    assert ParameterSet.load(path / "parameters.toml")["C_eng_J_per_K"] == res.params["C_eng_J_per_K"]
    with pytest.raises(ResultFileError, match="holds a 'calibration' result"):
        SimResult.load(path)


def test_dp_outcome_round_trip(tmp_path, params):
    from optimize.formulations import DPOutcome, solve_baseline
    from optimize.formulations.scenario import DPGrids, DPScenario

    o = solve_baseline(params, DPScenario(duration_s=150.0, terminal="free"), DPGrids())
    path = o.save(tmp_path / "dp")
    back = DPOutcome.load(path)
    _same(o.describe(), back.describe())
    pd.testing.assert_frame_equal(back.to_pandas(), o.to_pandas(), check_exact=True)
    _same(back.to_pandas().attrs, o.to_pandas().attrs)
    pd.testing.assert_frame_equal(back.dp.to_pandas(), o.dp.to_pandas(), check_exact=True)
    pd.testing.assert_frame_equal(back.on_thermal.to_pandas(), o.on_thermal.to_pandas(), check_exact=True)
    assert back.dp.V is None  # the value functions only when asked for
    full = DPOutcome.load(o.save(tmp_path / "dp_full", value_functions=True))
    assert np.array_equal(full.dp.V, o.dp.V)
    assert back.charge_sustaining() == o.charge_sustaining() and back.fuel_g == o.fuel_g
