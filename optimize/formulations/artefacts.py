"""Grid artefacts in a DP trajectory: the heater switching between neighbouring grid values step after
step (chatter), and the cabin state sitting on a grid node for long stretches (pinned: the interpolated
cost-to-go has a kink at every node, and a forward pass drawn to the kink is a property of the grid, not
of the car). Thermal-Cabin-DP records them in ``DPOutcome.extra["grid_artefacts"]``."""
from __future__ import annotations

import numpy as np

__all__ = ["trajectory_checks", "ON_NODE_K", "FLIP_TOL"]

#: A cabin temperature closer than this to a grid node counts as on the node (K).
ON_NODE_K = 1e-3
#: Heater changes smaller than this share of the heater grid step are no flip (W per W).
FLIP_TOL = 0.02


def _longest_run(mask) -> int:
    best = run = 0
    for m in mask:
        run = run + 1 if m else 0
        best = max(best, run)
    return best


def trajectory_checks(outcome) -> dict:
    """Grid artefacts in a Thermal-Cabin-DP solution (a :class:`DPOutcome` with a cabin state).

    Returns ``chatter_pct`` (share of steps where the heater goes to a neighbouring grid value and straight
    back; more generally, moves by more than ``FLIP_TOL`` and at most one heater grid step and comes back to
    within ``FLIP_TOL``), ``chatter_longest_s`` (longest stretch of such back-and-forth), ``chatter_off_bound_pct`` (the
    share of steps with such a flip that ends with the cabin off its comfort bound: on the bound, a heat
    between two grid values is held by an occasional step to the neighbouring value), ``pinned_pct`` (share of times
    the cabin sits within ``ON_NODE_K`` of a grid node above its comfort bound), ``pinned_longest_s``
    (longest such stretch) and ``at_bound_pct`` (share of times on the comfort bound, where the bound and
    not the grid holds it)."""
    ex = outcome.extra
    if "T_cab_grid_step" not in ex:
        raise ValueError("trajectory_checks needs a Thermal-Cabin-DP outcome (no cabin grid in this one)")
    sim = outcome.sim
    Ts = float(sim.t[1] - sim.t[0])
    q = np.asarray(sim.Q_heat_cmd, float)
    dq = ex["Q_heat_step"]
    flip = np.zeros(q.size, bool)
    if q.size >= 3:
        # away by more than FLIP_TOL grid steps but at most one, and straight back to within FLIP_TOL: on a
        # grid, a neighbouring value and back; with the hold control's off-grid heats, a grid value between two
        # holds counts too
        a, b, c = q[:-2], q[1:-1], q[2:]
        tol = FLIP_TOL * dq
        flip[1:-1] = (np.abs(b - a) > tol) & (np.abs(c - a) <= tol) & (np.abs(b - a) <= 1.0001 * dq)
    lo, h = ex["T_cab_grid_lo"], ex["T_cab_grid_step"]
    tc = np.asarray(sim.T_cab[1:], float)
    # a grid that moves with the comfort bound has its nodes at offset + lo + j h at each step
    off = np.asarray(ex.get("T_cab_grid_offset", 0.0), float)
    x = (tc - off - lo) / h
    on_node = np.abs(x - np.round(x)) * h < ON_NODE_K
    # riding the comfort bound is the constraint at work, not the grid, even where the bound is a node
    at_bound = np.zeros_like(on_node) if outcome.T_cab_lb is None else tc <= outcome.T_cab_lb + ON_NODE_K
    pinned = on_node & ~at_bound
    flip_off = flip & ~at_bound if flip.size == at_bound.size else flip
    return {"chatter_pct": 100.0 * float(flip.mean()) if q.size else 0.0,
            "chatter_longest_s": _longest_run(flip) * Ts,
            "chatter_off_bound_pct": 100.0 * float(flip_off.mean()) if q.size else 0.0,
            "pinned_pct": 100.0 * float(pinned.mean()) if pinned.size else 0.0,
            "pinned_longest_s": _longest_run(pinned) * Ts,
            "at_bound_pct": 100.0 * float(at_bound.mean()) if at_bound.size else 0.0}
