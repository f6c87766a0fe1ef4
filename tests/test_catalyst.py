"""Catalyst heating after a cold start as a prelude of the plant: the same for every strategy, in the DP's
accounts, and replayed from logs."""
import numpy as np
import pytest

from calib.model.catalyst import prelude_steps, run_prelude
from calib.model.cycles import Cycle, load_cycle
from calib.model.equations import CAT, IDLE, ON
from calib.model.params import default_parameters
from calib.model.rulebased import RuleBasedController, RuleParams
from calib.model.simulate import simulate

_A = load_cycle("artemis_urban")
#: the first 200 s of ARTEMIS Urban
SHORT = Cycle("artemis_urban_200", _A.t[:201], _A.v[:201])
COLD = {"T_amb": -10.0, "soc0": 0.6, "T_cl0": -10.0, "T_cab0": -10.0, "Q_heat": 1500.0}


@pytest.fixture(scope="module")
def ps():
    return default_parameters()


class _EngineAlwaysOn:
    """A strategy that asks for the engine from the first second (charging): the plant must refuse it."""

    def __init__(self, mp):
        self.mp = mp

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        return (ON, -5000.0, 1500.0) if P_trac > 0.0 else (IDLE, 0.0, 1500.0)


def _head(sim, n):
    return (sim.e_mode[:n], sim.soc[:n + 1], sim.T_cl[:n + 1], sim.T_cab[:n + 1], sim.flows["W_f"][:n],
            sim.flows["Q_heat"][:n])


def test_prelude_identical_across_strategies(ps):
    from optimize.causal.controllers import ECMSController
    from optimize.causal.ecms import ECMSParams

    mp = ps.model_params()
    n = prelude_steps(mp, COLD["T_cl0"], 10_000, 1.0)
    assert n == round(ps["t_cat_s"]) > 0
    runs = [simulate(ps, SHORT, **COLD),
            simulate(ps, SHORT, RuleBasedController(mp, RuleParams(Q_heat_W=1500.0, P_on_W=1.0)), **COLD),
            simulate(ps, SHORT, ECMSController(mp, ECMSParams(), COLD["T_amb"]), **COLD),
            simulate(ps, SHORT, _EngineAlwaysOn(mp), **COLD)]
    ref = _head(runs[0], n)
    assert (ref[0] == CAT).all()
    assert np.allclose(ref[4], ps["W_cat_g_per_s"])
    for r in runs[1:]:
        for a, b in zip(ref, _head(r, n)):
            np.testing.assert_array_equal(a, b)
        assert (r.e_mode[n:] != CAT).all()  # the prelude ends on time
    # the prelude is what run_prelude computes from the same state
    cyc = runs[0]
    pre = run_prelude(mp, cyc.v, np.zeros(cyc.v.size), np.full(cyc.v.size, -10.0), np.full(cyc.v.size, mp.T_bat_ref),
                      mp.W_bl, (0.6, -10.0, -10.0), 1.0, n, 1500.0)
    assert pre.fuel_g == pytest.approx(float(np.sum(ref[4])), rel=1e-12)
    np.testing.assert_array_equal(pre.x[:, 1], ref[2])


def test_no_prelude_when_warm_or_continuing(ps):
    mp = ps.model_params()
    assert prelude_steps(mp, ps["T_cat_degC"] + 0.1, 1000, 1.0) == 0
    warm = simulate(ps, SHORT, **{**COLD, "T_cl0": ps["T_cat_degC"] + 0.1})
    cont = simulate(ps, SHORT, **COLD, engine_start=False)
    assert CAT not in warm.e_mode and CAT not in cont.e_mode
    off = simulate(ps.with_values(t_cat_s=0.0), SHORT, **COLD)
    assert CAT not in off.e_mode


def test_prelude_starts_the_engine_when_the_battery_cannot_drive_alone(ps):
    from calib.model.catalyst import prelude_control

    mp = ps.model_params()
    assert prelude_control(mp, 5e3)[0] == CAT
    e, pb = prelude_control(mp, 1.2 * mp.P_bat_max)
    assert e == ON and pb >= 0.0


def test_dp_with_prelude_and_rule_based_on_equal_terms(ps):
    from optimize.formulations import DPGrids, DPScenario
    from optimize.formulations.solve import dp_objective, scenario_prelude, solve_thermal

    scen = DPScenario(cycle="artemis_urban", duration_s=200.0, T_amb=-10.0, T_cl0=-10.0, T_cab0=-10.0,
                      T_cl_min=-12.0, T_cl_max=60.0, terminal="valued")
    grids = DPGrids(soc=0.01, tcl=4.0, pbat=4000.0)
    o = solve_thermal(ps, scen, grids, threads=1)
    rule = simulate(ps, scen.load_cycle(), **{k: getattr(scen, k) for k in ("T_amb", "soc0", "T_cl0", "T_cab0",
                                                                               "Q_heat")})
    pre = scenario_prelude(ps, scen.load_cycle(), scen)
    n = pre.n_steps
    assert n == round(ps["t_cat_s"]) and o.extra["prelude"]["steps"] == n
    # the DP's re-simulated run and the rule-based run share the prelude: same modes, fuel, states
    for a, b in zip(_head(o.sim, n), _head(rule, n)):
        np.testing.assert_array_equal(a, b)
    assert o.extra["prelude"]["fuel_g"] == pytest.approx(pre.fuel_g) and pre.fuel_g > 0.0
    # the DP's own cost counts the prelude's fuel: it matches its re-simulated objective over the whole drive
    assert o.dp_cost == pytest.approx(dp_objective(ps, o.sim, scen, 2), rel=1e-3)
    # on its own terms the DP does no worse than the rule-based run (which its feasible set contains,
    # up to grid error)
    assert dp_objective(ps, o.sim, scen, 2) <= dp_objective(ps, rule, scen, 2) * 1.01
    assert o.sim.soc[-1] >= scen.soc0 - scen.soc_tol


def test_dp_refuses_a_drive_shorter_than_the_prelude(ps):
    from calib.errors import ScenarioError
    from optimize.formulations import DPScenario
    from optimize.formulations.solve import solve_baseline

    scen = DPScenario(cycle="artemis_urban", duration_s=30.0, T_cl0=-10.0, T_cab0=-10.0, T_cl_min=-12.0)
    with pytest.raises(ScenarioError, match="catalyst heating"):
        solve_baseline(ps, scen)


def test_replay_of_a_log_with_catalyst_heating(ps):
    from calib.fit.replay import full_replay, log_arrays
    from calib.ingest.resample import to_drivelog
    from calib.synth import IDENTIFICATION_RULES, HvacController, Scenario, sensor_streams
    from calib.drivelog import LogMeta

    mp = ps.model_params()
    sc = Scenario("cat", "udds", -10.0, 0.6, -10.0, -10.0, T_bat=-5.0)
    sim = simulate(ps, "udds", HvacController(mp, IDENTIFICATION_RULES, T_set=sc.T_set), T_amb=sc.T_amb,
                   soc0=sc.soc0, T_cl0=sc.T_cl0, T_cab0=sc.T_cab0, T_bat=sc.T_bat)
    n = round(ps["t_cat_s"])
    assert (sim.e_mode[:n] == CAT).all()
    streams = sensor_streams(sim, sc, seed=3)
    log = to_drivelog(streams, LogMeta(source="cat.synthetic", format="synthetic", synthetic=True))
    la = log_arrays(log, mp)
    # every bin wholly inside the prelude is recognised (the first straddles the start), none after it
    assert (la.mode[2:n - 1] == CAT).all() and (la.f_cat[2:n - 1] == 1.0).all()
    assert not (la.mode[n + 2:] == CAT).any()
    # replayed with the mode, the fuel of the prelude is the catalyst's rate, and the coolant follows the truth
    args = (mp, la.dt, sim.soc[0], sim.T_cl[0], sim.T_cab[0], la.f_on, la.P_on, la.f_idle,
            np.nan_to_num(la.P_bat), np.full(la.t.size, sc.T_bat), np.full(la.t.size, sc.T_amb),
            np.nan_to_num(la.Q_heat))
    _, T_cl, _, W = full_replay(*args, la.f_cat)
    _, T_cl_idle, _, W_idle = full_replay(*args)
    np.testing.assert_allclose(W[2:n - 1], ps["W_cat_g_per_s"])
    m = min(T_cl.size, sim.T_cl.size, 300)
    err = np.abs(T_cl[:m] - sim.T_cl[:m]).max()
    err_idle = np.abs(T_cl_idle[:m] - sim.T_cl[:m]).max()
    assert err < 1.0 and err < 0.5 * err_idle, (err, err_idle)


def test_catalyst_heating_is_told_only_after_a_cold_start(ps):
    from calib.fit.replay import catalyst_heating

    mp = ps.model_params()
    n = np.r_[np.zeros(5), np.full(60, mp.w_cat / (2 * np.pi / 60)), np.full(100, 1000.0), np.full(20, 1350.0)]
    cat = catalyst_heating(n, np.ones(n.size, bool), mp)
    assert cat[5:65].all() and not cat[:5].any() and not cat[65:].any()  # not after the start's window
    assert not catalyst_heating(n, np.ones(n.size, bool), mp._replace(t_cat=0.0)).any()
    assert not catalyst_heating(n, np.ones(n.size, bool), mp, T_cl0=mp.T_cat + 1.0).any()  # a warm start
    assert catalyst_heating(n, np.ones(n.size, bool), mp, T_cl0=mp.T_cat - 1.0)[5:65].all()


@pytest.mark.parametrize("name,nx", [("baseline", 1), ("thermal", 2), ("thermal_cabin", 3)])
def test_every_formulation_counts_the_prelude(ps, name, nx):
    from optimize.formulations import DPGrids, DPScenario
    from optimize.formulations.solve import dp_objective, solve_formulation

    scen = DPScenario(duration_s=150.0, T_cl0=20.0)
    o = solve_formulation(name, ps, scen, DPGrids(soc=0.01, tcl=4.0, tcab=1.0, pbat=2000.0, qheat=150.0))
    n = o.extra["prelude"]["steps"]
    assert n == round(ps["t_cat_s"]) and (o.sim.e_mode[:n] == CAT).all() and CAT not in o.sim.e_mode[n:]
    assert o.dp.feasible and o.charge_sustaining()
    assert o.sim.summary()["energy_balance_residual_rel"] < 1e-9
    # the forward pass after the prelude plus the prelude's fuel is the re-simulated drive's fuel
    assert np.sum(o.dp.stage_cost) + o.extra["prelude"]["fuel_g"] == pytest.approx(o.sim.fuel_g, rel=1e-9)
    assert o.dp_cost == pytest.approx(dp_objective(ps, o.sim, scen, nx), rel=1e-9)


def test_warm_up_charge_only_in_the_warm_up_after_a_cold_start():
    """A warm engine cooled by the heater is not warming up: it runs for heat by the thermal rules, with the
    normal SOC target; the same coolant trace after a cold start charges towards the warm-up target."""
    from dataclasses import replace

    from calib.model.params import default_parameters
    from calib.model.rulebased import RuleBasedController, RuleParams

    mp = default_parameters().model_params()
    rp = RuleParams()
    no_warmup = replace(rp, soc_warmup=rp.soc_target)

    def run(rules, T_cl_trace):
        c = RuleBasedController(mp, rules)
        return [c(k, 0.6, T, 20.0, 2000.0) for k, T in enumerate(T_cl_trace)]

    warm_then_cooled = [75.0, 72.0, 68.0, 60.0, 50.0, 45.0]
    assert run(rp, warm_then_cooled) == run(no_warmup, warm_then_cooled)
    cold_start = [30.0, 35.0, 40.0, 45.0, 50.0, 55.0]
    assert run(rp, cold_start) != run(no_warmup, cold_start)
    # once warmed up, a later dip below T_warm_degC does not start a second warm-up
    # (after the engine's minimum on-time has run out)
    warmed = [30.0, 45.0, 71.0] + [60.0] * 10 + [50.0, 45.0, 42.0]
    a, b = run(rp, warmed), run(no_warmup, warmed)
    assert a[:2] != b[:2] and a[-3:] == b[-3:]


def test_rule_limits_a_cold_battery_to_what_it_can_deliver(ps):
    """A cold pack's resistance caps its power below P_bat_max: the rule starts the engine for a demand the
    warm pack would carry alone, never commands more than the cold pack gives, over a whole cold US06 too."""
    from calib.model.equations import OFF, battery

    mp = ps.model_params()
    c = RuleBasedController(mp, RuleParams(P_on_W=1e9, soc_warmup=0.0, T_idle_degC=-50.0, T_heat_on_degC=-50.0))
    c.T_bat = -20.0
    limit = c.discharge_limit_W(0.6)
    assert limit < 0.6 * mp.P_bat_max  # the cold pack is the binding limit here
    P_trac = 0.97 * mp.eta_em * (limit - mp.P_aux)  # within the warm pack's reach, beyond 95 % of the cold one's
    c.T_bat = mp.T_bat_ref
    assert c(0, 0.6, 80.0, 20.0, P_trac)[0] == OFF
    c.reset()
    c.T_bat = -20.0
    e, P_bat_mg, _ = c(0, 0.6, 80.0, 20.0, 1.5 * P_trac)
    assert e == ON and P_bat_mg + mp.P_aux <= limit + 1e-6
    assert battery(mp, 0.6, P_bat_mg + mp.P_aux, -20.0)[4] == 0
    sim = simulate(ps, "us06", T_amb=-15.0, soc0=0.6, T_cl0=80.0, T_cab0=20.0, T_bat=-15.0, Q_heat=0.0,
                   engine_start=False)
    c.T_bat = -15.0
    limits = np.array([c.discharge_limit_W(s) for s in sim.soc[:-1]])
    assert np.all(sim.flows["P_bat"] <= limits + 1e-6)
    assert np.max(sim.flows["P_bat"] / limits) > 0.99  # US06 reaches the cold limit: the test exercises it
