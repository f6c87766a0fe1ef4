"""Catalyst heating after a cold start: a prelude of the plant that every strategy runs.

After a start with the coolant below ``T_cat_degC`` the engine control heats the catalyst for ``t_cat_s``
(engine mode ``CAT``): the engine turns at ``n_cat_rpm`` with its ignition retarded, gives no power to the
drive and burns ``W_cat_g_per_s``; the battery drives the car (docs/cold_start.md). It is an emissions
requirement of the engine control, not a fuel choice of the supervisory controller, so
:func:`calib.model.simulate.simulate` applies it whatever the controller asks, and the DP formulations start
from the state at its end and add its fuel: every strategy shares the same prelude fuel and heat.

A demand the battery cannot meet alone starts the engine in the prelude too; the engine then supplies the
traction (the battery only what exceeds the engine's maximum), a plant rule independent of the strategy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.errors import ScenarioError
from calib.model.equations import CAT, INFEASIBLE_REASONS, ON, OUTPUTS, step, traction_power

_W_F = OUTPUTS.index("W_f")


def prelude_steps(mp, T_cl0: float, n_steps: int, Ts: float) -> int:
    """Number of catalyst-heating steps of a drive that starts at coolant ``T_cl0`` (0 when warm enough or
    when the car has no catalyst heating), at most the drive's ``n_steps``."""
    if mp.t_cat <= 0.0 or T_cl0 >= mp.T_cat:
        return 0
    return min(int(round(mp.t_cat / Ts)), int(n_steps))


def prelude_control(mp, P_trac: float) -> tuple:
    """The engine command ``(e_mode, P_bat_mg)`` of one prelude step at traction demand ``P_trac`` (W)."""
    if (P_trac / mp.eta_em if P_trac > 0.0 else 0.0) + mp.P_aux <= 0.95 * mp.P_bat_max:
        return CAT, 0.0
    # the battery cannot drive alone: the engine supplies the traction up to its maximum
    return ON, max(P_trac - mp.eta_mech * mp.P_e_max, 0.0) / mp.eta_em


@dataclass
class Prelude:
    """The catalyst-heating steps at the start of a drive.

    ``x`` (n+1, 3): SOC, coolant, cabin at each step's start and at the end; ``u`` (n, 3): engine mode,
    ``P_bat_mg`` and heater command of each step; ``out`` (n, len(OUTPUTS)): the outputs of
    :func:`calib.model.equations.step`."""

    x: np.ndarray
    u: np.ndarray
    out: np.ndarray
    Ts: float

    @property
    def n_steps(self) -> int:
        return int(self.u.shape[0])

    @property
    def fuel_g(self) -> float:
        """Fuel burnt in the prelude (g)."""
        return float(np.sum(self.out[:, _W_F]) * self.Ts)

    @property
    def end(self) -> tuple:
        """SOC, coolant and cabin temperature at the prelude's end."""
        return tuple(float(a) for a in self.x[-1])


def run_prelude(mp, v, grade, T_amb, T_bat, W_bl, x0, Ts: float, n_steps: int, heat=0.0, t=None) -> Prelude:
    """Simulate ``n_steps`` of catalyst heating (:func:`prelude_steps`) from state ``x0`` = (SOC, coolant,
    cabin) over speeds ``v`` (m/s, at least n_steps + 1), ``grade``, ``T_amb`` and ``T_bat`` (per step).

    ``heat``: the heater command (W), a number or ``heat(k, soc, T_cl, T_cab, P_trac)`` (the climate control's
    request; :func:`calib.model.simulate.simulate` asks the controller for it)."""
    x = np.empty((n_steps + 1, 3))
    x[0] = x0
    u = np.empty((n_steps, 3))
    out = np.empty((n_steps, len(OUTPUTS)))
    for k in range(n_steps):
        P_trac = traction_power(mp, v[k], v[k + 1], grade[k], Ts)
        q = float(heat(k, x[k, 0], x[k, 1], x[k, 2], P_trac)) if callable(heat) else float(heat)
        e, pb = prelude_control(mp, P_trac)
        r = step(mp, x[k, 0], x[k, 1], x[k, 2], e, pb, q, v[k], v[k + 1], grade[k], T_amb[k], T_bat[k], W_bl, Ts)
        if r[3] != 0:
            when = f"t={t[k]:.0f} s" if t is not None else f"step {k}"
            raise ScenarioError(
                f"catalyst heating at {when} (v={v[k] * 3.6:.1f} km/h): {INFEASIBLE_REASONS[int(r[3])]} (mode {e}, "
                f"P_trac {P_trac / 1e3:.1f} kW) - the cycle asks more than battery and engine deliver; check the "
                "cycle and the P_bat / P_e limits")
        u[k] = e, pb, q
        out[k] = r
        x[k + 1] = r[0], r[1], r[2]
    return Prelude(x, u, out, float(Ts))
