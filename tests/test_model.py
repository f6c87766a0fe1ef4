"""Unit tests per equation of docs/model.md: balances, steady states, limits."""
import math

import numpy as np
import pytest

from calib.model import equations as M


def test_traction_power_road_load_at_constant_speed(mp):
    v = 20.0
    P = M.traction_power(mp, v, v, 0.0, 1.0)
    assert P == pytest.approx((mp.A + mp.B * v + mp.C * v * v) * v)


def test_traction_power_road_load_applies_at_any_speed_above_zero(mp):
    """Creeping at 0.5 m/s (mean of 0.4 and 0.6 over 1 s) the road load acts; at standstill it does not."""
    vm, a = 0.5, 0.2
    P = M.traction_power(mp, 0.4, 0.6, 0.0, 1.0)
    assert P == pytest.approx((mp.m_eq * a + mp.A + mp.B * vm + mp.C * vm * vm) * vm, rel=1e-12)
    assert M.traction_power(mp, 0.0, 0.0, 0.0, 1.0) == 0.0


def test_traction_power_kinetic_energy_exact(mp):
    # with no road load the energy over a step is exactly the kinetic-energy change of m_eq
    mp0 = mp._replace(A=0.0, B=0.0, C=0.0)
    v0, v1 = 3.0, 5.5
    assert M.traction_power(mp0, v0, v1, 0.0, 1.0) == pytest.approx(0.5 * mp.m_eq * (v1**2 - v0**2))


def test_traction_power_grade(mp):
    P = M.traction_power(mp._replace(A=0, B=0, C=0), 10.0, 10.0, 0.05, 1.0)
    assert P == pytest.approx(mp.m * 9.81 * math.sin(0.05) * 10.0)


@pytest.mark.parametrize("P_bat", [-20e3, -1e3, 0.0, 500.0, 15e3])
def test_battery_power_identity(mp, P_bat):
    I, V, U, R, code = M.battery(mp, 0.55, P_bat, 26.0)
    assert code == M.FEASIBLE
    assert V * I == pytest.approx(P_bat, abs=1e-6)
    assert U * I == pytest.approx(P_bat + R * I * I, abs=1e-6)  # chemical = terminal + loss


def test_battery_infeasible_beyond_max_power(mp):
    U, R = M.battery_ocv_r(mp, 0.5, 26.0)
    I, V, _, _, code = M.battery(mp, 0.5, 1.01 * U * U / (4 * R), 26.0)
    assert code == M.BATTERY_ROOT and math.isnan(I)


def test_battery_limit_flagged(mp):
    assert M.battery(mp, 0.5, mp.P_bat_max + 1.0, 26.0)[4] == M.BATTERY_LIMIT
    assert M.battery(mp, 0.5, mp.P_bat_min - 1.0, 26.0)[4] == M.BATTERY_LIMIT


def test_each_infeasibility_has_its_own_code_and_reason(mp):
    """The power limit and the missing root are told apart: distinct codes, each with its own message."""
    assert len({M.FEASIBLE, M.ENGINE_POWER, M.BATTERY_LIMIT, M.BATTERY_ROOT}) == 4
    U, R = M.battery_ocv_r(mp, 0.5, 26.0)
    limit = M.battery(mp, 0.5, mp.P_bat_max + 1.0, 26.0)[4]
    root = M.battery(mp, 0.5, 1.01 * U * U / (4 * R), 26.0)[4]
    assert "outside [P_bat_min, P_bat_max]" in M.INFEASIBLE_REASONS[limit]
    assert "no real current" in M.INFEASIBLE_REASONS[root]
    assert "engine power" in M.INFEASIBLE_REASONS[M.ENGINE_POWER]


def test_battery_resistance_rises_in_cold(mp):
    _, R26 = M.battery_ocv_r(mp, 0.5, 26.0)
    _, R1 = M.battery_ocv_r(mp, 0.5, 1.0)
    assert R26 == pytest.approx(0.26, rel=0.02)
    assert R1 == pytest.approx(0.50, rel=0.05)  # spec: 0.50 Ohm at 1 degC


def test_pack_ocv_matches_spec(mp):
    assert M.battery_ocv_r(mp, 0.5, 26.0)[0] == pytest.approx(220.8, abs=0.1)


def test_power_split_engine_path_balance(mp):
    P_trac = 12e3
    P_e, Pbm, P_em, brake, ok = M.power_split(mp, M.ON, 3e3, P_trac)
    assert ok and brake == 0.0
    assert mp.eta_mech * P_e + P_em == pytest.approx(P_trac)
    assert P_em == pytest.approx(mp.eta_em * 3e3)


def test_power_split_charging_at_standstill(mp):
    P_e, Pbm, P_em, _, ok = M.power_split(mp, M.ON, -5e3, 0.0)
    assert ok and P_e == pytest.approx(5e3 / mp.eta_em / mp.eta_mech)


def test_power_split_engine_off_regen_limit(mp):
    P_e, Pbm, P_em, brake, ok = M.power_split(mp, M.OFF, 0.0, -40e3)
    assert ok and P_e == 0.0
    assert P_em == -mp.P_regen_max and brake == pytest.approx(-40e3 + mp.P_regen_max)
    assert Pbm == pytest.approx(-mp.P_regen_max * mp.eta_em)


def test_power_split_engine_power_limits(mp):
    assert not M.power_split(mp, M.ON, 10e3, 0.0)[4]  # engine would absorb power
    assert not M.power_split(mp, M.ON, 0.0, 80e3)[4]  # above P_e_max
    # the bounds: 0 < P_e <= P_e_max (an engine at half a watt is on, one at zero power is not)
    assert M.power_split(mp, M.ON, 0.0, 0.5 * mp.eta_mech)[4]
    assert not M.power_split(mp, M.ON, 0.0, 0.0)[4]
    assert M.power_split(mp, M.ON, 0.0, mp.P_e_max * mp.eta_mech)[4]


def test_fuel_modes_and_cold_factor(mp):
    assert M.fuel_rate(mp, M.OFF, 0.0, 20.0) == 0.0
    assert M.fuel_rate(mp, M.IDLE, 0.0, 90.0) == pytest.approx(mp.W_idle)
    assert M.fuel_rate(mp, M.IDLE, 0.0, -10.0) == pytest.approx(1.5 * mp.W_idle)
    w_warm = M.fuel_rate(mp, M.ON, 20e3, 90.0)
    assert w_warm == pytest.approx(mp.fuel_scale * 20e3 / (np.interp(20e3, mp.P_ool, mp.eta_ool) * mp.LHV))
    assert M.fuel_rate(mp, M.ON, 20e3, 20.0) == pytest.approx(1.2 * w_warm)
    assert M.fuel_rate(mp, M.ON, 10.0, 90.0) == pytest.approx(mp.W_idle)  # never below idle


def test_fuel_above_the_thermostat(mp):
    """The coolant factor's nodes above the warm reference (80 degC): at their default (1) the fuel is that
    of a table that ends at 80 degC; below 1 they lower the fuel there, and only there."""
    assert list(mp.T_fcl[mp.T_fcl >= 80.0]) == [80.0, 90.0, 100.0, 120.0]
    old = mp._replace(T_fcl=np.array([-10.0, 20.0, 60.0, 80.0]), f_cl=np.array([1.5, 1.2, 1.05, 1.0]))
    for T in (-20.0, -10.0, 5.0, 40.0, 70.0, 80.0, 85.0, 95.0, 110.0, 120.0, 150.0):
        for mode, P in ((M.IDLE, 0.0), (M.ON, 14e3), (M.ON, 40e3)):
            assert M.fuel_rate(mp, mode, P, T) == M.fuel_rate(old, mode, P, T), (T, mode, P)
    hot = mp._replace(f_cl=np.array([1.5, 1.2, 1.05, 1.0, 0.98, 0.95, 0.9]))
    w80 = M.fuel_rate(mp, M.ON, 14e3, 80.0)
    assert M.fuel_rate(hot, M.ON, 14e3, 80.0) == w80
    assert M.fuel_rate(hot, M.ON, 14e3, 40.0) == M.fuel_rate(mp, M.ON, 14e3, 40.0)  # cold side unchanged
    assert M.fuel_rate(hot, M.ON, 14e3, 95.0) == pytest.approx(0.965 * w80)  # halfway 90-100
    assert M.fuel_rate(hot, M.ON, 14e3, 120.0) == pytest.approx(0.9 * w80)
    assert M.fuel_rate(hot, M.ON, 14e3, 140.0) == pytest.approx(0.9 * w80)  # flat beyond the last node
    assert M.fuel_rate(hot, M.IDLE, 0.0, 100.0) == pytest.approx(0.95 * mp.W_idle)


def test_engine_speed_on_ool_matches_rating(mp):
    w = M.engine_speed(mp, M.ON, 72e3)
    assert w * 60 / (2 * math.pi) == pytest.approx(5200, rel=0.01)


def test_heater_core_limit(mp):
    assert M.heater_limit(mp, 70.0, 20.0, -10.0, 0.06) == pytest.approx(0.7 * 0.06 * 1005 * 80)
    assert M.heater_limit(mp, -15.0, 20.0, -10.0, 0.06) == 0.0
    r = M.step(mp, 0.6, 0.0, 15.0, M.OFF, 0.0, 5000.0, 0.0, 0.0, 0.0, -10.0, 26.0, 0.06, 1.0)
    q = dict(zip(M.OUTPUTS, r))
    assert q["Q_heat"] == pytest.approx(q["Q_heat_max"]) and q["Q_heat"] < 5000.0
    # below the limit the command is delivered as it is, however small; a negative one delivers nothing
    for cmd, want in ((0.5, 0.5), (-200.0, 0.0)):
        q = dict(zip(M.OUTPUTS, M.step(mp, 0.6, 70.0, 15.0, M.OFF, 0.0, cmd, 0.0, 0.0, 0.0, -10.0, 26.0, 0.06, 1.0)))
        assert q["Q_heat"] == want


def test_radiator_caps(mp):
    assert M.radiator(mp, mp.T_open - 1) == 0.0
    assert M.radiator(mp, mp.T_open + 2) == pytest.approx(2 * mp.k_rad)
    assert M.radiator(mp, 200.0) == mp.Q_rad_max


def test_cabin_steady_state(mp):
    T_amb, Q = -10.0, 1500.0
    T_ss = T_amb + (Q + mp.Q_sun) / mp.UA_cab
    assert M.cabin_rate(mp, T_ss, T_amb, Q)[0] == pytest.approx(0.0, abs=1e-12)
    T = 0.0
    for _ in range(40000):
        T += M.cabin_rate(mp, T, T_amb, Q)[0]
    assert T == pytest.approx(T_ss, abs=0.01)


def test_coolant_decays_to_ambient_with_nothing_on(mp):
    T = 80.0
    for _ in range(200000):
        T += M.coolant_flows(mp, T, -10.0, 0.0, 0.0, 0.0)[0]
    assert T == pytest.approx(-10.0, abs=0.05)


def test_radiator_caps_coolant_under_sustained_load(mp):
    # engine at 30 kW for an hour, no heater: the coolant settles where the radiator (not saturated) and
    # the engine-bay loss carry away the heat: T = (Q_in + hA' T_amb + k_rad T_open) / (hA' + k_rad)
    T, P_e, T_amb = 20.0, 30e3, -10.0
    for _ in range(3600):
        W = M.fuel_rate(mp, M.ON, P_e, T)
        T += M.coolant_flows(mp, T, T_amb, mp.LHV * W, P_e, 0.0)[0]
    Q_in = (1 - mp.gamma_exh) * (mp.LHV * M.fuel_map(mp, P_e) - P_e)
    hA = mp.hA_eng * (1 - mp.kappa)
    T_ss = (Q_in + hA * T_amb + mp.k_rad * mp.T_open) / (hA + mp.k_rad)
    assert T == pytest.approx(T_ss, abs=0.05)
    assert mp.T_open < T_ss < mp.T_open + mp.Q_rad_max / mp.k_rad
    # without the radiator the same load would boil the coolant
    assert T_amb + Q_in / hA > 150.0


def test_evaluate_broadcasts_over_grids(params):
    soc = np.linspace(0.4, 0.8, 41)[:, None, None]
    T_cl = np.linspace(0, 100, 11)[None, :, None]
    P = np.linspace(-25e3, 25e3, 21)[None, None, :]
    r = M.evaluate(params, soc, T_cl, 20.0, M.ON, P, 1500.0, 8.0, 8.5, T_amb=-10.0)
    assert r["soc_next"].shape == (41, 11, 21)
    # scalar step and vectorised evaluation are the same implementation
    s = M.step(params.model_params(), 0.5, 50.0, 20.0, M.ON, 5e3, 1500.0, 8.0, 8.5, 0.0, -10.0, 26.0, 0.06, 1.0)
    r1 = M.evaluate(params, 0.5, 50.0, 20.0, M.ON, 5e3, 1500.0, 8.0, 8.5, T_amb=-10.0)
    assert [float(r1[n]) for n in M.OUTPUTS] == pytest.approx(list(s), nan_ok=True)
