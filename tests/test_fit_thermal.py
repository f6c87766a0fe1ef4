"""Engine thermal fit: output-error truth recovery, the thermostat flags, missing coolant channel."""
import dataclasses
import functools

import numpy as np
import pytest

import calib.fit.thermal as thermal
from calib.fit.thermal import fit_thermal
from calib.ingest import to_drivelog
from calib.model.params import default_parameters
from calib.synth import Scenario, draw_truth, synthesise

FIT = [Scenario("cold", "udds", -10.0, 0.60, -10.0, -10.0, T_bat=-5.0, with_bay_temp=True,
                 heater_off=[(800.0, 1100.0)]),  # identification protocol (logs/README.md)
       Scenario("warm", "hwfet", -5.0, 0.55, 65.0, 15.0, T_bat=5.0),
       Scenario("hot", "us06", -3.0, 0.60, 80.0, 18.0, T_bat=8.0)]
THERMAL = ("C_eng_J_per_K", "gamma_exh", "hA_eng_W_per_K", "kappa", "T_open_degC", "k_rad_W_per_K")


@functools.lru_cache(maxsize=None)
def logs_for(seed, which=(0, 1, 2), drop=()):
    truth = draw_truth(seed)
    out = []
    for i in which:
        sc = Scenario(**{**FIT[i].__dict__, "drop_channels": list(drop)})
        out.append(to_drivelog(*synthesise(sc, truth, seed=seed)[1:]))
    return truth, out


def recovery_failures(fit, truth):
    bad = []
    for n, e in fit.estimates.items():
        if e.status == "estimated":
            tv = truth[n]
            if abs(e.value - tv) > 3 * e.stderr or abs(e.value - tv) > 0.1 * abs(tv):
                bad.append((n, e.value, e.stderr, tv))
    return bad


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_thermal_recovers_truth(seed):
    truth, logs = logs_for(seed)
    fit = fit_thermal(logs, default_parameters())
    for n in ("C_eng_J_per_K", "gamma_exh", "kappa"):
        assert fit.estimates[n].status == "estimated", (n, fit.estimates[n].note)
    assert recovery_failures(fit, truth) == []
    for e in fit.estimates.values():
        assert e.stderr is not None and e.prior_sd is not None and 0 <= e.informed <= 1
    assert fit.metrics["rmse_degC"] < 0.6
    assert fit.metrics["above_regulation_s"] == 0.0  # a radiator that regulates: nothing is left out


def test_winter_log_below_thermostat_flags_T_open_and_k_rad():
    truth, logs = logs_for(1, which=(0,))  # UDDS cold start at -10 degC: coolant stays far below 80 degC
    fit = fit_thermal(logs, default_parameters())
    assert fit.metrics["coolant_max_degC"] < 80
    for n in ("T_open_degC", "k_rad_W_per_K"):
        e = fit.estimates[n]
        # no data above the thermostat: the posterior is the prior, with the prior sd
        assert e.status == "weak" and e.informed < 0.3
        assert "thermostat" in e.note
        assert e.value == pytest.approx(default_parameters()[n], rel=0.02)


def test_log_without_coolant_says_thermal_not_fitted():
    truth, logs = logs_for(1, which=(0,), drop=("coolant_temp_degC",))
    fit = fit_thermal(logs, default_parameters())
    assert not fit.fitted
    assert "coolant_temp_degC" in fit.message
    for n in THERMAL:
        assert fit.estimates[n].status == "prior"
        assert "not fitted" in fit.estimates[n].note


def test_kappa_without_bay_temperature_stays_at_prior():
    truth, logs = logs_for(2, which=(1, 2))  # no bay temperature in these two
    fit = fit_thermal(logs, default_parameters())
    k = fit.estimates["kappa"]
    assert k.status == "weak" and k.value == default_parameters()["kappa"] and k.informed == 0.0
    assert "hA_eng (1 - kappa)" in k.note
    h = fit.estimates["hA_eng_W_per_K"]
    if h.status == "estimated":
        assert "only as hA_eng (1 - kappa)" in h.note


def test_coolant_beyond_the_radiator_span_does_not_drag_k_rad(monkeypatch):
    """A 300 s excursion to 50 K above the regulated coolant (a radiator that did not hold it, like one that
    cools only at a standstill) is left out: k_rad stays with the truth; fitted, it drags k_rad down."""
    truth, logs = logs_for(1)
    lg = logs[2]  # warm US06 start: the thermostat regulates
    T = lg.data["coolant_temp_degC"].to_numpy(float)
    a = T.size // 3
    d = lg.data.copy()
    d["coolant_temp_degC"] = T + np.interp(np.arange(T.size), [a, a + 150, a + 300], [0.0, 50.0, 0.0])
    hot = [logs[0], logs[1], dataclasses.replace(lg, data=d)]
    base = default_parameters()
    limit = thermal.regulation_limit(base)
    assert limit == pytest.approx(base["T_open_degC"] + base["Q_rad_max_W"] / base["k_rad_W_per_K"])
    fit = fit_thermal(hot, base)
    e, tv = fit.estimates["k_rad_W_per_K"], truth["k_rad_W_per_K"]
    n_hot = int(np.sum(d["coolant_temp_degC"].to_numpy(float) > limit))
    assert n_hot > 60 and fit.metrics["above_regulation_s"] == pytest.approx(n_hot * lg.dt)
    assert "above the thermostat" in fit.used[hot[2].label()]
    assert f"{limit:.0f} degC informs it" in e.note
    assert abs(e.value - tv) < 2 * e.stderr
    monkeypatch.setattr(thermal, "regulation_limit", lambda p: np.inf)
    dragged = fit_thermal(hot, base).estimates["k_rad_W_per_K"]
    assert dragged.value < 0.7 * tv and abs(dragged.value - tv) > 2 * dragged.stderr
