"""Calibration speed on power-only logs: the fuel fit's analytic Jacobian is the derivative of its residuals,
its minimiser reaches the posterior mode in few evaluations, and ``calibrate`` times each step."""
from pathlib import Path

import numpy as np
import pytest

import calib.fit.fuel as fuel_mod
import calib.fit.thermal as thermal_mod
from calib.fit import toolkit
from calib.fit.fuel import fit_fuel
from calib.fit.thermal import fit_thermal
from calib.ingest import read_log
from calib.model.params import default_parameters
from testcars.synth_fastsim import fastsim_available

SAMPLE_CSV = Path(__file__).parent / "data" / "fastsim" / "SYNTHETIC_fastsim_sonata_cold_udds_300s.csv"


@pytest.fixture(scope="module")
def sample():
    return read_log(SAMPLE_CSV)


def _captured_fuel_problem(monkeypatch, logs):
    """The arguments fit_fuel hands to map_fit (its residuals, priors, Jacobian), and its result."""
    cap = {}

    def spy(make_params, segments, cand, **kw):
        cap.update(make_params=make_params, segments=segments, cand=cand, kw=kw)
        cap["out"] = toolkit.map_fit(make_params, segments, cand, **kw)
        return cap["out"]

    monkeypatch.setattr(fuel_mod, "map_fit", spy)
    fit = fit_fuel(logs, default_parameters())
    assert cap, "fit_fuel did not reach map_fit on this log"
    return cap, fit


def _differences(cap, ps, h=1e-6):
    """Central differences of the data residuals and of the extra priors over the varied parameters."""
    seg, extra = cap["segments"], cap["kw"]["extra"]
    names = [k for k in ps if ps[k].vary]
    cols_d, cols_e = [], []
    for k in names:
        step = h * max(abs(ps[k].value), 1e-2)
        up, dn = ps.copy(), ps.copy()
        up[k].set(value=ps[k].value + step, min=-np.inf, max=np.inf)
        dn[k].set(value=ps[k].value - step, min=-np.inf, max=np.inf)
        cols_d.append((np.concatenate(seg(up)) - np.concatenate(seg(dn))) / (2 * step))
        cols_e.append((extra(up) - extra(dn)) / (2 * step))
    return np.array(cols_d).T, np.array(cols_e).T


@pytest.mark.parametrize("where", ["start", "mode"])
def test_fuel_jacobian_is_the_derivative_of_the_residuals(monkeypatch, sample, where):
    cap, _ = _captured_fuel_problem(monkeypatch, [sample])
    ps = cap["make_params"]() if where == "start" else cap["out"]["params"]
    jd, je = cap["kw"]["jac"](ps)
    nd, ne = _differences(cap, ps)
    assert jd.shape == nd.shape and je.shape == ne.shape
    scale_d = np.maximum(np.abs(nd).max(axis=0), 1e-9)
    scale_e = np.maximum(np.abs(ne).max(axis=0), 1e-9)
    assert np.max(np.abs(jd - nd) / scale_d) < 1e-4
    assert np.max(np.abs(je - ne) / scale_e) < 1e-4


def test_fuel_fit_on_a_power_only_log_takes_few_evaluations(monkeypatch, sample):
    calls = []
    real = fuel_mod.fuel_replay

    def counting(*a):
        calls.append(1)
        return real(*a)

    monkeypatch.setattr(fuel_mod, "fuel_replay", counting)
    fit = fit_fuel([sample], default_parameters())
    assert fit.logs
    # Levenberg-Marquardt with differenced Jacobians took thousands here; each start now needs tens
    assert len(calls) < 300, len(calls)


def test_fuel_mode_is_no_worse_than_levenberg_marquardt(monkeypatch, sample):
    """The trust-region minimiser with the analytic Jacobian ends at an objective at most that of the former
    minimiser (Levenberg-Marquardt, differenced Jacobian) on the same problem."""
    cap, _ = _captured_fuel_problem(monkeypatch, [sample])
    kw = dict(cap["kw"])
    kw.pop("jac")
    lm = toolkit.map_fit(cap["make_params"], cap["segments"], cap["cand"], **kw)
    trf = cap["out"]
    s = trf["noise_sd"]
    prior, psd, extra = kw["prior"], kw["prior_sd"], kw["extra"]

    def cost(ps):
        r = np.concatenate([np.concatenate(cap["segments"](ps)) / s,
                            toolkit.prior_residual(ps.valuesdict(), prior, psd), extra(ps)])
        return float(np.sum(r[np.isfinite(r)] ** 2))

    assert cost(trf["params"]) <= cost(lm["params"]) * (1 + 1e-6)


@pytest.mark.skipif(not fastsim_available(), reason="optional package fastsim (extra 'fastsim') not installed")
def test_thermal_fit_on_power_only_logs_takes_few_evaluations(monkeypatch):
    """A cold soak and a warm restart of the FASTSim car (drives 1 and 4 of the selection pool): with the
    bounds transformed, Levenberg-Marquardt ran into its limit of 16000 evaluations here."""
    from calib.ingest import to_drivelog
    from testcars.synth_fastsim import synthesise_fastsim
    from iptm.benchmarks.calib import SELECTION_SEED, selection_pool

    pool = selection_pool()
    logs = [to_drivelog(*synthesise_fastsim(pool[i - 1][1], seed=SELECTION_SEED + i)[1:]) for i in (1, 4)]
    calls = []
    real = thermal_mod.coolant_replay

    def counting(*a):
        calls.append(1)
        return real(*a)

    monkeypatch.setattr(thermal_mod, "coolant_replay", counting)
    fit = fit_thermal(logs, default_parameters())
    assert len(fit.logs) == 2
    assert len(calls) < 2000, len(calls)


def test_calibrate_times_each_step(sample):
    from calib.fit.driver import calibrate

    res = calibrate([sample], validate=[sample], progress=False)
    assert set(res.timings) == {"battery", "fuel", "thermal", "cabin", "validation", "diagnostics"}
    assert all(v >= 0.0 for v in res.timings.values())
    assert sum(res.timings.values()) <= res.wall_s
