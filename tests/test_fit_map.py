"""Maximum a posteriori estimation, channel inference and honest validation."""
import functools

import lmfit
import numpy as np
import pytest

from calib.fit.toolkit import map_fit
from calib.ingest import to_drivelog
from calib.synth import Scenario, draw_truth, synthesise


def _toy(n, slope_data=True, noise=0.1, seed=0):
    """y = a x + noise; b has no data at all."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, n)
    y = 2.0 * x + rng.normal(0, noise, n)

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=1.0, min=-10, max=10)
        ps.add("b", value=5.0, min=-100, max=100)
        return ps

    def segs(ps):
        return [ps["a"].value * x - y] if slope_data else [np.zeros(n)]

    return map_fit(make, segs, ["a", "b"], prior={"a": 1.0, "b": 5.0}, prior_sd={"a": 0.5, "b": 3.0},
                   noise_sd=noise)


def test_parameter_without_data_returns_its_prior_with_the_prior_sd():
    out = _toy(500)
    assert out["values"]["b"] == pytest.approx(5.0, abs=1e-6)
    assert out["post_sd"]["b"] == pytest.approx(3.0, rel=1e-3)
    assert out["informed"]["b"] == pytest.approx(0.0, abs=1e-3)


def test_strong_data_dominate_the_prior():
    out = _toy(2000)
    assert out["values"]["a"] == pytest.approx(2.0, abs=0.03)  # the prior said 1.0 +- 0.5
    assert out["post_sd"]["a"] < 0.05 * 0.5
    assert out["informed"]["a"] > 0.95


def test_weak_data_stay_between_prior_and_data():
    out = _toy(5, noise=2.0, seed=1)
    a = out["values"]["a"]
    assert 0.4 < out["post_sd"]["a"] / 0.5 < 1.0  # some information, not much
    assert abs(a - 1.0) < 1.0  # pulled towards the prior


def test_posterior_sd_matches_the_closed_form():
    """Linear Gaussian model: posterior precision = sum x^2 / s^2 + 1 / prior_sd^2."""
    n, s = 200, 0.3
    x = np.linspace(0, 1, n)
    y = 1.5 * x  # noise-free so that the re-estimated noise is the floor

    def make():
        ps = lmfit.Parameters()
        ps.add("a", value=1.0)
        return ps

    out = map_fit(make, lambda ps: [ps["a"].value * x - y + s * np.sign(np.sin(40 * x))], ["a"],
                  prior={"a": 1.0}, prior_sd={"a": 0.5}, noise_sd=s, floor=s)
    sd = out["noise_sd"]
    expect = 1.0 / np.sqrt(np.sum(x * x) / sd ** 2 + 1 / 0.25)
    assert out["post_sd"]["a"] == pytest.approx(expect, rel=0.05)


# -------------------------------------------------------------------------------------------------
# what a log has
# -------------------------------------------------------------------------------------------------
SC = Scenario("t", "udds", -10.0, 0.60, -10.0, -10.0, T_bat=-5.0)


@functools.lru_cache(maxsize=None)
def _log(drop=(), power=False):
    truth = draw_truth(5)
    sim, streams, meta = synthesise(Scenario(**{**SC.__dict__, "drop_channels": list(drop)}), truth, seed=5)
    lg = to_drivelog(streams, meta)
    if power:  # a logger that records powers instead of speed x torque and V x I
        d = lg.data.copy()
        full = to_drivelog(*synthesise(SC, truth, seed=5)[1:]).data
        d["engine_power_W"] = full["engine_speed_rpm"] * full["engine_torque_Nm"] * 2 * np.pi / 60
        d["bat_power_W"] = full["bat_current_A"] * full["bat_voltage_V"]
        lg = type(lg)(d, lg.meta)
    return truth, lg


def test_power_channels_are_canonical():
    from calib.drivelog import CHANNELS
    from calib.ingest.common import canonical_name

    assert "engine_power_W" in CHANNELS and "bat_power_W" in CHANNELS
    assert canonical_name("Engine Power") == "engine_power_W"
    assert canonical_name("battery_power") == "bat_power_W"


def test_engine_power_without_speed_and_torque_is_used():
    from calib.fit.replay import log_arrays
    from calib.model.equations import ON

    truth, lg = _log(drop=("engine_speed_rpm", "engine_torque_Nm", "bat_current_A", "bat_voltage_V"), power=True)
    la = log_arrays(lg, truth.model_params())
    assert la.engine_source == "engine_power_W" and la.battery_source == "bat_power_W"
    assert (la.mode == ON).sum() > 100
    from calib.fit.fuel import fit_fuel

    fit = fit_fuel([lg], truth)
    assert fit.logs and "engine_power_W" in next(iter(fit.used.values()))["engine power"]


def test_engine_power_inferred_from_the_balance():
    from calib.fit.replay import log_arrays

    truth, lg = _log(drop=("engine_speed_rpm", "engine_torque_Nm"))
    la = log_arrays(lg, truth.model_params())
    assert la.engine_source.startswith("inferred") and "engine power" in la.inferred
    full = to_drivelog(*synthesise(SC, truth, seed=5)[1:])
    P_true = (full.data["engine_speed_rpm"] * full.data["engine_torque_Nm"] * 2 * np.pi / 60).to_numpy()
    on = P_true > 5e3
    # the balance gives the engine power within a few kW where the engine runs (the 1 s bins mix steps)
    assert np.nanmedian(np.abs(la.P_e[on] - P_true[on])) < 3e3


def test_battery_current_inferred_from_power_for_the_capacity():
    from calib.fit.battery import fit_battery

    truth, lg = _log(drop=("engine_speed_rpm", "engine_torque_Nm", "bat_current_A", "bat_voltage_V"), power=True)
    fit = fit_battery([lg], truth)
    assert "inferred" in next(iter(fit.used.values()))["current"]
    assert fit.estimates["U_oc_V"].status == "prior"  # the tables need voltage and current
    assert "C_bat_Ah" in fit.estimates and fit.estimates["C_bat_Ah"].status in ("estimated", "weak")


# -------------------------------------------------------------------------------------------------
# validation refuses what it cannot replay
# -------------------------------------------------------------------------------------------------
def test_replay_without_engine_data_refuses_fuel_and_coolant():
    from calib.fit.validate import replay, validate

    truth, lg = _log(drop=("engine_speed_rpm", "engine_torque_Nm", "bat_current_A", "bat_voltage_V", "speed_mps"))
    rep = replay(lg, truth)
    assert "fuel_rate" in rep.refused and "coolant_temp" in rep.refused
    assert "engine_speed_rpm" in rep.refused["fuel_rate"]
    m = validate([lg], truth)[rep.name]
    assert "fuel_rate" not in m and "coolant_temp" not in m and "cumulative_fuel" not in m
    assert "fuel_rate" in m["refused"]


def test_replay_without_heater_data_refuses_or_says_it_inferred():
    from calib.fit.validate import replay

    truth, lg = _log(drop=("heater_power_W", "vent_temp_degC", "blower_flow_kg_per_s"))
    rep = replay(lg, truth)
    # the heater heat is inferred from the cabin balance: the coolant runs on it (and says so), the cabin
    # cannot be checked against the signal it was inferred from
    assert "heater power" in rep.inferred and "cabin_temp" in rep.refused and "coolant_temp" in rep.simulated
    truth, lg2 = _log(drop=("heater_power_W", "vent_temp_degC", "blower_flow_kg_per_s", "cabin_temp_degC"))
    rep2 = replay(lg2, truth)
    assert "heater_power_W" in rep2.refused["coolant_temp"]


def test_calibration_without_engine_data_states_what_it_could_not_do():
    from calib.fit.driver import calibrate

    truth, lg = _log(drop=("engine_speed_rpm", "engine_torque_Nm", "bat_current_A", "bat_voltage_V", "speed_mps"))
    res = calibrate([lg], validate=[lg], progress=False)
    assert "engine operating point" in res.fits["fuel"].message
    rep = res.report()
    assert "NOT CHECKED" in rep and "cumulative fuel" not in rep


def test_residual_diagnostics_by_regime():
    from calib.fit.validate import diagnostics, replay

    truth, lg = _log()
    d = diagnostics(replay(lg, truth))
    assert {"soc", "coolant_temp", "cabin_temp", "fuel_rate"} <= set(d)
    c = d["coolant_temp"]
    assert "1s" in c["autocorrelation"] and c["n_eff"] <= c["n"]
    assert any(k.startswith("heater") for k in c["by_regime"])


def test_advice_names_the_drive():
    from calib.fit.driver import calibrate

    truth, lg = _log()  # a cold UDDS: never reaches the thermostat
    res = calibrate([lg], progress=False)
    assert any("thermostat" in a and "T_open" in a for a in res.advice)
    assert "Advice" in res.report()
    assert res.to_dict()["calibration"]["advice"] == res.advice


def test_power_only_log_uses_the_tables_fitted_on_a_full_log():
    from calib.fit.battery import fit_battery

    truth, full = _log()
    _, power = _log(drop=("engine_speed_rpm", "engine_torque_Nm", "bat_current_A", "bat_voltage_V"), power=True)
    power = type(power)(power.data, type(power.meta)(**{**power.meta.__dict__, "source": "power_only.csv"}))
    fit = fit_battery([full, power], truth)
    assert "fitted OCV/resistance" in fit.used[power.label()]["current"]
    assert fit.estimates["U_oc_V"].status == "estimated"
