"""The model's heat equations against references written independently here: hand-worked single flows,
and whole drives whose coolant and cabin temperatures are re-integrated by scipy's ODE solver from the
equations of spec/model.md (eqs. 3, 6-10), with solar gain and recirculation switched on."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from calib.model import equations as M
from calib.model.params import default_parameters
from calib.model.simulate import simulate

# Non-zero sun and recirculation, and values away from the defaults, so that a term with a wrong sign or
# a wrong factor changes the answer.
VALUES = dict(Q_sun_W=350.0, recirc_frac=0.35, gamma_exh=0.42, kappa=0.25, hA_eng_W_per_K=30.0,
              C_eng_J_per_K=70e3, C_cab_J_per_K=55e3, UA_cab_W_per_K=45.0)


@pytest.fixture(scope="module")
def sunny():
    return default_parameters().with_values(**VALUES)


def test_cabin_rate_by_hand(sunny):
    p = sunny.model_params()
    # (Q_heat + UA (T_amb - T_cab) + Q_sun) / C_cab = (1200 + 45 * (-5 - 15) + 350) / 55e3
    d, load = M.cabin_rate(p, 15.0, -5.0, 1200.0)
    assert load == pytest.approx(45.0 * -20.0)
    assert d == pytest.approx((1200.0 - 900.0 + 350.0) / 55e3)


def test_heater_limit_uses_recirculated_inlet_air(sunny):
    p = sunny.model_params()
    # inlet = 0.35 * 18 + 0.65 * (-10) = -0.2 degC; eps W c_p (T_cl - T_in)
    q = M.heater_limit(p, 60.0, 18.0, -10.0, 0.05)
    assert q == pytest.approx(p.eps_hc * 0.05 * p.cp_air * (60.0 + 0.2))


def test_coolant_flows_by_hand(sunny):
    p = sunny.model_params()
    Q_fuel, P_e, Q_heat, T_cl, T_amb = 40e3, 12e3, 2e3, 50.0, -10.0
    d, Q_exh, Q_air, Q_rad, T_com = M.coolant_flows(p, T_cl, T_amb, Q_fuel, P_e, Q_heat)
    assert Q_exh == pytest.approx(0.42 * 28e3)  # exhaust takes gamma of the heat not turned into work
    assert T_com == pytest.approx(-10.0 + 0.25 * 60.0)
    assert Q_air == pytest.approx(30.0 * (50.0 - 5.0))
    assert Q_rad == 0.0  # below the thermostat
    assert d == pytest.approx((28e3 * 0.58 - 30.0 * 45.0 - 2e3) / 70e3)


def _reintegrate(res, p):
    """Coolant and cabin temperatures re-integrated from the drive's logged inputs (fuel, engine work,
    heater heat: piecewise constant over each step), with scipy's RK45 at a fine step; also the heat
    flows integrated along the way (J)."""
    Ts = res.Ts
    N = len(res.e_mode)
    f = res.flows
    T_amb = res.info["T_amb_degC"]
    Q_fuel = p.LHV * f["W_f"]

    def flows(t, y):
        k = min(int(t / Ts), N - 1)
        T_cl, T_cab = y[0], y[1]
        q_exh = p.gamma_exh * (Q_fuel[k] - f["P_e"][k])
        T_com = T_amb + p.kappa * (T_cl - T_amb)
        q_air = p.hA_eng * (T_cl - T_com)
        q_rad = min(max(p.k_rad * (T_cl - p.T_open), 0.0), p.Q_rad_max)
        q_load = p.UA_cab * (T_amb - T_cab)
        d_cl = (Q_fuel[k] - f["P_e"][k] - q_exh - q_air - q_rad - f["Q_heat"][k]) / p.C_eng
        d_cab = (f["Q_heat"][k] + q_load + p.Q_sun) / p.C_cab
        return d_cl, d_cab, q_exh, q_air, q_rad

    def rhs(t, y):
        return list(flows(t, y))

    y0 = [res.T_cl[0], res.T_cab[0], 0.0, 0.0, 0.0]
    sol = solve_ivp(rhs, (0.0, N * Ts), y0, method="RK45", max_step=0.25, rtol=1e-8, atol=1e-6,
                    t_eval=res.t)
    assert sol.success
    return sol.y


@pytest.mark.parametrize("case", [
    dict(cycle="nycc", T_amb=-10.0, T_cl0=5.0, T_cab0=0.0),  # cold: heater limited by the core
    dict(cycle="hwfet", T_amb=-5.0, T_cl0=88.0, T_cab0=15.0),  # hot: the radiator works
])
def test_drive_matches_an_independent_ode_solution(sunny, case):
    p = sunny.model_params()
    res = simulate(sunny, case["cycle"], T_amb=case["T_amb"], soc0=0.6, T_cl0=case["T_cl0"],
                   T_cab0=case["T_cab0"], Q_heat=1500.0)
    T_cl, T_cab, E_exh, E_air, E_rad = _reintegrate(res, p)
    # the model is explicit Euler at 1 s; with time constants of minutes to hours the two solutions differ
    # by a few hundredths of a kelvin
    assert np.max(np.abs(res.T_cl - T_cl)) < 0.1
    assert np.max(np.abs(res.T_cab - T_cab)) < 0.1
    bal = res.energy_balance()
    assert bal["exhaust_J"] == pytest.approx(E_exh[-1], rel=1e-3)  # inputs piecewise constant in both
    assert bal["engine_bay_loss_J"] == pytest.approx(E_air[-1], rel=0.01, abs=2e3)
    assert bal["radiator_J"] == pytest.approx(E_rad[-1], rel=0.02, abs=2e3)
    assert bal["coolant_stored_J"] == pytest.approx(p.C_eng * (T_cl[-1] - T_cl[0]), rel=0.01, abs=1e4)
    assert bal["cabin_stored_J"] == pytest.approx(p.C_cab * (T_cab[-1] - T_cab[0]), rel=0.01, abs=1e4)
    if case["cycle"] == "hwfet":
        assert E_rad[-1] > 1e5  # the radiator case really exercises the radiator


def test_power_split_small_discharge_uses_the_discharge_efficiency(sunny):
    p = sunny.model_params()
    # 0.5 W of battery discharge reaches the motor as eta_em * 0.5 W (charging would divide by eta_em)
    P_e, Pbm, P_em, brake, ok = M.power_split(p, M.ON, 0.5, 10e3)
    assert P_em == pytest.approx(p.eta_em * 0.5, rel=1e-12)
    assert P_e == pytest.approx((10e3 - p.eta_em * 0.5) / p.eta_mech, rel=1e-12)


def test_engine_mode_coding_is_the_documented_one(sunny):
    """docs/model.md: e_mode 1 off, 2 idle, 3 on (the numbers stored in results and logs)."""
    p = sunny.model_params()
    v = 50 / 3.6  # cruising: traction power from the road load only
    r = M.evaluate(p, 0.6, 85.0, 20.0, np.array([1, 2, 3]), 0.0, 0.0, v, v, T_amb=0.0)
    assert (M.OFF, M.IDLE, M.ON) == (1, 2, 3)
    W_f, P_e = r["W_f"], r["P_e"]
    assert W_f[0] == 0.0 and P_e[0] == 0.0  # off
    assert W_f[1] == pytest.approx(p.W_idle * M.f_cold(p, 85.0)) and P_e[1] == 0.0  # idle
    # off and idle: the motor supplies the traction power from the battery (s.2)
    assert r["P_bat_mg"][:2] == pytest.approx(r["P_trac"][:2] / p.eta_em, rel=1e-12)
    # on with P_bat_mg = 0: the engine supplies it through the mechanical efficiency
    assert P_e[2] == pytest.approx(r["P_trac"][2] / p.eta_mech, rel=1e-12) and P_e[2] > 1e3 and W_f[2] > p.W_idle
    # torque times speed is the engine power; no torque off or idle (no power)
    assert r["tau_e"][2] * r["omega_e"][2] == pytest.approx(P_e[2], rel=1e-12) and r["omega_e"][2] > 0
    assert r["tau_e"][0] == 0.0 and r["tau_e"][1] == 0.0


def test_battery_current_solves_the_terminal_power_equation():
    """Eq. 1: P = U I - R I^2; the root of smaller magnitude; no real current where U^2 < 4 R P."""
    U, R = 200.0, 0.5
    for P in (10e3, 1.0, -15e3):
        I = M.battery_current(U, R, P, 0.0)
        assert U * I - R * I * I == pytest.approx(P, rel=1e-12, abs=1e-9)
        assert I == pytest.approx((U - np.sqrt(U * U - 4 * R * P)) / (2 * R), rel=1e-9)
    assert np.isnan(M.battery_current(U, R, U * U / (4 * R) * 1.001, 0.0))


def test_battery_hysteresis_is_a_loss_linear_in_the_current():
    """V = U - U_h sgn(I) - R I: the chemical power U I exceeds the terminal power by U_h |I| + R I^2 both ways;
    the current is continuous through zero power; the terminal voltage has the step."""
    U, R, Uh = 200.0, 0.5, 6.0
    for P in (10e3, 300.0, -300.0, -15e3):
        I = M.battery_current(U, R, P, Uh)
        assert np.sign(I) == np.sign(P)
        assert U * I - P == pytest.approx(Uh * abs(I) + R * I * I, rel=1e-10)
    assert M.battery_current(U, R, 0.0, Uh) == 0.0
    assert M.battery_current(U, R, 1e-6, Uh) == pytest.approx(0.0, abs=1e-8)
    assert M.battery_current(U, R, -1e-6, Uh) == pytest.approx(0.0, abs=1e-8)
    p = default_parameters().with_values(U_hyst_V=Uh).model_params()
    I, V, U0, R0, code = M.battery(p, 0.6, 5e3, 20.0)
    assert V == pytest.approx(U0 - Uh - R0 * I, rel=1e-12) and V * I == pytest.approx(5e3, rel=1e-10)
    I, V, U0, R0, code = M.battery(p, 0.6, -5e3, 20.0)
    assert V == pytest.approx(U0 + Uh - R0 * I, rel=1e-12) and V * I == pytest.approx(-5e3, rel=1e-10)


def test_battery_power_limits_are_inclusive():
    """docs/model.md: P_bat is limited to [P_bat_min, P_bat_max] (-25 ... +25 kW): both ends feasible,
    one watt beyond either infeasible."""
    p = default_parameters().model_params()
    assert (p.P_bat_min, p.P_bat_max) == (-25e3, 25e3)
    codes = [M.battery(p, 0.6, P, p.T_bat_ref)[4] for P in (-25e3, 25e3, -25001.0, 25001.0)]
    assert codes == [M.FEASIBLE, M.FEASIBLE, M.BATTERY_LIMIT, M.BATTERY_LIMIT]


def test_cabin_heat_to_reach_lands_on_the_target_in_one_euler_step():
    """The heat that takes the cabin to a target in one step, checked by stepping eq. 10 written out here
    (C_cab dT/dt = Q_heat + UA_cab (T_amb - T_cab) + Q_sun) with sun and a cabin colder and warmer than the
    target."""
    UA, Q_sun, C, T_amb, Ts = 95.0, 240.0, 180e3, -10.0, 1.0
    for dt in (1.0, 2.0, 0.5):  # steps other than 1 s: the heat scales with 1 / Ts
        for T_cab, T_target in ((18.0, 19.5), (21.0, 20.0), (5.0, 5.0)):
            q = M.cabin_heat_to_reach(UA, Q_sun, C, T_cab, T_amb, T_target, dt)
            T_next = T_cab + dt * (q + UA * (T_amb - T_cab) + Q_sun) / C
            assert T_next == pytest.approx(T_target, abs=1e-9)
    # holding 19 degC against -10 degC with 240 W of sun: the load minus the sun
    assert M.cabin_heat_to_reach(UA, Q_sun, C, 19.0, T_amb, 19.0, Ts) == pytest.approx(UA * 29.0 - Q_sun, rel=1e-12)
