"""Full-size checks (paper grids, 993-s ARTEMIS Urban): `pytest -m slow`."""
import pytest

from optimize.formulations.scenario import DPGrids, DPScenario

pytestmark = pytest.mark.slow


def test_full_case_study_ordering(params):
    """Valued terminal condition: corrected fuel ordered rule >= Baseline on thermal >= Thermal >=
    Thermal-Cabin, each DP's V_0(x0) within 1 % of its forward-simulated cost."""
    from optimize.casestudy import run_case_study

    cs = run_case_study(params, DPScenario(), progress=False)
    assert cs.ordering_ok(), cs.ordering_statement()
    assert cs.table()["charge_sustaining"].all()
    for k, (v0, fwd, gap) in cs.value_check().items():
        assert abs(gap) <= 1.0, (k, v0, fwd)


@pytest.mark.xfail(reason="every step halved: Thermal-DP's corrected fuel changes by +0.04 % (converged), "
                          "Baseline-DP's fuel by +0.03 % but its corrected fuel, which values the coolant heat "
                          "of a run that does not optimise it, by -0.11 %", strict=False)
def test_convergence_baseline_thermal(params):
    from optimize.convergence import convergence_study

    rows = convergence_study(params, DPScenario(), ("baseline", "thermal"), DPGrids())
    for r in rows:
        assert r["converged"], r
