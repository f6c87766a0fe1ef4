"""Full-size checks (paper grids, 993-s ARTEMIS Urban): `pytest -m slow`."""
import pytest

from optimize.formulations.scenario import DPGrids, DPScenario

pytestmark = pytest.mark.slow


def test_full_case_study_ordering(params):
    from optimize.casestudy import run_case_study

    cs = run_case_study(params, DPScenario(), progress=False)
    f = {k: s.fuel_g for k, s in cs.sims.items()}
    assert f["rule"] > f["baseline"] > f["thermal"] >= f["thermal_cabin"] - 1e-6
    assert cs.table()["charge_sustaining"].all()


def test_convergence_baseline_thermal(params):
    from optimize.convergence import convergence_study

    rows = convergence_study(params, DPScenario(), ("baseline", "thermal"), DPGrids())
    for r in rows:
        assert abs(r["rel_change_pct"]) < 0.5, r
