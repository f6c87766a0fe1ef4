"""The FTP procedure (bag weighting, soak, cold-test heater) and the engine-on-while-cold rule."""
import numpy as np
import pytest

from calib.model import ftp
from calib.model.equations import CAT, IDLE, OFF, ON
from calib.model.params import default_parameters
from calib.model.rulebased import RuleBasedController, RuleParams


def test_weighting_three_bags_by_hand():
    # 0.43 (10 + 20) / (3 + 4) + 0.57 (30 + 20) / (5 + 4)
    assert ftp.weighted_fuel_per_distance([10, 20, 30], [3, 4, 5]) == pytest.approx(
        0.43 * 30 / 7 + 0.57 * 50 / 9, rel=1e-12)
    assert ftp.weighted_fuel_per_distance([10, 20, 30], [3, 4, 5]) == pytest.approx(5.0095238, rel=1e-6)


def test_weighting_four_bags_by_hand():
    # 0.43 (10 + 20) / (3 + 4) + 0.57 (30 + 40) / (5 + 6)
    assert ftp.weighted_fuel_per_distance([10, 20, 30, 40], [3, 4, 5, 6]) == pytest.approx(5.4701299, rel=1e-6)


def test_weighting_reproduces_epa_composite_from_its_bags():
    # EPA Test Car List 2022 Prius: bags 50.71/126.29/62.72/114.35 mpg, FTP 78.0 mpg; UDDS phases
    # 3.59 and 3.86 miles (FTP-75: 11.04 miles over bags 1-3)
    mpg = ftp.composite_mpg([50.71, 126.29, 62.72, 114.35], [3.59, 3.86, 3.59, 3.86])
    assert mpg == pytest.approx(78.0, abs=0.1)


def test_weighting_rejects_wrong_bag_count():
    with pytest.raises(ValueError, match="3 or 4 bags"):
        ftp.weighted_fuel_per_distance([1, 2], [1, 2])


def _ctrl(Q_heat, **kw):
    # the thermal engine-on rules alone: no warm-up charge (tested separately below)
    kw = {"soc_warmup": RuleParams().soc_target, **kw}
    return RuleBasedController(default_parameters().model_params(), RuleParams(Q_heat_W=Q_heat, **kw))


@pytest.mark.parametrize("T_cl, Q_heat, expected", [
    (45.0, 1500.0, IDLE),  # heat requested, coolant below T_heat_on: keeps running
    (45.0, 0.0, OFF),  # no heat requested: above T_idle it may stop
    (60.0, 1500.0, OFF),  # warm enough: stops even with the heater on
    (30.0, 0.0, IDLE),  # below T_idle it never stops
])
def test_engine_kept_running_while_cold_and_heat_requested(T_cl, Q_heat, expected):
    c = _ctrl(Q_heat)
    e, _, _ = c(0, 0.6, T_cl, 10.0, 0.0)  # standstill: the load rules would stop the engine
    assert e == expected


def test_engine_on_rule_threshold_is_a_parameter():
    assert _ctrl(1500.0, T_heat_on_degC=40.0)(0, 0.6, 45.0, 10.0, 0.0)[0] == OFF


def test_cold_udds_never_stops_engine_below_threshold_with_heat():
    from calib.model.simulate import simulate

    res = simulate(default_parameters(), "udds", T_amb=-6.7, soc0=0.6, T_cl0=-6.7, T_cab0=-6.7, Q_heat=1500.0)
    cold = res.T_cl[:-1] < RuleParams().T_heat_on_degC
    assert cold.sum() > 100 and not np.any(res.e_mode[cold] == OFF)


def test_soak_cools_towards_ambient_without_heater():
    mp = default_parameters().model_params()
    T_cl, T_cab = ftp.soak(mp, 80.0, 20.0, -6.7)
    assert -6.7 < T_cl < 80.0 and -6.7 < T_cab < 20.0
    assert ftp.soak(mp, -6.7, -6.7, -6.7) == pytest.approx((-6.7, -6.7))


def test_cold_test_heater_waits_for_warm_coolant():
    mp = default_parameters().model_params()
    c = ftp.ColdTestController(mp, RuleParams(), T_amb=-6.7)
    assert c(0, 0.6, ftp.BLOWER_RAMP_DEGC[0] - 1.0, -6.7, 0.0)[2] == 0.0
    q_full = c(0, 0.6, 70.0, -6.7, 0.0)[2]
    assert q_full == pytest.approx(mp.eps_hc * ftp.BLOWER_MAX_KG_PER_S * mp.cp_air * 76.7)
    assert c(0, 0.6, 70.0, ftp.T_SET_DEGC + 1.0, 0.0)[2] == 0.0  # cabin at its set point


def test_ftp_bags_match_the_udds_phases():
    r = ftp.run_ftp(default_parameters(), ftp.COLD_FTP)
    miles = np.array(r.distance_m) / ftp.M_PER_MILE
    assert len(miles) == 3
    # the UDDS phases are 3.59 and 3.86 miles (EPA; FTP-75 11.04 miles)
    assert miles == pytest.approx([3.59, 3.86, 3.59], abs=0.02)
    assert r.soc_bounds[0] == 0.6 and len(r.T_cl_bounds) == 4
    assert r.runs[1].T_cl[0] < r.runs[0].T_cl[-1]  # the soak cooled the engine
    w = ftp.run_ftp(default_parameters(), ftp.WARM_FTP)
    assert len(w.distance_m) == 4 and not np.any(w.runs[0].flows["Q_heat"] > 0)
    assert r.composite_mpg < w.composite_mpg


def test_engine_on_rule_follows_the_actual_heat_request():
    # a climate control that switches the heater off releases the engine
    c = _ctrl(1500.0)
    c.heat_request_W = 0.0
    assert c(0, 0.6, 45.0, 10.0, 0.0)[0] == OFF
    c.reset()  # back to the controller's own fixed demand
    assert c(0, 0.6, 45.0, 10.0, 0.0)[0] == IDLE


def test_ftp_comparison_table_has_both_tests():
    from calib.model import ftp_comparison

    df = ftp_comparison(default_parameters())
    assert list(df["test"]) == [ftp.WARM_FTP.name, ftp.COLD_FTP.name]
    assert list(df["epa_mpg"]) == [78.0, 56.3]


def test_catalyst_heating_burns_its_rate_and_gives_no_power():
    from calib.model.equations import evaluate

    ps = default_parameters()
    r = evaluate(ps, 0.6, -5.0, -5.0, CAT, 0.0, 0.0, 5.0, 6.0, T_amb=-5.0)
    assert r["W_f"] == pytest.approx(ps["W_cat_g_per_s"]) and r["P_e"] == 0.0
    assert r["omega_e"] == pytest.approx(ps["n_cat_rpm"] * 2 * np.pi / 60)
    assert r["P_em"] == pytest.approx(r["P_trac"])  # the motor drives the car


def test_warm_up_charges_the_battery_at_a_standstill():
    rp = RuleParams()
    c = RuleBasedController(default_parameters().model_params(), rp)
    e, pb, _ = c(0, rp.soc_warmup - 0.05, 30.0, 10.0, 0.0)
    assert e == ON and pb < 0.0  # charging
    c.reset()
    assert c(0, rp.soc_warmup + 0.01, 30.0, 10.0, 0.0)[0] == IDLE  # charged: only the thermal hold remains
    c.reset()
    assert c(0, rp.soc_warmup - 0.05, rp.T_warm_degC + 1.0, 10.0, 0.0)[0] == OFF  # warm: no warm-up charge


def test_surplus_charge_raises_the_start_threshold():
    rp = RuleParams()
    P = rp.P_on_W + 0.5 * rp.k_on_W * 0.1
    c = RuleBasedController(default_parameters().model_params(), rp)
    assert c(0, rp.soc_target, 90.0, 20.0, P)[0] == ON
    c.reset()
    assert c(0, rp.soc_target + 0.1, 90.0, 20.0, P)[0] == OFF


def test_us06_bag_split_reproduces_epa_result():
    # EPA's two US06 bags, weighted by the city (0-130 s and 495 s to the end) and highway (130-495 s)
    # distances of the bundled cycle, give EPA's 48.6 mpg: the split is the one EPA used
    from calib.model.cycles import load_cycle
    from calib.model.epa import EPA_BAGS_MPG, EPA_MPG, US06_BAGS_S

    v = load_cycle("us06").v
    miles = [sum(float(np.sum(0.5 * (v[a + 1:(b or len(v) - 1) + 1] + v[a:(b or len(v) - 1)])))
                 for a, b in parts) / ftp.M_PER_MILE for parts in US06_BAGS_S]
    gal = sum(m / e for m, e in zip(miles, EPA_BAGS_MPG["us06"]))
    assert sum(miles) / gal == pytest.approx(EPA_MPG["us06"], abs=0.1)


def test_every_bag_within_15_percent_and_composites_within_5():
    from calib.model.epa import bag_table

    ps = default_parameters()
    df = bag_table(ps)
    assert len(df) == 10 and (df["error_raw_pct"].abs() <= 15.0).all(), df.to_string()
    for c in (ftp.WARM_FTP, ftp.COLD_FTP):
        assert abs(ftp.run_ftp(ps, c).error_pct) <= 5.0
