"""Causal controllers with the rule-based controller's call signature.

``controller(k, soc, T_cl, T_cab, P_trac, Ts) -> (e_mode, P_bat_mg, Q_heat_cmd)``: they see only the
present states and demand (and the ambient, a sensor reading given when built), never the drive ahead.
Both track the vehicle speed from the wheel powers seen so far (:func:`optimize.causal.onestep.speed_after`,
from standstill at ``reset()``) to count the kinetic energy a stop will return to the battery.
:func:`make_controller` builds any of ``rule``, ``ecms``, ``sdp`` for :func:`calib.model.simulate.simulate`.
"""
from __future__ import annotations

import numpy as np

from calib.errors import IptmError
from calib.model.rulebased import RuleBasedController, RuleParams

from optimize.causal.ecms import ECMSParams, co_states, ecms_choice, valuations
from optimize.causal.onestep import coolant_g_per_K, electric_g_per_soc, kinetic_soc_per_v2, power_controls
from optimize.causal.sdp import PENALTY_G_PER_STEP, SDPPolicy, lookahead_choice

CONTROLLERS = ("rule", "ecms", "sdp")


class _Causal:
    """Shared plumbing: control rows, work buffer, fallback when no control is feasible."""

    def __init__(self, mp, controls, Q_heat, T_amb, T_bat=None, W_bl=None):
        self.mp = mp
        self.controls = np.ascontiguousarray(controls, float)
        self.Q_heat = float(Q_heat)
        self.T_amb = float(T_amb)
        self.T_bat = float(mp.T_bat_ref if T_bat is None else T_bat)
        self.W_bl = float(mp.W_bl if W_bl is None else W_bl)
        self.work = np.empty((self.controls.shape[0], 5))
        self._fallback = RuleBasedController(mp, RuleParams(Q_heat_W=Q_heat), T_bat=self.T_bat)
        self.n_fallback = 0
        self.v = 0.0  # speed estimate (m/s), from standstill

    def reset(self) -> None:
        self._fallback.reset()
        self.n_fallback = 0
        self.v = 0.0

    def _emit(self, u, k, soc, T_cl, T_cab, P_trac, Ts):
        if u < 0:  # nothing feasible on the grid (demand beyond the limits): the rule-based choice
            self.n_fallback += 1
            self._fallback.T_bat = self.T_bat
            return self._fallback(k, soc, T_cl, T_cab, P_trac, Ts)
        return int(self.controls[u, 0]), float(self.controls[u, 1]), self.Q_heat


class SDPController(_Causal):
    """Runs a stored :class:`SDPPolicy` causally: one-step look-ahead on its expected next value."""

    def __init__(self, mp, policy: SDPPolicy, T_amb: float | None = None, T_bat=None, W_bl=None):
        cfg = policy.config
        super().__init__(mp, policy.controls, cfg.Q_heat, cfg.T_amb if T_amb is None else T_amb, T_bat, W_bl)
        self.policy = policy
        self.EV = np.ascontiguousarray(policy.EV)
        self.g_cl = cfg.mu_cl * coolant_g_per_K(mp)
        self.g_el = cfg.mu_el * electric_g_per_soc(mp, cfg.soc_target)
        self.kin = kinetic_soc_per_v2(mp, cfg.soc_target, cfg.regen_fraction)
        self.kin_slope = kinetic_soc_per_v2(mp, cfg.soc_target, cfg.regen_slope_per_mps)

    def describe(self) -> str:
        c = self.policy.config
        return (f"SDP (stationary policy, {self.policy.demand_W.size} demand bins, discount {c.discount:g}, "
                f"w_soc {c.w_soc_g_per_s:g} g/s, mu_el {c.mu_el:g}, mu_cl {c.mu_cl:g}, "
                f"regen_fraction {c.regen_fraction:g}{c.regen_slope_per_mps:+g} v, built at {c.T_amb:g} degC)")

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        c, pol = self.policy.config, self.policy
        u, self.v = lookahead_choice(self.mp, soc, T_cl, T_cab, P_trac, self.controls, self.Q_heat, self.T_amb,
                                     self.T_bat, self.W_bl, Ts, pol.soc_grid, pol.tcl_grid, pol.demand_W, self.EV,
                                     c.discount, c.w_soc_g_per_s, c.soc_target + c.soc_bias, PENALTY_G_PER_STEP,
                                     self.g_cl, self.g_el, self.kin, self.v, self.work, self.kin_slope)
        return self._emit(u, k, soc, T_cl, T_cab, P_trac, Ts)


class ECMSController(_Causal):
    """Thermal-aware ECMS with adaptive co-states (:mod:`optimize.causal.ecms`)."""

    def __init__(self, mp, ep: ECMSParams | None = None, T_amb: float = -10.0, T_bat=None, W_bl=None):
        ep = ep or ECMSParams()
        super().__init__(mp, power_controls(mp, ep.pbat_step_W), ep.Q_heat_W, T_amb, T_bat, W_bl)
        self.ep = ep
        self.k_el, self.k_cl = valuations(mp, ep.soc_target)
        self.kin = kinetic_soc_per_v2(mp, ep.soc_target, ep.regen_fraction)

    def describe(self) -> str:
        return "ECMS " + ", ".join(f"{k}={v:g}" for k, v in self.ep.to_dict().items())

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        s, mu = co_states(self.ep, soc, T_cl, self.kin * self.v * self.v)
        u, self.v = ecms_choice(self.mp, soc, T_cl, T_cab, P_trac, self.controls, self.Q_heat, self.T_amb,
                                self.T_bat, self.W_bl, Ts, s, self.k_el, mu, self.k_cl, self.v, self.work)
        return self._emit(u, k, soc, T_cl, T_cab, P_trac, Ts)


def make_controller(kind: str, params, *, T_amb: float, Q_heat: float = 1500.0, soc_target: float = 0.6,
                    policy: SDPPolicy | None = None, ecms: ECMSParams | None = None, rule: RuleParams | None = None,
                    markov=None):
    """A controller of ``kind`` (rule, ecms, sdp). ``sdp`` uses ``policy``, or builds one from ``markov``."""
    mp = params.model_params() if hasattr(params, "model_params") else params
    if kind == "rule":
        return RuleBasedController(mp, rule or RuleParams(Q_heat_W=Q_heat))
    if kind == "ecms":
        from dataclasses import replace

        return ECMSController(mp, replace(ecms or ECMSParams(), Q_heat_W=Q_heat, soc_target=soc_target), T_amb)
    if kind == "sdp":
        if policy is None:
            if markov is None:
                raise IptmError("controller sdp: give a stored policy (--policy FILE.npz) or a Markov model")
            from optimize.causal.sdp import SDPConfig, build_policy

            policy = build_policy(params, markov, SDPConfig(T_amb=T_amb, Q_heat=Q_heat, soc_target=soc_target))
        if abs(policy.config.Q_heat - Q_heat) > 1e-9:
            raise IptmError(f"controller sdp: the policy was built for a {policy.config.Q_heat:g}-W heater, "
                            f"the drive asks {Q_heat:g} W; rebuild the policy for this heater demand")
        return SDPController(mp, policy, T_amb)
    raise IptmError(f"unknown controller {kind!r}; choose from {', '.join(CONTROLLERS)}")
