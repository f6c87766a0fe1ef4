"""ECMS: with a fixed equivalence factor it is Pontryagin's optimum on a problem with an analytic solution."""
import numpy as np
import pytest

from calib.model.equations import ON
from calib.model.params import default_parameters
from optimize.causal.controllers import ECMSController
from optimize.causal.ecms import ECMSParams
from optimize.causal.onestep import step_demand

A_G_PER_J = 5e-5  # fuel rate W_f = a P_e + b P_e^2 (g/s, P_e in W)
B_G_PER_J_W = 2e-9


def _quadratic_car():
    """Lossless drivetrain, constant OCV, no resistance, warm engine, fuel rate quadratic in engine power
    (exact at the fuel-map nodes, every 500 W, where the 500-W control grid puts the engine)."""
    mp = default_parameters().model_params()
    P = np.arange(0.0, 40e3 + 1, 500.0)
    eta = mp.fuel_scale / (mp.LHV * (A_G_PER_J + B_G_PER_J_W * P))
    return mp._replace(eta_em=1.0, eta_mech=1.0, P_aux=0.0, U_oc=np.full_like(mp.U_oc, 220.0),
                       R_int=np.zeros_like(mp.R_int), f_cl=np.ones_like(mp.f_cl), W_idle=1e-9, P_ool=P,
                       eta_ool=eta, w_ool=np.linspace(105, 500, P.size), P_e_max=40e3)


def _drive(mp, ctrl, demand):
    soc, tcl, tcab = 0.6, 85.0, 20.0
    fuel, P_e = 0.0, []
    for k, Pt in enumerate(demand):
        e, pb, q = ctrl(k, soc, tcl, tcab, Pt, 1.0)
        r = step_demand(mp, soc, tcl, tcab, e, pb, q, Pt, -10.0, mp.T_bat_ref, mp.W_bl, 1.0)
        assert r[4] == 0
        P_e.append(Pt - pb if e == ON else 0.0)
        soc, tcl, tcab = r[0], r[1], r[2]
        fuel += r[3]
    return fuel, soc, np.array(P_e)


@pytest.mark.parametrize("mean_W", [10e3, 7e3])
def test_fixed_equivalence_factor_gives_pontryagin_optimum(mean_W):
    mp = _quadratic_car()
    dev = np.array([-4e3, 4e3, -2e3, 2e3, 0.0, -6e3, 6e3, 1.5e3, -1.5e3])
    demand = np.tile(mean_W + dev, 20)
    # PMP: constant co-state, dW/dP_e = s / (LHV eta_max) everywhere, and SOC_N = SOC_0 gives P_e = mean demand
    eta_max = float(np.max(mp.eta_ool))
    s_star = mp.LHV * eta_max * (A_G_PER_J + 2 * B_G_PER_J_W * mean_W)
    ctrl = ECMSController(mp, ECMSParams(s0=s_star, k_s=0.0, mu0=0.0, k_mu=0.0, Q_heat_W=0.0), T_amb=-10.0)
    fuel, soc_N, P_e = _drive(mp, ctrl, demand)
    np.testing.assert_allclose(P_e, mean_W, atol=1e-6)
    assert abs(soc_N - 0.6) < 1e-9
    optimum = demand.size * (A_G_PER_J * mean_W + B_G_PER_J_W * mean_W ** 2)
    assert fuel == pytest.approx(optimum, rel=1e-9)
    # a strictly worse charge-sustaining strategy: the engine follows the demand (Jensen)
    follow = np.sum(A_G_PER_J * demand + B_G_PER_J_W * demand ** 2)
    assert fuel < follow - 1e-3
    # a different equivalence factor is not charge sustaining: the co-state is what the analysis says
    for f, sign in ((0.9, -1), (1.1, 1)):
        c2 = ECMSController(mp, ECMSParams(s0=f * s_star, k_s=0.0, Q_heat_W=0.0), T_amb=-10.0)
        _, soc2, _ = _drive(mp, c2, demand)
        assert sign * (soc2 - 0.6) > 1e-3
