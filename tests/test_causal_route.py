"""The route-aware ECMS: the route file is validated, the co-states follow the distance to go, with constant
co-states it is the hindsight constant-co-state ECMS, and a trip that ends early still sustains the charge."""
from dataclasses import replace

import numpy as np
import pytest

from calib.errors import IptmError
from calib.model.cycles import load_cycle
from calib.model.params import default_parameters
from calib.model.simulate import simulate
from optimize.causal.compare import valued_fuel
from optimize.causal.ecms import ECMSParams
from optimize.causal.hindsight import drive_ecms, tune_ecms_on_drive
from optimize.causal.route import (Route, RouteECMSController, RouteECMSParams, drive_route, ended_early,
                                   load_route, route_from_args, route_of_cycle)
from optimize.formulations.scenario import DPScenario

SCEN = replace(DPScenario(), cycle="nycc", T_amb=-10.0, duration_s=240.0)
GOOD = """length_km = 10.0
ambient_degC = -5
[[segment]]
from_km = 0
to_km = 4
class = "urban"
[[segment]]
from_km = 4
to_km = 10
speed_limit_kph = 100
"""


@pytest.fixture(scope="module")
def ps():
    return default_parameters()


def test_route_file_reads_classes_and_speed_limits(tmp_path):
    p = tmp_path / "trip.toml"
    p.write_text(GOOD)
    r = load_route(p)
    assert r.length_km == 10.0 and r.ambient_degC == -5.0
    assert [s.road_class for s in r.segments] == ["urban", "highway"]
    assert r.class_shares() == pytest.approx({"urban": 0.4, "highway": 0.6})
    assert r.class_shares(7.0) == {"highway": 1.0}
    assert route_from_args(None, 12.5).length_km == 12.5 and route_from_args(None, None) is None


@pytest.mark.parametrize("text, message", [
    ("ambient_degC = 0\n", "length_km missing"),
    ("length_km = -3\n", "length_km: -3 km"),
    ("length_km = 'ten'\n", "length_km: 'ten' is not a finite number"),
    ("length_km = 5\nlenght = 2\n", "unknown field.*lenght"),
    ("length_km = 5\nambient_degC = 80\n", "ambient_degC 80 outside"),
    ("length_km = 5\n[[segment]]\nfrom_km = 0\nto_km = 5\nclass = 'motorway'\n", "segment 1: class 'motorway'"),
    ("length_km = 5\n[[segment]]\nfrom_km = 0\nto_km = 2\nclass = 'urban'\n[[segment]]\nfrom_km = 3\nto_km = 5\n"
     "class = 'urban'\n", "segment 2: from_km 3 but the route so far ends at 2 km"),
    ("length_km = 5\n[[segment]]\nfrom_km = 0\nto_km = 4\nclass = 'urban'\n", "segments end at 4 km"),
    ("length_km = 5\n[[segment]]\nfrom_km = 0\nto_km = 5\nclass = 'urban'\nspeed_limit_kph = 50\n",
     "exactly one of class"),
    ("length_km = 5\n[[segment]\n", "not a valid TOML route file"),
])
def test_bad_route_file_is_one_clear_error(tmp_path, text, message):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(IptmError, match=message) as e:
        load_route(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_route_and_length_together_are_refused(tmp_path):
    with pytest.raises(IptmError, match="not both"):
        route_from_args(tmp_path / "trip.toml", 5.0)
    with pytest.raises(IptmError, match="trip length must be above 0"):
        route_from_args(None, 0.0)


def test_co_states_follow_distance_to_go_and_classes(ps):
    mp = ps.model_params()
    route = Route.from_dict({"length_km": 10.0, "segment": [{"from_km": 0, "to_km": 4, "class": "urban"},
                                                           {"from_km": 4, "to_km": 10, "class": "highway"}]})
    rp = RouteECMSParams(k_end=40.0, d_near_km=1.0, k_min=5.0, k_i=0.0, k_mu=0.03, d_heat_km=2.0)
    c = RouteECMSController(mp, route, rp, class_s={"urban": 0.5, "highway": 1.0, "suburban": 0.75})
    assert c.s_base(0.0) == pytest.approx(0.4 * 0.5 + 0.6 * 1.0)
    assert c.s_base(2.0) == pytest.approx((2 * 0.5 + 6 * 1.0) / 8)
    assert c.s_base(12.0) == 1.0  # past the announced end: the last class
    err = 0.01  # SOC below the target, at standstill
    c.d_km = 0.0
    s_far, mu_far, _ = c.co_states(0.6 - err, 60.0)
    c.d_km = 9.5
    s_near, mu_near, _ = c.co_states(0.6 - err, 60.0)
    assert s_far == pytest.approx(c.s_base(0.0) + max(40.0 / 10.0, 5.0) * err)
    assert s_near == pytest.approx(1.0 + 40.0 * err)
    assert mu_far == pytest.approx(0.03 * 20.0) and mu_near == pytest.approx(0.03 * 20.0 * 0.25)


def test_distance_to_go_is_tracked_from_the_wheel_power(ps):
    cyc = load_cycle("nycc")
    route = route_of_cycle(cyc)
    ctrl = RouteECMSController(ps.model_params(), Route.from_length(route.length_km), RouteECMSParams())
    simulate(ps, cyc, ctrl, T_amb=-10.0)
    assert ctrl.d_km == pytest.approx(cyc.distance_m / 1e3, rel=1e-3)


def test_exact_length_and_constant_co_states_is_the_hindsight_constant_ecms(ps):
    """The constant-co-state ECMS tuned on the drive (Pontryagin with fixed co-states, the hindsight study's
    best in the band) and the route-aware ECMS told the exact length with its schedule switched off drive
    the same run."""
    h = tune_ecms_on_drive(ps, SCEN, search="constant", s_grid=(0.3, 0.7, 1.1, 1.5), mu_grid=(0.0, 0.5))
    assert h.best is not None
    cyc = SCEN.load_cycle()
    rp = RouteECMSParams(s0=h.best["s"], mu0=h.best["mu"], k_end=0.0, k_min=0.0, k_i=0.0, k_mu=0.0,
                         Q_heat_W=SCEN.Q_heat, soc_target=SCEN.soc0)
    route = Route.from_length(cyc.distance_m / 1e3)
    mine = drive_route(ps, SCEN, cyc, route, "length", rp)
    theirs = drive_ecms(ps, ps.model_params(), cyc, SCEN, replace(ECMSParams(), s0=h.best["s"], mu0=h.best["mu"],
                                                                   k_s=0.0, k_mu=0.0, Q_heat_W=SCEN.Q_heat,
                                                                   soc_target=SCEN.soc0))
    assert valued_fuel(mine, SCEN, "corrected")[0] == h.best["fuel_valued_g"]
    np.testing.assert_array_equal(mine.soc, theirs.soc)
    np.testing.assert_array_equal(mine.T_cl, theirs.T_cl)
    np.testing.assert_array_equal(mine.P_bat_mg_cmd, theirs.P_bat_mg_cmd)


@pytest.mark.parametrize("knowledge", ["length", "route"])
def test_trip_that_ends_early_sustains_the_charge(ps, knowledge):
    base = replace(DPScenario(), cycle="udds", T_amb=-10.0)
    cyc = base.load_cycle()
    route = route_of_cycle(cyc)
    short = ended_early(cyc, 0.5)
    assert short.distance_m < 0.55 * cyc.distance_m and short.v[-1] == 0.0
    class_s = {"urban": 0.84, "suburban": 0.87, "highway": 0.90}  # those class_costates gives at -10 degC
    sim = drive_route(ps, base, short, route, knowledge, RouteECMSParams(), class_s)
    assert abs(sim.soc[-1] - base.soc0) <= 0.02


def test_ended_early_refuses_a_fraction_outside_the_trip():
    with pytest.raises(IptmError, match="fraction 1.5"):
        ended_early("nycc", 1.5)
