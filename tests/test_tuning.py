"""The rule-based controller's tuning: on one drive, and one set of thresholds for several drives."""
import itertools
from dataclasses import replace

import pytest

from calib.errors import IptmError
from calib.model.params import default_parameters
from calib.model.rulebased import RuleParams
from calib.model.simulate import simulate
from optimize.formulations.scenario import DPScenario
from optimize.tuning import tune_rule_based, tune_rule_on_drives

#: A small grid (16 settings) keeps the search to a second or two.
GRID = {"P_on_W": [5e3, 12e3], "P_off_ratio": [0.4], "P_e_min_W": [6e3, 14e3], "k_soc_W": [50e3, 400e3],
        "soc_target_offset": [0.0, 0.03]}
KW = dict(T_amb=-10.0, soc0=0.6, T_cl0=70.0, T_cab0=20.0, Q_heat=1500.0)


@pytest.fixture(scope="module")
def setup():
    ps = default_parameters()
    cycles = [replace(DPScenario(), cycle=c, duration_s=300.0).load_cycle() for c in ("nycc", "hwfet")]
    return ps, cycles


def test_one_drive_is_the_per_drive_tuning(setup):
    ps, cycles = setup
    a = tune_rule_based(ps, cycles[0], grid=GRID, **KW)
    b = tune_rule_on_drives(ps, cycles[:1], grid=GRID, **KW)
    assert a.rule == b.rule and a.result.fuel_g == b.result.fuel_g and (a.n_tried, a.n_feasible) == (16, b.n_feasible)


def test_several_drives_take_the_least_total_fuel_among_settings_sustaining_charge_on_all(setup):
    ps, cycles = setup
    t = tune_rule_on_drives(ps, cycles, grid=GRID, **KW)
    assert len(t.results) == 2 and t.result is t.results[0]
    # exhaustive check, written independently of the search
    base = RuleParams(Q_heat_W=KW["Q_heat"], soc_low=0.5)
    totals = []
    for P_on, ratio, P_min, k, off in itertools.product(*GRID.values()):
        rp = replace(base, P_on_W=P_on, P_off_W=ratio * P_on, P_e_min_W=P_min, k_soc_W=k, soc_target=0.6 + off)
        res = [simulate(ps, c, rule_params=rp, **KW) for c in cycles]
        if all(r.soc[-1] >= 0.6 for r in res):
            totals.append(sum(r.fuel_g for r in res))
    assert t.n_feasible == len(totals) > 0
    assert sum(r.fuel_g for r in t.results) == min(totals)
    assert all(r.soc[-1] >= 0.6 for r in t.results)
    # each drive's own tuning can only do better on that drive
    for c, r in zip(cycles, t.results):
        assert tune_rule_based(ps, c, grid=GRID, **KW).result.fuel_g <= r.fuel_g


def test_no_drives_is_refused(setup):
    with pytest.raises(IptmError, match="no drives"):
        tune_rule_on_drives(setup[0], [], **KW)
