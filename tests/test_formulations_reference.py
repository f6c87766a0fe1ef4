"""Baseline-DP against exhaustive enumeration: on a few steps of a short cycle every control sequence of
the problem's control set is simulated by the model (:func:`calib.model.equations.evaluate`, not the DP's
tables) and the cheapest charge-sustaining one is the reference the DP must reach."""
import numpy as np
import pytest

from calib.model.equations import evaluate
from optimize.formulations import DPGrids, DPScenario, solve_baseline
from optimize.formulations.solve import _power_controls


def _enumerate(mp, v, soc0, controls, Ts=1.0):
    """Least fuel (g) over all control sequences ending with SOC >= soc0 (warm engine, f_cl = 1)."""
    soc, fuel = np.array([soc0]), np.array([0.0])
    e, pb = controls[:, 0], controls[:, 1]
    for k in range(len(v) - 1):
        r = evaluate(mp, soc[:, None], 70.0, 20.0, e[None, :], pb[None, :], 0.0, v[k], v[k + 1], T_amb=-5.0, Ts=Ts)
        ok = r["feasible"]
        soc = r["soc_next"][ok]
        fuel = (fuel[:, None] + r["W_f"] * Ts)[ok]
    return float(np.min(fuel[soc >= soc0]))


# Accelerating (the engine must run to sustain the charge). On the paper's 0.01 SOC grid SOC moves by less
# than half a cell per step here, and the linear interpolation of the cost-to-go across the kink at the
# terminal boundary lets the forward pass dip below SOC_0 and pay to recover: +33 % fuel on the first
# profile (3.60 g against 2.70 g). Every SOC step halved (0.005) reaches the enumerated optimum; the
# paper-grid case is kept as a strict xfail so that a fix is noticed. On a decelerating profile the exhaustive optimum
# is 0 g (regeneration alone restores the charge) while the DP on its 0.01 SOC grid runs the engine: SOC moves
# by far less than a grid step in 3 s and the level set cannot see the sub-step recovery; that is the grid's
# resolution, not checked here.
@pytest.mark.parametrize("soc_step", [pytest.param(0.01, marks=pytest.mark.xfail(
    strict=True, reason="paper SOC grid: interpolation across the terminal kink (see above)")), 0.005])
@pytest.mark.parametrize("kmh", [(30, 33, 37, 38), (10, 14, 19, 22)])
def test_baseline_dp_reaches_the_enumerated_optimum(params, tmp_path, kmh, soc_step):
    cyc = tmp_path / "c.csv"
    cyc.write_text("time_s,speed_kph\n" + "".join(f"{i},{s}\n" for i, s in enumerate(kmh)))
    scen = DPScenario(cycle=str(cyc), T_amb=-5.0, soc0=0.6, T_cl0=70.0, T_cab0=20.0, Q_heat=0.0)
    grids = DPGrids(pbat=1000.0, soc=soc_step)
    mp = params.model_params()
    mp = mp._replace(f_cl=np.ones_like(mp.f_cl))
    best = _enumerate(mp, np.asarray(kmh, float) / 3.6, 0.6, _power_controls(mp, grids))
    o = solve_baseline(params, scen, grids)
    assert o.sim.soc[-1] >= 0.6 - 1e-12
    assert best > 0.5  # the engine must run
    assert o.sim.fuel_g == pytest.approx(best, rel=1e-9)
    # the DP's own off-grid SOC steps are the model's
    np.testing.assert_allclose(o.dp.x[:, 0], o.sim.soc, rtol=0, atol=1e-12)
