"""Forward simulation: energy balances, EPA comparison, rule-based behaviour, results object."""
import numpy as np
import pytest

from calib.model.epa import epa_comparison
from calib.errors import ScenarioError
from calib.model.equations import IDLE, OFF, ON
from calib.model.rulebased import RuleParams
from calib.model.simulate import simulate


@pytest.fixture(scope="module")
def winter(params):
    return simulate(params, "artemis_urban", T_amb=-10.0, soc0=0.6, T_cl0=70.0, T_cab0=20.0, Q_heat=1500.0)


def test_energy_balances_close(winter):
    bal = winter.energy_balance()
    for k, v in bal.items():
        if k.startswith("residual"):
            assert abs(v) < 1e-9, k
    assert bal["fuel_energy_J"] > 0 and bal["heater_J"] > 0


def test_cold_start_balances_close_with_heater_shortfall(params):
    r = simulate(params, "nycc", T_amb=-10.0, soc0=0.6, T_cl0=-10.0, T_cab0=-10.0, Q_heat=1500.0)
    s = r.summary()
    assert s["energy_balance_residual_rel"] < 1e-9
    assert s["heater_shortfall_J"] > 0  # the cold core cannot deliver 1500 W at first
    assert np.all(r.flows["Q_heat"] <= r.flows["Q_heat_max"] + 1e-9)
    # thermal rule: below 40 degC the engine idles rather than stops
    cold = r.T_cl[:-1] < 40.0
    assert np.all(r.e_mode[cold] != OFF)
    assert np.any(r.e_mode == IDLE)


def test_epa_within_3_percent(params):
    # README: the default parameter set is within 3 % (SOC-corrected mpg) of EPA on UDDS, HWFET and US06
    df = epa_comparison(params)
    assert (df["error_pct"].abs() <= 3.0).all(), df.to_string()


def test_results_object(winter, tmp_path):
    df = winter.to_pandas()
    assert len(df) == len(winter.t)
    assert {"soc", "T_cl_degC", "P_e", "W_f", "fuel_cum_g"} <= set(df.columns)
    assert df["fuel_cum_g"].iloc[-1] == pytest.approx(winter.fuel_g)
    winter.plot(tmp_path / "x.png")
    assert (tmp_path / "x.png").stat().st_size > 10_000
    s = winter.summary()
    assert s["engine_starts"] > 0 and s["distance_km"] == pytest.approx(4.87, abs=0.05)


def test_soc_correction_sign(params):
    low = simulate(params, "nycc", rule_params=RuleParams(soc_target=0.5, soc_low=0.45), T_amb=24.0, soc0=0.6,
                   T_cl0=90.0, T_cab0=22.0, Q_heat=0.0).summary()
    assert low["soc_final"] < 0.6
    assert low["fuel_soc_corrected_g"] > low["fuel_g"]  # ending with less charge costs fuel


def test_infeasible_controller_is_reported(params):
    def greedy(k, soc, T_cl, T_cab, P_trac, Ts):
        return ON, 30e3, 0.0  # above the battery's discharge limit

    with pytest.raises(ScenarioError, match="step 0 .*infeasible: engine power outside"):
        simulate(params, "nycc", greedy)


def test_custom_cycle_file(params, tmp_path):
    f = tmp_path / "c.csv"
    t = np.arange(0, 121)
    f.write_text("time_s,speed_kph\n" + "\n".join(f"{a},{min(a, 60) * 0.8:.2f}" for a in t))
    r = simulate(params, str(f), T_amb=0.0)
    assert len(r.t) == 121


def test_credit_per_gram_is_the_closed_form_and_exceeds_one_when_the_engine_works():
    """The corrected fuel credits charge at the best-efficiency valuation and coolant heat at the idling
    valuation; one gram burnt at brake efficiency eta is then credited 1 + eta (1/eta_max - 1) grams
    (work P_e = eta LHV W_f; heat to coolant (1 - gamma)(1 - eta) LHV W_f), worked out by hand here."""
    from calib.model import credit_per_gram
    from calib.model.equations import ON, fuel_rate
    from calib.model.params import default_parameters

    p = default_parameters().model_params()
    eta_max = float(np.max(p.eta_ool))
    for P_e in (5e3, 12e3, 25e3):
        eta = P_e / (p.LHV * fuel_rate(p, ON, P_e, 90.0))
        assert credit_per_gram(p, P_e) == pytest.approx(1.0 + eta * (1.0 / eta_max - 1.0), rel=1e-3)
        assert credit_per_gram(p, P_e) > 1.4
