"""Valuation of final states by a common continuation (calib.model.continuation) and the DP's
``continued`` terminal condition."""
from dataclasses import replace

import numpy as np
import pytest

from calib.errors import IptmError, ScenarioError
from calib.model import (continuation_corrected, continuation_credit_per_gram, continuation_run, continuation_value,
                         credit_per_gram, default_parameters, simulate)
from optimize.formulations.scenario import DPGrids, DPScenario
from optimize.formulations.solve import dp_objective, reference_run, solve_thermal

X0 = (0.6, 70.0, 20.0)
KW = dict(T_amb=-10.0, Q_heat=1500.0)


@pytest.fixture(scope="module")
def ps():
    return default_parameters()


def test_initial_state_gives_zero_correction(ps):
    # a drive that ends where it started has no continuation correction, and C(x0) is ref's own fuel
    C, run, ref = continuation_value(ps, *X0, ref=X0, cycle="udds", details=True, **KW)
    assert C == pytest.approx(float(ref["fuel_g"]), abs=1e-9)
    res = simulate(ps, "nycc", T_amb=-10.0, soc0=X0[0], T_cl0=X0[1], T_cab0=X0[2], Q_heat=1500.0)
    c = continuation_corrected(res, Q_heat=1500.0, cycle="udds")
    # the corrected figure is fuel + C(x_N) - C(x_0), computed independently here
    CN = continuation_value(ps, res.soc[-1], res.T_cl[-1], res.T_cab[-1], ref=X0, cycle="udds", **KW)
    assert c["fuel_continuation_g"] == pytest.approx(res.fuel_g + CN - C, abs=1e-9)
    assert c["continuation_credit_g"] == pytest.approx(C - CN, abs=1e-9)
    # the final state differs from the initial one, so the correction is not zero here
    assert abs(c["continuation_credit_g"]) > 0.1


def test_value_decreases_with_charge_and_coolant_heat(ps):
    soc = np.array([0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75])
    C_soc = continuation_value(ps, soc, 70.0, 20.0, ref=X0, **KW)
    assert np.all(np.diff(C_soc) < 0), C_soc
    tcl = np.array([30.0, 40.0, 50.0, 60.0, 70.0, 80.0])
    C_tcl = continuation_value(ps, 0.6, tcl, 20.0, ref=X0, **KW)
    assert np.all(np.diff(C_tcl) < 0), C_tcl
    # above the thermostat extra heat is dumped by the radiator: worth (almost) nothing, never a cost
    C_hot = continuation_value(ps, 0.6, np.array([85.0, 90.0, 95.0, 100.0]), 20.0, ref=X0, **KW)
    assert np.all(np.diff(C_hot) <= 1e-6), C_hot


def test_no_double_credit(ps):
    # a gram burnt to charge the battery, its heat to the coolant: the fuel equivalents credit it 1.53-1.58 g,
    # the continuation at most the gram itself
    for P_e in (5e3, 15e3, 30e3):
        assert credit_per_gram(ps.model_params(), P_e) > 1.5
        for T_cl in (60.0, 85.0):
            c = continuation_credit_per_gram(ps, P_e, T_cl=T_cl)
            assert 0.3 < c <= 1.0, (P_e, T_cl, c)


def test_bad_input(ps):
    with pytest.raises(ScenarioError, match="ref"):
        continuation_value(ps, 0.6, 70.0, 20.0, ref=(0.6, 70.0), **KW)
    with pytest.raises(ScenarioError, match="finite"):
        continuation_value(ps, np.nan, 70.0, 20.0, ref=X0, **KW)
    with pytest.raises(ScenarioError, match="cont_soc_every"):
        DPScenario(cont_soc_every=0)
    from optimize.causal.compare import compare_causal

    with pytest.raises(IptmError, match="valuation"):
        compare_causal(ps, valuation="prices")
    for g in (0.0, -1.0, float("nan")):
        with pytest.raises(ScenarioError, match="grams must be positive"):
            continuation_credit_per_gram(ps, 15e3, grams=g, cycle="udds")
    assert np.isfinite(continuation_credit_per_gram(ps, 15e3, grams=0.5, cycle="udds"))  # any positive amount
    # a result that records no ambient needs it given, and then uses the one given
    res = simulate(ps, "nycc", T_amb=-10.0, soc0=X0[0], T_cl0=X0[1], T_cab0=X0[2], Q_heat=1500.0)
    bare = replace(res, info={k: v for k, v in res.info.items() if k != "T_amb_degC"})
    with pytest.raises(ScenarioError, match="records no ambient; pass T_amb"):
        continuation_corrected(bare, Q_heat=1500.0, cycle="udds")
    given = continuation_corrected(bare, Q_heat=1500.0, T_amb=-10.0, cycle="udds")
    assert given == continuation_corrected(res, Q_heat=1500.0, cycle="udds")
    assert given != continuation_corrected(res, Q_heat=1500.0, T_amb=0.0, cycle="udds")


SHORT = DPScenario(duration_s=300.0, terminal="continued", cont_cycle="udds+udds")
GRIDS = DPGrids(pbat=1000.0)


@pytest.fixture(scope="module")
def dp_short(ps):
    return solve_thermal(ps, SHORT, GRIDS, threads=1)


def test_continued_objective_consistent(ps, dp_short):
    dp = dp_short
    # the DP's cost at its own re-simulated run is fuel + phi(x_N) (dp_objective on the same grids)
    assert dp_objective(ps, dp.sim, SHORT, 2, grids=GRIDS) == pytest.approx(dp.dp_cost, abs=1e-3)
    assert dp.extra["terminal"] == "continued"
    # phi is C(x_N) - C(x_0) up to interpolation: compare with the direct continuation of the final state
    direct = continuation_corrected(dp.sim, Q_heat=SHORT.Q_heat, cycle=SHORT.cont_cycle)
    assert dp.dp_cost == pytest.approx(direct["fuel_continuation_g"], abs=1.5)


def test_continued_dp_beats_rule_on_equal_terms(ps, dp_short):
    rule = reference_run(ps, SHORT.load_cycle(), SHORT)
    obj_rule = dp_objective(ps, rule, SHORT, 2, grids=GRIDS)
    assert dp_short.dp_cost <= obj_rule + 0.05, (dp_short.dp_cost, obj_rule)
    # and on the valued terminal's terms the DP is a different optimum (the two conditions differ)
    valued = solve_thermal(ps, replace(SHORT, terminal="valued"), GRIDS, threads=1)
    assert dp_objective(ps, valued.sim, SHORT, 2, grids=GRIDS) >= dp_short.dp_cost - 0.05


def test_continued_soc_band(ps):
    # with a band the DP ends charge sustaining as the causal controllers must; without, it may not
    scen = replace(SHORT, cont_soc_band=0.01)
    dp = solve_thermal(ps, scen, GRIDS, threads=1)
    assert abs(dp.sim.soc[-1] - scen.soc0) <= 0.011
    with pytest.raises(ScenarioError, match="cont_soc_band"):
        DPScenario(cont_soc_band=-0.01)


def test_continued_thermal_cabin(ps):
    # three states: C is tabulated along the cabin too, which the DP's cabin state is measured from its bound
    from optimize.formulations.solve import solve_thermal_cabin

    scen = DPScenario(duration_s=200.0, terminal="continued", cont_cycle="udds")
    grids = DPGrids(pbat=1000.0, qheat=100.0)
    dp = solve_thermal_cabin(ps, scen, grids)
    assert len(dp.extra["continuation_nodes"][2]) >= 2
    assert dp_objective(ps, dp.sim, scen, 3, grids=grids) == pytest.approx(dp.dp_cost, abs=1e-3)
    direct = continuation_corrected(dp.sim, Q_heat=scen.Q_heat, cycle=scen.cont_cycle)
    assert dp.dp_cost == pytest.approx(direct["fuel_continuation_g"], abs=1.5)


def test_every_terminal_soc_set_gets_the_reach_rule_by_default(ps):
    # one-sided SOC_N >= SOC_0, the continued terminal's two-sided band and SOC_N free: one interpolation
    from optimize.formulations.solve import build_problem

    one = build_problem(ps, DPScenario(duration_s=30.0), GRIDS, 2)
    band = build_problem(ps, replace(SHORT, duration_s=30.0, cont_soc_band=0.01), GRIDS, 2)
    free = build_problem(ps, replace(SHORT, duration_s=30.0), GRIDS, 2)
    assert (one.prob.interp, band.prob.interp, free.prob.interp) == ("reach_first",) * 3
    assert build_problem(ps, replace(SHORT, duration_s=30.0, cont_soc_band=0.01), GRIDS, 2,
                         interp="multilinear").prob.interp == "multilinear"  # an explicit choice is kept


@pytest.mark.slow  # two full-size Thermal-DP solves; `make test-slow`
def test_reach_rule_with_a_soc_band_is_not_worse_than_the_chord(ps):
    """With a two-sided terminal SOC band, phi outside the band is phi at its edge, so the reach-boundary
    interpolation's premise (an unreachable node's value is about the boundary's cost) holds at the upper
    edge too. On NYCC at 0 degC (where C extended beyond the band made the reach rule 0.9 g worse than
    the plain chord, continuation-corrected 55.33 g against 54.41 g) it is now at most the chord's,
    measured by the direct continuation of each run's final state, not by the DP's own terms."""
    from optimize.formulations import solve as S

    scen = DPScenario(cycle="nycc", T_amb=0.0, terminal="continued", cont_soc_band=0.01)
    out = {}
    for interp in ("reach_first", "multilinear"):
        b = S.build_problem(ps, scen, DPGrids(), 2, interp=interp)
        res = S._solve(b, "fused")
        sim = S.resimulate(ps, b.cyc, res.u[:, 0], res.u[:, 1], res.u[:, 2], scen, interp)
        assert abs(sim.soc[-1] - scen.soc0) <= 0.01 + 1e-3
        out[interp] = continuation_corrected(sim, Q_heat=scen.Q_heat, T_amb=scen.T_amb,
                                             cycle=scen.cont_cycle)["fuel_continuation_g"]
    assert out["reach_first"] <= out["multilinear"] + 0.05, out


def test_continued_terminal_cost_is_zero_at_the_initial_state_and_c_differences_at_its_nodes(ps):
    # phi(x) = C(x) - C(x_0) on the sub-grid: 0 at the initial state, and between two sub-grid nodes the
    # difference of the continuation values computed directly (Thermal-DP: at the reference run's final cabin)
    from optimize.formulations.solve import build_problem

    scen = replace(SHORT, duration_s=30.0, cont_soc_every=3)
    b = build_problem(ps, scen, GRIDS, 2)
    phi = b.prob.terminal_cost
    assert phi(np.array([[scen.soc0, scen.T_cl0]]))[0] == pytest.approx(0.0, abs=1e-12)
    soc_n, tcl_n, _ = (np.array(a) for a in b.extra["continuation_nodes"])
    # every 3rd node of the SOC range, and its top, which the stride misses here (a shorter last gap)
    gaps = np.diff(soc_n)
    assert soc_n[0] == scen.soc_min and soc_n[-1] == pytest.approx(scen.soc_max, abs=1e-12)
    np.testing.assert_allclose(gaps[:-1], gaps[0], rtol=1e-9)
    assert 0.0 < gaps[-1] < gaps[0] - 1e-9
    xa, xb = (soc_n[0], tcl_n[0]), (soc_n[-1], tcl_n[-1])
    C = continuation_value(ps, np.array([xa[0], xb[0]]), np.array([xa[1], xb[1]]), b.extra["T_cab_ref_final"],
                           ref=(scen.soc0, scen.T_cl0, scen.T_cab0), T_amb=scen.T_amb, Q_heat=scen.Q_heat,
                           cycle=scen.cont_cycle)
    d = phi(np.array([xb, xa]))
    assert d[0] - d[1] == pytest.approx(C[1] - C[0], abs=1e-9)
    assert abs(C[1] - C[0]) > 1.0  # the nodes are states of different value


def test_corrected_fuel_of_a_drive_ending_where_it_started_is_its_fuel_and_the_residual_the_end_state_gap(ps):
    # a drive that ends in its initial state: both continuations are the same run, nothing to correct
    from types import SimpleNamespace

    from calib.model.simulate import fuel_equivalents_g

    def drive(x_end):
        return SimpleNamespace(mp=ps.model_params(), info={"T_amb_degC": -10.0}, fuel_g=42.0,
                               soc=np.array([X0[0], x_end[0]]), T_cl=np.array([X0[1], x_end[1]]),
                               T_cab=np.array([X0[2], x_end[2]]))

    c = continuation_corrected(drive(X0), Q_heat=1500.0, cycle="udds")
    assert c["fuel_continuation_g"] == 42.0 and c["continuation_credit_g"] == 0.0
    assert (c["residual_g"], c["residual_dsoc"], c["residual_dT_cl"], c["residual_dT_cab"]) == (0.0, 0.0, 0.0, 0.0)
    # otherwise the residual is the fuel equivalent of the continuation end states' differences
    c = continuation_corrected(drive((0.65, 85.0, 22.0)), Q_heat=1500.0, cycle="udds")
    ref = simulate(ps, "udds", T_amb=-10.0, soc0=X0[0], T_cl0=X0[1], T_cab0=X0[2], Q_heat=1500.0)
    end = (ref.soc[-1], ref.T_cl[-1], ref.T_cab[-1])
    eq = fuel_equivalents_g(ps.model_params(), end[0], end[0] + c["residual_dsoc"], end[1],
                            end[1] + c["residual_dT_cl"], end[2], end[2] + c["residual_dT_cab"])
    assert c["residual_g"] == pytest.approx(eq["electric_g"] + eq["coolant_g"] + eq["cabin_g"], abs=1e-9)
    assert abs(c["residual_g"]) > 1e-3


def test_corrected_fuel_of_a_drive_ending_where_its_last_sample_lies_values_that_state(ps):
    # three samples, the middle one far from both ends: the correction is C(x_0) - C(x_last), each value
    # computed here by continuation_value (a middle sample in place of the last changes every state)
    from types import SimpleNamespace

    res = SimpleNamespace(mp=ps.model_params(), info={"T_amb_degC": -10.0}, fuel_g=42.0,
                          soc=np.array([X0[0], 0.5, 0.65]), T_cl=np.array([X0[1], 40.0, 85.0]),
                          T_cab=np.array([X0[2], 15.0, 22.0]))
    c = continuation_corrected(res, Q_heat=1500.0, cycle="udds")
    C0 = continuation_value(ps, *X0, ref=X0, cycle="udds", **KW)
    CN = continuation_value(ps, 0.65, 85.0, 22.0, ref=X0, cycle="udds", **KW)
    assert c["continuation_credit_g"] == pytest.approx(C0 - CN, abs=1e-9)
    assert c["fuel_continuation_g"] == pytest.approx(42.0 + CN - C0, abs=1e-9)
    for i in range(3):  # each state of the last sample matters: moving it alone changes the value
        x = [0.65, 85.0, 22.0]
        x[i] = (0.5, 40.0, 15.0)[i]
        assert abs(continuation_value(ps, *x, ref=X0, cycle="udds", **KW) - CN) > 1e-3


def test_continuation_run_reports_each_runs_fuel_and_last_sample(ps):
    """The end states are the last samples of the rule-based run from each state, computed here by
    calling the simulator directly (the trip goes on: no catalyst heating from the 40-degC state)."""
    soc, tcl, tcab = np.array([0.55, 0.65]), np.array([40.0, 80.0]), np.array([12.0, 21.0])
    out = continuation_run(ps, soc, tcl, tcab, cycle="nycc", **KW)
    for i in range(2):
        r = simulate(ps, "nycc", T_amb=-10.0, soc0=soc[i], T_cl0=tcl[i], T_cab0=tcab[i], Q_heat=1500.0,
                     engine_start=False)
        assert out["fuel_g"][i] == r.fuel_g
        assert (out["soc_end"][i], out["T_cl_end"][i], out["T_cab_end"][i]) == (r.soc[-1], r.T_cl[-1], r.T_cab[-1])
        # the last sample, not the one before it: the states still move over the last step
        assert r.T_cab[-1] != r.T_cab[-2] and r.T_cl[-1] != r.T_cl[-2]


def test_credit_per_gram_defaults_to_a_warm_car_and_ignores_the_cabin_when_warm(ps):
    """Without a state, the credit is that of the documented defaults (SOC 0.6, coolant 85 degC, ambient
    -10 degC, 1500 W of heater, 20 g); with the coolant warm the heater core delivers the full heater power
    whatever the cabin temperature, so the cabin does not enter either continuation and the credit is the
    same for any cabin temperature."""
    d = continuation_credit_per_gram(ps, 15e3, cycle="udds")
    assert d == continuation_credit_per_gram(ps, 15e3, soc=0.6, T_cl=85.0, T_amb=-10.0, Q_heat=1500.0, grams=20.0,
                                             cycle="udds")
    # each of those defaults matters: another ambient or another finite amount gives another credit
    assert d != continuation_credit_per_gram(ps, 15e3, T_amb=10.0, cycle="udds")
    assert d != continuation_credit_per_gram(ps, 15e3, grams=21.0, cycle="udds")
    for T_cab in (0.0, 21.0):
        assert d == continuation_credit_per_gram(ps, 15e3, T_cab=T_cab, cycle="udds")


def test_continued_terminal_cost_sub_grid_of_a_degenerate_range_is_one_node():
    """The continuation's sub-grid along an axis: equal spacing at most ``step`` between the ends, and one
    node (not two equal ones, a cell of zero width) when the range is a single value."""
    from optimize.formulations.solve import _sub_nodes

    assert np.array_equal(_sub_nodes(0.6, 0.6, 0.01), [0.6])
    assert np.allclose(_sub_nodes(0.5, 0.6, 0.03), [0.5, 0.525, 0.55, 0.575, 0.6])


def test_credit_per_gram_is_the_continuation_value_of_the_grams_charge_and_heat(ps):
    """The credit worked from its definition: 20 g burnt at P_e charge the battery by
    P_e eta_mech eta_em / (C_bat U) per gram of fuel and heat the coolant by (1 - gamma) (LHV W_f - P_e) /
    (C_eng W_f) per gram (no heater, no losses in the gram's own balance); the credit is the drop of the
    continuation value from x to x + made, per gram."""
    from calib.model.equations import ON, battery_ocv_r, fuel_rate

    mp, P_e, x = ps.model_params(), 15e3, (0.6, 60.0, 20.0)
    W_f = fuel_rate(mp, ON, P_e, x[1])
    U, _ = battery_ocv_r(mp, x[0], mp.T_bat_ref)
    dsoc = 20.0 * P_e * mp.eta_mech * mp.eta_em / (mp.C_bat_As * U) / W_f
    dT = 20.0 * (1.0 - mp.gamma_exh) * (mp.LHV * W_f - P_e) / mp.C_eng / W_f
    C0, C1 = continuation_value(ps, np.array([x[0], x[0] + dsoc]), np.array([x[1], x[1] + dT]), x[2], ref=x,
                                cycle="udds", **KW)
    assert continuation_credit_per_gram(ps, P_e, soc=x[0], T_cl=x[1], T_cab=x[2], cycle="udds", **KW) == \
        pytest.approx((C0 - C1) / 20.0, rel=1e-9)
