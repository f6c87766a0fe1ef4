"""Assembling and solving the three formulations (see :mod:`optimize.formulations`)."""
from __future__ import annotations

import math
import resource
import time
from contextlib import contextmanager
from dataclasses import dataclass, field


import numba
import numpy as np

from calib.model.cycles import Cycle
from calib.errors import ScenarioError
from calib.model.equations import IDLE, OFF, ON, engine_bay_loss, f_cold, radiator, traction_power
from calib.model.simulate import fuel_equivalents_g

from optimize.dp.engine import DPProblem, DPResult, backward_pass, forward_pass
from optimize.formulations.artefacts import trajectory_checks
from optimize.formulations.layout import (HOLD, LEVEL_TOL, PENALTY_G_PER_STEP, _C_CH, _C_CHI, _C_CREL, _C_HOLD, _C_NQ,
                                          _C_NX, _C_PEN, _C_QHI, _C_QLO, _C_SH, _C_SHI,
                     _C_SLO, _C_TAMB, _C_TBAT, _C_TH, _C_THI, _C_TLO, _C_TS, _C_WBL, _MS, _T_SOC0,
                     SLOT, pack_params, packed_array)
from optimize.formulations.scenario import (FORMULATIONS, DPGrids, DPScenario, FormulationGrids, _grid,
                                            check_table_size)
from optimize.formulations.transition import delivered_heat, drift_offsets, fill_tables, hev_precompute, hev_transition




#: Interpolation of the cost-to-go of every formulation (:class:`optimize.dp.engine.DPProblem`): multilinear
#: with the cell the terminal SOC set's reach boundary cuts interpolated from the boundary, located from the
#: level along SOC (``"reach_first"``), for the one-sided set SOC_N >= SOC_0 and the ``continued`` terminal's
#: two-sided band alike (the band needs phi clamped to it beyond its edges, :func:`_continued_phi`).
INTERP = "reach_first"
#: Thermal-Cabin-DP's interpolation of the cost-to-go (the cabin is the last state).
CABIN_INTERP = INTERP
#: Coordinates of Thermal-Cabin-DP's cabin state (:func:`build_problem`) and the default.
CABIN_STATES = ("absolute", "bound")
CABIN_STATE = "bound"
#: Coordinates of the SOC state of every formulation (:func:`build_problem`) and the default.
SOC_STATES = ("absolute", "drift")
SOC_STATE = "drift"


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB; ru_maxrss, process-wide peak)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class DPOutcome:
    """Result of one formulation: the re-simulated :class:`SimResult` and the DP figures."""

    formulation: str
    sim: object
    dp: DPResult = field(repr=False)
    dp_cost: float
    predicted_cost: float
    t_backward: float
    t_forward: float
    t_total: float
    n_evaluations: int
    n_states: int
    n_controls: int
    peak_rss_mb: float
    grids: dict
    scenario: dict
    on_thermal: object = None  # Baseline-DP's controls on the full thermal model
    extra: dict = field(default_factory=dict)
    T_cab_lb: np.ndarray | None = field(default=None, repr=False)  # cabin comfort bound at steps 1..N (Thermal-Cabin-DP)

    @property
    def evals_per_second(self) -> float:
        """State-control evaluations per second of the backward pass."""
        return self.n_evaluations / self.t_backward if self.t_backward > 0 else float("nan")

    @property
    def fuel_g(self) -> float:
        """Fuel of the re-simulated optimum, in g."""
        return self.sim.fuel_g

    def charge_sustaining(self, soc_tol: float | None = None) -> bool:
        """Whether the final SOC is at least the initial one minus ``soc_tol``."""
        tol = self.scenario.get("soc_tol", 1e-3) if soc_tol is None else soc_tol
        ok = self.sim.soc[-1] >= self.sim.soc[0] - tol
        if self.on_thermal is not None:
            ok = ok and self.on_thermal.soc[-1] >= self.on_thermal.soc[0] - tol
        return bool(ok)

    def describe(self) -> dict:
        """The DP figures (fuel, costs, timings, sizes, grids) as a JSON-able dict."""
        return {"formulation": self.formulation, "fuel_g": self.sim.fuel_g, "dp_cost_g": self.dp_cost,
                "predicted_cost_g": self.predicted_cost, "feasible": bool(self.dp.feasible),
                "t_backward_s": self.t_backward, "t_forward_s": self.t_forward, "t_total_s": self.t_total,
                "n_evaluations": self.n_evaluations, "evals_per_second": self.evals_per_second,
                "n_states": self.n_states, "n_controls": self.n_controls, "peak_rss_mb": self.peak_rss_mb,
                "grids": self.grids, **self.extra}

    def to_pandas(self):
        """The re-simulated drive, one row per step (:meth:`SimResult.to_pandas`), the DP figures in ``attrs``."""
        df = self.sim.to_pandas()
        df.attrs.update({k: v for k, v in self.describe().items() if not isinstance(v, np.ndarray)})
        return df

    def save(self, path, value_functions: bool = False):
        """Save as a result folder of kind ``dp-outcome`` (:mod:`optimize.formulations.outcome_io`)."""
        from optimize.formulations.outcome_io import save_outcome

        return save_outcome(self, path, value_functions)

    @classmethod
    def load(cls, path) -> "DPOutcome":
        """Read a folder written by :meth:`save`."""
        from optimize.formulations.outcome_io import load_outcome

        return load_outcome(path, cls)


class _Replay:
    """Open-loop controller replaying a control sequence (for :func:`calib.model.simulate.simulate`)."""

    def __init__(self, e_mode, P_bat_mg, Q_cmd, name):
        self.e, self.p, self.q, self.name = e_mode, P_bat_mg, Q_cmd, name

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        return int(self.e[k]), float(self.p[k]), float(self.q[k])

    def describe(self):
        return self.name


def resimulate(params, cycle, e_mode, P_bat_mg, Q_cmd, scen: DPScenario, name: str):
    """Re-simulate a control sequence through :func:`calib.model.equations.step` from the scenario's initial state."""
    from calib.model.simulate import simulate

    return simulate(params, cycle, _Replay(e_mode, P_bat_mg, Q_cmd, name), T_amb=scen.T_amb, soc0=scen.soc0,
                    T_cl0=scen.T_cl0, T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)


# ---------------------------------------------------------------------------------------------------
# problem assembly
# ---------------------------------------------------------------------------------------------------
def _mp(params):
    return params.model_params() if hasattr(params, "model_params") else params


def scenario_prelude(params, cycle: Cycle, scen: DPScenario):
    """The catalyst heating a drive of the scenario starts with (:mod:`calib.model.catalyst`; 0 steps when the
    coolant is warm enough), under the scenario's constant heater demand: the same prelude the simulator runs
    for the rule-based and causal strategies."""
    from calib.model.catalyst import prelude_steps, run_prelude

    mp = _mp(params)
    N, Ts = cycle.n_steps, cycle.Ts
    grade = cycle.grade if cycle.grade is not None else np.zeros(N + 1)
    n = prelude_steps(mp, scen.T_cl0, N, Ts)
    return run_prelude(mp, cycle.v, grade, np.full(N + 1, float(scen.T_amb)), np.full(N + 1, float(mp.T_bat_ref)),
                       mp.W_bl, (scen.soc0, scen.T_cl0, scen.T_cab0), Ts, n, float(scen.Q_heat), t=cycle.t)


def reference_run(params, cycle: Cycle, scen: DPScenario):
    """The (untuned) rule-based controller under a constant ``Q_heat`` demand: its cabin trajectory is
    the cabin reference, its final states the default targets of the ``match`` terminal condition."""
    from calib.model.simulate import simulate

    return simulate(params, cycle, T_amb=scen.T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0, T_cab0=scen.T_cab0,
                    Q_heat=scen.Q_heat)


def reference_cabin(params, cycle: Cycle, scen: DPScenario) -> np.ndarray:
    """Cabin trajectory (N+1,) under a constant ``Q_heat`` demand (heater-limited; rule-based coolant)."""
    return reference_run(params, cycle, scen).T_cab.copy()


#: Continuation tables already computed (key: car, scenario and sub-grid): one table serves every drive
#: of a comparison at the same ambient and initial state.
_CONT_CACHE: dict = {}


def _sub_nodes(lo: float, hi: float, step: float) -> np.ndarray:
    n = max(1, int(math.ceil((hi - lo) / step - 1e-9)))
    return np.linspace(lo, hi, n + 1) if hi > lo else np.array([lo])


def continuation_table(mp, scen: DPScenario, soc_nodes, tcl_nodes, tcab_nodes) -> np.ndarray:
    """C (g, :func:`calib.model.continuation.continuation_value`, ``ref`` the scenario's initial state) on the
    sub-grid ``soc_nodes x tcl_nodes x tcab_nodes``, at the scenario's ambient and heater demand; cached."""
    from calib.model.continuation import continuation_value

    nodes = [np.asarray(a, dtype=np.float64) for a in (soc_nodes, tcl_nodes, tcab_nodes)]
    key = (tuple(np.asarray(v, dtype=np.float64).tobytes() for v in mp), scen.T_amb, scen.Q_heat, scen.soc0,
           scen.T_cl0, scen.T_cab0, scen.cont_cycle, *(a.tobytes() for a in nodes))
    if key not in _CONT_CACHE:
        S, T, B = np.meshgrid(*nodes, indexing="ij")
        _CONT_CACHE[key] = continuation_value(mp, S, T, B, T_amb=scen.T_amb, Q_heat=scen.Q_heat,
                                              ref=(scen.soc0, scen.T_cl0, scen.T_cab0), cycle=scen.cont_cycle)
        if len(_CONT_CACHE) > 16:
            _CONT_CACHE.pop(next(iter(_CONT_CACHE)))
    return _CONT_CACHE[key]


def _continued_phi(mp, scen: DPScenario, grid_list, cab_offset: float, cab_final: float | None):
    """phi(X) = C(X) - C(x_0) on the DP grid ``grid_list``: C tabulated on a sub-grid (every
    ``cont_soc_every``-th SOC node, coolant every ``cont_tcl_step`` K, cabin every ``cont_tcab_step`` K over
    the grids' ranges) and interpolated multilinearly; the offset at x_0 is removed so that phi(x_0) = 0.

    With a SOC band (``cont_soc_band``) phi outside it is phi at the band's nearest edge. The level-set
    method stores, at a node that cannot reach the band, the cost of its least-level control, and the
    reach-boundary interpolation (:func:`optimize.dp.kernels._lin_reach`) places that value on the reach
    boundary as the boundary's cost. With C extended beyond the band that cost includes the credit for
    the charge above the band the drive ends with, which no feasible run gets: the boundary looked cheap,
    the policy drifted to it and paid to get back (NYCC at 0 degC: 55.33 g against 54.39 g with phi
    clamped, continuation-corrected). Runs that end in the band are valued the same either way."""
    from scipy.interpolate import RegularGridInterpolator

    socg, tclg = grid_list[0], grid_list[1]
    soc_n = socg[:: int(scen.cont_soc_every)]
    if soc_n[-1] != socg[-1]:
        soc_n = np.append(soc_n, socg[-1])
    tcl_n = _sub_nodes(float(tclg[0]), float(tclg[-1]), scen.cont_tcl_step)
    three = len(grid_list) == 3
    if three:
        tcab_n = _sub_nodes(float(grid_list[2][0] + cab_offset), float(grid_list[2][-1] + cab_offset),
                            scen.cont_tcab_step)
    else:
        tcab_n = np.array([float(cab_final)])
    tab = continuation_table(mp, scen, soc_n, tcl_n, tcab_n)
    if three and tcab_n.size > 1:
        f = RegularGridInterpolator((soc_n, tcl_n, tcab_n), tab, bounds_error=False, fill_value=None)
    else:
        f = RegularGridInterpolator((soc_n, tcl_n), tab[:, :, 0], bounds_error=False, fill_value=None)
    use_cab = three and tcab_n.size > 1
    x0 = [scen.soc0, scen.T_cl0] + ([scen.T_cab0] if use_cab else [])
    c0 = float(f(np.array([x0]))[0])

    band = scen.cont_soc_band
    lo, hi = (-np.inf, np.inf) if band is None else (scen.soc0 - band, scen.soc0 + band)

    def phi(X):
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        # outside the terminal SOC band, the value at the band's nearest edge: a state the drive cannot
        # bring into the band is not credited the charge it would end with (see the docstring)
        pts = np.column_stack([np.clip(X[:, 0], lo, hi), X[:, 1]] + ([X[:, 2] + cab_offset] if use_cab else []))
        return f(pts) - c0
    phi.nodes = (soc_n, tcl_n, tcab_n)
    return phi


def _terminal_cost(mp, scen: DPScenario, nx: int, cab_soft=None, cab_offset: float = 0.0,
                   cab_final: float | None = None, grid_list=None):
    """Terminal cost phi(X) on grid points X (n, nx) for the scenario's terminal condition; the cabin
    temperature is ``X[:, 2] + cab_offset`` (3 states) or ``cab_final`` (Thermal-DP's ``continued``: the
    reference run's final cabin, the cabin not being a state); ``continued`` tabulates on a sub-grid of
    ``grid_list`` (the DP's grids)."""
    if scen.terminal == "continued":
        if nx == 1:
            return None
        if grid_list is None or (nx == 2 and cab_final is None):
            raise ScenarioError("terminal 'continued' needs the DP's grids (and, with 2 states, the final cabin)")
        return _continued_phi(mp, scen, grid_list, cab_offset, cab_final)
    if scen.terminal == "valued":
        if nx == 1:
            return None

        # Heat only: the charge is held by the terminal set SOC_N >= SOC_0. Crediting charge above SOC_0 at
        # the corrected fuel's rate would be exploited: the engine's marginal efficiency exceeds the best
        # average efficiency that rate assumes (measured: Thermal-DP then charges to the SOC ceiling and
        # "saves" 50 g of corrected fuel).
        def phi(X):
            eq = fuel_equivalents_g(mp, scen.soc0, scen.soc0, scen.T_cl0, X[:, 1], scen.T_cab0,
                                    X[:, 2] + cab_offset if nx == 3 else scen.T_cab0)
            return -(eq["coolant_g"] + eq["cabin_g"]) * np.ones(X.shape[0])
        return phi
    if scen.terminal == "free" and cab_soft is not None:
        T_term, rate = cab_soft
        return lambda X: rate * np.maximum(T_term - (X[:, 2] + cab_offset), 0.0)  # noqa: E731
    return None


def _power_controls(mp, grids: DPGrids) -> np.ndarray:
    P_bat = _grid(mp.P_bat_min, mp.P_bat_max, grids.pbat, "battery-power grid (P_bat_min_W:pbat:P_bat_max_W)")
    rows = [(OFF, 0.0), (IDLE, 0.0)] + [(ON, pb - mp.P_aux) for pb in P_bat]
    return np.array(rows, dtype=np.float64)


def _traction(mp, cyc: Cycle) -> np.ndarray:
    N, Ts = cyc.n_steps, cyc.Ts
    grade = cyc.grade if cyc.grade is not None else np.zeros(N + 1)
    return np.array([traction_power(mp, cyc.v[k], cyc.v[k + 1], grade[k], Ts) for k in range(N)])


def _t_cl_tables(mp, tclg, T_amb):
    fcl = np.array([f_cold(mp, t) for t in tclg])
    loss = np.array([engine_bay_loss(mp.hA_eng, mp.kappa, t, T_amb)[0] + radiator(mp, t) for t in tclg])
    return fcl, loss


def dp_objective(params, sim, scen: DPScenario, nx: int, T_cab_terminal_min: float | None = None, *,
                 grids: DPGrids | None = None, cabin: str = CABIN_STATE) -> float:
    """The objective a formulation with ``nx`` states minimises, evaluated on any simulated run ``sim``:
    fuel plus the scenario's terminal cost at its final state (the ``match`` bounds and ``SOC_N >= SOC_0``
    are constraints, not costs). Compares strategies on the DP's own terms: a DP whose feasible set
    contains another strategy's run has an objective at most that run's, up to grid error. With
    ``continued`` the terminal cost is the DP's own interpolated ``C(x_N) - C(x_0)`` (Thermal-DP: at the
    reference run's final cabin, as in the DP), on ``grids`` and the ``cabin`` coordinate of that DP."""
    if scen.terminal == "continued" and nx >= 2:
        b = build_problem(params, scen, FormulationGrids.coerce(grids).of(FORMULATIONS[nx - 1]), nx, cabin=cabin)
        off = float(b.extra["T_cab_grid_offset"][-1]) if nx == 3 else 0.0
        X = np.array([[sim.soc[-1], sim.T_cl[-1], sim.T_cab[-1] - off][:nx]])
        return float(sim.fuel_g + b.prob.terminal_cost(X)[0])
    cab_soft = None
    if nx == 3 and T_cab_terminal_min is not None:
        cab_soft = (float(T_cab_terminal_min), float(scen.cab_terminal_g_per_K))
    phi = _terminal_cost(_mp(params), scen, nx, cab_soft)
    if phi is None:
        return float(sim.fuel_g)
    X = np.array([[sim.soc[-1], sim.T_cl[-1], sim.T_cab[-1]]])
    return float(sim.fuel_g + phi(X)[0])


@dataclass
class _Built:
    prob: DPProblem
    x0: np.ndarray
    cyc: Cycle  # the whole drive, catalyst heating included; the DP's steps are those after the prelude
    extra: dict
    mp: object = None
    pre: object = None  # the catalyst-heating prelude (calib.model.catalyst.Prelude; 0 steps when warm)

    def controls(self, e_mode, P_bat_mg, Q_cmd) -> list:
        """The DP's engine mode, battery power and heater sequences with the prelude's commands in front (one
        value per step of the drive)."""
        return [np.concatenate([self.pre.u[:, i], np.asarray(a, float)]) for i, a in enumerate((e_mode, P_bat_mg, Q_cmd))]


#: Budgets of one DP problem, checked before anything is allocated (environment variables override them):
#: states (IPTM_DP_MAX_STATES), state-control pairs per step (IPTM_DP_MAX_PAIRS) and the memory of the
#: transition tables (:func:`~optimize.formulations.scenario.check_table_size`). The paper's grids and their
#: halving stay inside; the dashboard's finest sliders, or a battery-power step of a few watts, do not.
DP_MAX_STATES = 4_000_000
DP_MAX_PAIRS = 2e10


def check_problem_size(axis_sizes, n_controls: int, n_steps: int, table_cells: int = 0) -> dict:
    """Refuse a problem whose states, state-control pairs per step or transition tables exceed the budgets,
    with the figures.

    Returns the estimate ``{"states", "controls", "pairs_per_step", "value_MB", "table_MB"}``."""
    import os

    states = int(np.prod([int(n) for n in axis_sizes]))
    pairs = float(states) * float(n_controls)
    table_mb = 8.0 * float(table_cells) / 1e6
    est = {"states": states, "controls": int(n_controls), "pairs_per_step": pairs,
           "value_MB": 2 * states * 8 / 1e6, "table_MB": table_mb}
    max_states = float(os.environ.get("IPTM_DP_MAX_STATES", DP_MAX_STATES))
    max_pairs = float(os.environ.get("IPTM_DP_MAX_PAIRS", DP_MAX_PAIRS))
    if states > max_states or pairs > max_pairs:
        raise ScenarioError(
            f"the DP problem is too large: {states:,} states ({' x '.join(str(int(n)) for n in axis_sizes)}) x "
            f"{n_controls:,} controls = {pairs:.3g} evaluations per step over {n_steps} steps (budgets: "
            f"{max_states:.3g} states, {max_pairs:.3g} per step): use larger grid steps, or raise "
            "IPTM_DP_MAX_STATES / IPTM_DP_MAX_PAIRS")
    check_table_size(n_steps, table_mb)
    return est


def build_problem(params, scen: DPScenario, grids: DPGrids, nx: int, *, heater: float | None = None,
                  warm: bool = False, cycle=None, interp: str = INTERP,
                  cabin: str = "absolute", soc: str = SOC_STATE, hold: bool | None = None) -> _Built:
    """Assemble the :class:`DPProblem` of a formulation with ``nx`` states (1, 2 or 3); ``interp``: the
    cost-to-go interpolation (:class:`optimize.dp.engine.DPProblem`); ``cabin`` (3 states): the cabin
    state is the temperature (``"absolute"``) or its height above the step's comfort bound (``"bound"``:
    the grid moves with the bound, which is a node at every step); ``soc``: the SOC state is the charge
    (``"absolute"``) or the charge minus the step's engine-off drift (``"drift"``: the SOC grid moves with
    the charge an engine-off drive carries to SOC_0 at the end, :func:`~optimize.formulations.transition.drift_offsets`;
    ``extra["soc_grid_offset"]`` holds the offsets, the charge is ``x[:, 0]`` plus them). ``hold`` (3 states; default: with
    ``cabin="bound"``): besides the heater grid, every power control is paired with "hold the bound", the
    heat that puts the next cabin temperature on the next step's comfort bound (control value
    :data:`~optimize.formulations.layout.HOLD`; :func:`optimize.formulations.transition.hold_heat`).

    Why the drift: with SOC_N >= SOC_0 the cost-to-go has a convex kink at the charge from which the rest
    of the drive can be driven on the battery alone. Engine-off steps move the charge by a fraction of a
    0.01 cell, so on a fixed grid every step re-interpolates the kink linearly and diffuses it; the
    policy then undervalues charge mid-drive and recovers it at a high marginal cost at the end. On the
    moving grid the kink stays on a node. The grid spans the charges [soc_min, soc_max] at every step, so
    it has more nodes (74 instead of 41 on the default drive at 0.01)."""
    if cabin not in CABIN_STATES:
        raise ScenarioError(f"cabin state {cabin!r}: choose one of {', '.join(CABIN_STATES)}")
    if soc not in SOC_STATES:
        raise ScenarioError(f"SOC state {soc!r}: choose one of {', '.join(SOC_STATES)}")
    hold = (cabin == "bound" and nx == 3) if hold is None else bool(hold)
    if hold and nx != 3:
        raise ScenarioError(f"the hold-the-bound heater control needs the cabin state (3 states), not {nx}")
    mp = _mp(params)
    if warm:
        mp = mp._replace(f_cl=np.ones_like(mp.f_cl))
    full = scen.load_cycle(cycle)
    # catalyst heating after a cold start belongs to the plant: the DP starts from the state at its end
    pre = scenario_prelude(mp, full, scen)
    n0 = pre.n_steps
    if n0 >= full.n_steps:
        raise ScenarioError(f"the drive ({full.n_steps * full.Ts:g} s) ends within the catalyst heating of a cold start "
                            f"({n0 * full.Ts:g} s, coolant {scen.T_cl0:g} degC below T_cat_degC): nothing is left to "
                            "optimise; drive longer or start warmer")
    cyc = Cycle(full.name, full.t[n0:], full.v[n0:], None if full.grade is None else full.grade[n0:])
    soc_start, T_cl_start, T_cab_start = pre.end
    N, Ts = cyc.n_steps, cyc.Ts
    if not (scen.soc_min <= scen.soc0 <= scen.soc_max):
        raise ScenarioError(f"soc0 {scen.soc0} outside the SOC grid [{scen.soc_min}, {scen.soc_max}]")
    phys = _grid(scen.soc_min, scen.soc_max, grids.soc, "SOC grid (soc_min:soc:soc_max)")
    tclg = _grid(scen.T_cl_min, scen.T_cl_max, grids.tcl, "coolant grid (T_cl_min:tcl:T_cl_max)")
    fclg, lossg = _t_cl_tables(mp, tclg, scen.T_amb)
    pc = _power_controls(mp, grids)
    P_trac = _traction(mp, cyc)
    extra = {"soc_state": soc}
    if soc == "drift":
        soff = drift_offsets(mp, P_trac, float(Ts), float(mp.T_bat_ref), float(scen.soc0))
        # the same lattice as the fixed grid, extended so that it spans [soc_min, soc_max] at every step
        h = grids.soc
        j0 = math.floor((phys[0] - soff.max() - phys[0]) / h + 1e-9)
        j1 = math.ceil((phys[-1] - soff.min() - phys[0]) / h - 1e-9)
        socg = phys[0] + h * np.arange(j0, j1 + 1)
    else:
        soff = np.zeros(N + 1)
        socg = phys
    extra["soc_grid_offset"] = soff.copy()
    w = np.zeros((N, 6))
    w[:, 0] = P_trac
    w[:, 4] = soff[:-1]
    w[:, 5] = soff[1:]
    grid_list = [socg]
    # the continuation values charge, so with it the terminal SOC is free or held to a band around SOC_0
    # (Baseline-DP, without it, keeps the set); the SOC state at N is the charge minus soff[-1]
    s_end = scen.soc0 - soff[-1]
    bounds = [(s_end, None)]
    if scen.terminal == "continued" and nx >= 2:
        band = scen.cont_soc_band
        bounds = [(None, None) if band is None else (s_end - band, s_end + band)]
    x0 = [soc_start - soff[0]]
    if nx >= 2:
        if not (scen.T_cl_min <= scen.T_cl0 <= scen.T_cl_max):
            raise ScenarioError(f"T_cl0 {scen.T_cl0} outside the coolant grid")
        if not (scen.T_cl_min <= T_cl_start <= scen.T_cl_max):
            raise ScenarioError(f"the coolant at the end of catalyst heating, {T_cl_start:.2f} degC, is outside the "
                                f"coolant grid [{scen.T_cl_min:g}, {scen.T_cl_max:g}]: widen T_cl_min / T_cl_max")
        grid_list.append(tclg)
        bounds.append((None, None))
        x0.append(T_cl_start)
    if nx >= 2:
        rref = reference_run(params, full, scen)
        ref = rref.T_cab[n0:].copy()
        w[:, 1] = ref[:-1]
        extra["T_cab_ref_final"] = float(ref[-1])
        extra["T_cab_ref_mean"] = float(np.mean(ref))
        if scen.terminal == "match":
            t_cl = scen.T_cl_final_min if scen.T_cl_final_min is not None else float(rref.T_cl[-1])
            t_cab = scen.T_cab_final_min if scen.T_cab_final_min is not None else float(rref.T_cab[-1])
            bounds[1] = (t_cl, None)
            extra.update(T_cl_final_min=t_cl, T_cab_final_min=t_cab)
    cab_soft = None
    if nx == 3:
        lb = ref - scen.cab_lb_offset
        lb[0] = min(lb[0], T_cab_start)
        w[:, 2] = lb[1:]
        hi = max(scen.T_cab_ub, float(ref[-1]), T_cab_start)
        rel = cabin == "bound"
        if rel:
            # the state is the height above the step's comfort bound: the bound is the node 0 at every step
            w[:, 3] = lb[:-1]
            off = lb.copy()
            lo, hi = 0.0, hi - float(np.min(lb))
        else:
            off = np.zeros(N + 1)
            lo = math.floor(float(np.min(lb)) + 1e-9)
        if hi - lo < grids.tcab:
            hi = lo + grids.tcab
        tcabg = _grid(lo, hi, grids.tcab, "cabin grid (tcab)")
        if tcabg[-1] < hi - 1e-9:
            tcabg = np.append(tcabg, tcabg[-1] + grids.tcab)
        grid_list.append(tcabg)
        bounds.append((t_cab - off[-1], None) if scen.terminal == "match" else (None, None))
        cab_soft = (float(ref[-1]), float(scen.cab_terminal_g_per_K))
        x0.append(T_cab_start - off[0])
        Q = _grid(scen.Q_heat_min, scen.Q_heat_max, grids.qheat, "heater grid (Q_heat_min:qheat:Q_heat_max)")
        extra.update(T_cab_lb_min=float(np.min(lb)), T_cab_ub=float(tcabg[-1] + np.min(off)),
                     T_cab_terminal_min=float(ref[-1]), T_cab_grid_lo=float(tcabg[0]),
                     T_cab_grid_step=float(grids.tcab), Q_heat_step=float(grids.qheat), cabin_state=cabin,
                     T_cab_grid_offset=np.concatenate([np.full(n0, np.nan), off[1:]]), heater_hold=hold)
        q_range = (float(Q[0]), float(Q[-1]))  # the hold heat stays within the grid's ends
        if hold:
            Q = np.append(Q, HOLD)
    else:
        Q = np.array([scen.Q_heat if heater is None else heater])
    terminal = _terminal_cost(mp, scen, nx, cab_soft, float(off[-1]) if nx == 3 else 0.0,
                              cab_final=extra.get("T_cab_ref_final"), grid_list=[phys] + grid_list[1:])
    if scen.terminal == "continued" and terminal is not None:
        extra["continuation_nodes"] = [a.tolist() for a in terminal.nodes]
    extra["terminal"] = scen.terminal
    extra["prelude"] = {"steps": n0, "fuel_g": pre.fuel_g, "soc_end": soc_start, "T_cl_end_degC": T_cl_start,
                        "T_cab_end_degC": T_cab_start}
    nq = Q.size
    controls = np.column_stack([np.repeat(pc, nq, axis=0), np.tile(Q, pc.shape[0])])
    cfg = np.zeros(16)
    cfg[_C_SLO], cfg[_C_SHI], cfg[_C_SH] = phys[0], phys[-1], phys[1] - phys[0]
    cfg[_C_TLO], cfg[_C_THI], cfg[_C_TH] = tclg[0], tclg[-1], tclg[1] - tclg[0]
    if nx == 3:
        cfg[_C_CHI], cfg[_C_CH] = scen.T_cab_ub, grids.tcab
        cfg[_C_CREL] = 1.0 if rel else 0.0
    cfg[_C_PEN] = PENALTY_G_PER_STEP
    cfg[_C_NX], cfg[_C_NQ], cfg[_C_TAMB], cfg[_C_TS] = nx, nq, scen.T_amb, Ts
    cfg[_C_TBAT], cfg[_C_WBL] = mp.T_bat_ref, mp.W_bl
    ms = np.array([float(getattr(mp, n)) for n in _MS])
    tab_shape = (N, pc.shape[0], _T_SOC0 + socg.size)
    # before the tables are allocated
    check_problem_size([g.size for g in grid_list], controls.shape[0], N, table_cells=int(np.prod(tab_shape)))
    c = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    p = pack_params(cfg, ms, [socg, fclg, lossg, c(mp.soc_bp), c(mp.U_oc), c(mp.soc_bp_R), c(mp.R_int),
                              c(mp.T_fcl), c(mp.f_cl), tab_shape])
    fill_tables(packed_array(p, "big", tab_shape), mp, pc, socg, P_trac, float(Ts), float(mp.T_bat_ref), soff)
    if nx == 3:
        # clipped to the grid's ends, a hold heat beyond them is what a grid control already delivers
        p[_C_QLO], p[_C_QHI], p[_C_HOLD] = q_range[0], q_range[1], 1.0 if hold else 0.0
    from optimize.formulations.fused import forward_hev

    prob = DPProblem(grids=grid_list, controls=controls, N=N, transition=hev_transition, w=w, params=p,
                     terminal_bounds=bounds, terminal_cost=terminal, boundary="levelset", clip=True,
                     level_tol=LEVEL_TOL, precompute=hev_precompute,
                     table_shape=(pc.shape[0], _T_SOC0 + socg.size), interp=interp, forward_kernel=forward_hev)
    return _Built(prob, np.array(x0), full, extra, mp, pre)


#: Backward kernels of the formulations (:func:`optimize.formulations.fused.backward_pass_fused`; Baseline-DP's
#: fused kernel gives the generic engine's values bit for bit, so "fused" and "fused-exact" are one there).
ENGINES = ("fused", "fused-exact", "generic")


def _solve(b: _Built, engine: str, progress=None):
    if engine not in ENGINES:
        raise ScenarioError(f"engine {engine!r}: choose one of {', '.join(ENGINES)}")
    if engine in ("fused", "fused-exact"):
        from optimize.formulations.fused import backward_pass_fused

        vf = backward_pass_fused(b.prob, separable=engine == "fused", progress=progress)
    else:
        vf = backward_pass(b.prob, progress=progress)
    res = forward_pass(b.prob, vf, b.x0)
    return res


def _check_drivable(name, b, res) -> None:
    """A ScenarioError naming the cycle and the time where no state has a feasible way on (every cost-to-go
    infinite), before an infeasible policy (NaN controls) is re-simulated. Where every step has a feasible
    state, the drive is possible and :func:`_outcome` names the grids or the terminal condition instead."""
    if res.feasible or res.V is None:
        return
    V = np.asarray(res.V)
    dead = ~np.isfinite(V.reshape(V.shape[0], -1)).any(axis=1)[:-1]
    if not dead.any():
        return
    cyc = b.cyc
    k = int(np.flatnonzero(dead)[-1]) + (b.pre.n_steps if b.pre is not None else 0)  # the DP starts after the prelude
    raise ScenarioError(f"{name}: the cycle {cyc.name} cannot be driven within the car's limits at t = {cyc.t[k]:g} s "
                        f"({cyc.v[k] * 3.6:.0f} km/h to {cyc.v[k + 1] * 3.6:.0f} km/h in {cyc.Ts:g} s): no power split "
                        "is feasible there from any state of charge; check the cycle's speeds and time base, or the "
                        "parameters' power limits (P_e_max_W, P_bat_max_W)")


def _outcome(name, params, b, res, scen, grids, sim, t0, on_thermal=None):
    if not res.feasible:
        raise ScenarioError(f"{name}: no feasible charge-sustaining solution on these grids (steps completed "
                            f"{res.steps_completed}/{b.prob.N}, terminal level {res.terminal_level:.3g})")
    # the DP's costs start after catalyst heating: its fuel, the same for every strategy, is added
    pre_g = b.pre.fuel_g
    lb = None
    if len(b.prob.grids) == 3:
        lb = np.concatenate([np.full(b.pre.n_steps, np.nan), b.prob.w[:, 2]])
    return DPOutcome(formulation=name, sim=sim, dp=res, dp_cost=float(res.cost) + pre_g,
                     predicted_cost=float(res.predicted_cost[0]) + pre_g, t_backward=res.t_backward,
                     t_forward=res.t_forward, t_total=time.perf_counter() - t0,
                     n_evaluations=int(res.n_evaluations), n_states=b.prob.n_states,
                     n_controls=b.prob.n_controls, peak_rss_mb=peak_rss_mb(), grids=grids.to_dict(),
                     scenario=scen.to_dict(), on_thermal=on_thermal, extra=b.extra,
                     T_cab_lb=lb)


@contextmanager
def _threads(n):
    """Temporarily run numba parallel kernels on ``n`` threads (None: unchanged)."""
    if n is None:
        yield
        return
    old = numba.get_num_threads()
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(old)


def solve_baseline(params, scenario: DPScenario | None = None, grids=None, *,
                   threads: int | None = 1, soc: str = SOC_STATE, engine: str = "fused",
                   progress=None) -> DPOutcome:
    """Baseline-DP (SOC only, f_cl = 1). ``grids``: a :class:`DPGrids`, a :class:`FormulationGrids` (its
    Baseline-DP grid) or None (the default, :data:`optimize.formulations.BASELINE_CONVERGED_GRIDS`); the
    other solvers take the same. ``.sim``: its own optimum (f_cl = 1); ``.on_thermal``: its controls
    re-simulated on the full thermal model with the scenario's heater demand. ``soc``: the SOC state's
    coordinate (:func:`build_problem`). ``engine``: "fused" (default, the serial kernel
    :func:`optimize.formulations.fused.backward1`, the generic engine's values bit for bit) or "generic"
    (the engine, on ``threads`` threads). ``progress``: None or ``progress(done, total)``, called with the
    backward pass's steps done and the number of steps as it goes (:func:`optimize.dp.engine.solve`); the
    other solvers take it too."""
    scen, grids = scenario or DPScenario(), FormulationGrids.coerce(grids).of("baseline")
    t0 = time.perf_counter()
    b = build_problem(params, scen, grids, 1, warm=True, soc=soc)
    with _threads(threads):
        res = _solve(b, engine, progress)
    _check_drivable("baseline", b, res)
    mp_warm = b.mp
    e, pbm, q = b.controls(res.u[:, 0], res.u[:, 1], np.full(b.prob.N, scen.Q_heat))
    sim = resimulate(mp_warm, b.cyc, e, pbm, q, scen, "Baseline-DP (f_cl = 1)")
    sim.info["params"] = params.meta.get("name", "") if hasattr(params, "meta") else ""
    on = resimulate(params, b.cyc, e, pbm, q, scen, "Baseline-DP policy on the thermal model")
    out = _outcome("baseline", params, b, res, scen, grids, sim, t0, on_thermal=on)
    out.extra["engine"] = engine
    out.extra["kernel"] = res.kernel
    return out


def solve_thermal(params, scenario: DPScenario | None = None, grids=None, *,
                  heater: float | None = None, warm: bool = False, engine: str = "fused",
                  threads: int | None = None, soc: str = SOC_STATE, progress=None) -> DPOutcome:
    """Thermal-DP (SOC, T_cl). ``heater`` overrides the scenario's demand (e.g. 0 W); ``warm=True``
    sets f_cl = 1 (with heater 0 W it must reproduce Baseline-DP); ``soc``: the SOC state's coordinate
    (:func:`build_problem`). ``engine``: "fused" (default: the separable kernel where the terminal level
    depends on SOC alone, :func:`optimize.formulations.fused.backward_pass_fused`), "fused-exact" (the
    fused kernel that gives the generic engine's values bit for bit) or "generic"; ``.extra["kernel"]``
    names the kernel that ran."""
    scen, grids = scenario or DPScenario(), FormulationGrids.coerce(grids).of("thermal")
    t0 = time.perf_counter()
    b = build_problem(params, scen, grids, 2, heater=heater, warm=warm, soc=soc)
    with _threads(threads):
        res = _solve(b, engine, progress)
    _check_drivable("thermal", b, res)
    mp_used = b.mp
    e, pbm, q = b.controls(res.u[:, 0], res.u[:, 1], res.u[:, 2])
    sim = resimulate(mp_used if warm else params, b.cyc, e, pbm, q, scen, "Thermal-DP")
    out = _outcome("thermal", params, b, res, scen, grids, sim, t0)
    out.extra["engine"] = engine
    out.extra["kernel"] = res.kernel
    return out


def solve_thermal_cabin(params, scenario: DPScenario | None = None, grids=None, *,
                        engine: str = "fused", threads: int | None = None,
                        interp: str = CABIN_INTERP, cabin: str = CABIN_STATE,
                        soc: str = SOC_STATE, hold: bool | None = None, progress=None) -> DPOutcome:
    """Thermal-Cabin-DP (SOC, T_cl, T_cab; Q_heat a control). ``engine``: "fused" (default; separable where
    it applies), "fused-exact" or "generic" (:func:`solve_thermal`).
    ``interp``: how both passes interpolate the cost-to-go along the cabin axis
    (:class:`optimize.dp.engine.DPProblem`; default :data:`CABIN_INTERP`); ``cabin``: the cabin state's
    coordinate (:func:`build_problem`; default :data:`CABIN_STATE`); ``soc``: the SOC state's coordinate
    (:func:`build_problem`; default :data:`SOC_STATE`); ``hold``: offer the "hold the bound" heater control
    besides the grid (:func:`build_problem`; default: with ``cabin="bound"``). ``.dp.u[:, 2]`` is the heat
    each step delivered where the hold control was chosen."""
    scen, grids = scenario or DPScenario(), FormulationGrids.coerce(grids).of("thermal_cabin")
    t0 = time.perf_counter()
    b = build_problem(params, scen, grids, 3, interp=interp, cabin=cabin, soc=soc, hold=hold)
    with _threads(threads):
        res = _solve(b, engine, progress)
    _check_drivable("thermal_cabin", b, res)
    held = np.zeros(b.prob.N, bool)
    if b.extra["heater_hold"] and res.steps_completed == b.prob.N:
        # the hold control's heat depends on the state: replay the heat the forward pass applied
        held = np.isnan(res.u[:, 2])
        q = delivered_heat(b.prob.params, res.x, np.ascontiguousarray(res.u), b.prob.w)
        res.u[held, 2] = q[held]
    sim = resimulate(params, b.cyc, *b.controls(res.u[:, 0], res.u[:, 1], res.u[:, 2]), scen, "Thermal-Cabin-DP")
    out = _outcome("thermal_cabin", params, b, res, scen, grids, sim, t0)
    out.extra["engine"] = engine
    out.extra["kernel"] = res.kernel
    out.extra["interp"] = b.prob.interp
    out.extra["heater_hold_pct"] = 100.0 * float(held.mean())
    out.extra["grid_artefacts"] = trajectory_checks(out)
    return out


def estimate_problem(name: str, params, scenario=None, grids=None) -> dict:
    """The size of a formulation's problem before it is solved: ``{"states", "controls", "pairs_per_step",
    "steps", "evaluations"}``, built as the solver builds it (the same grids and state coordinates) but not
    solved. Raises :class:`ScenarioError` with the figures when it exceeds the budgets
    (:func:`check_problem_size`)."""
    nx = {"baseline": 1, "thermal": 2, "thermal_cabin": 3}.get(name)
    if nx is None:
        raise ScenarioError(f"unknown formulation {name!r}; choose from baseline, thermal, thermal_cabin")
    scen = scenario or DPScenario()
    b = build_problem(params, scen, FormulationGrids.coerce(grids).of(name), nx, warm=nx == 1)
    est = check_problem_size([g.size for g in b.prob.grids], b.prob.controls.shape[0], b.prob.N,
                             table_cells=int(b.prob.params[SLOT["array:big"] + 1]))
    est.update(steps=int(b.prob.N), evaluations=est["pairs_per_step"] * b.prob.N)
    return est


def solve_formulation(name: str, params, scenario=None, grids=None, **kw) -> DPOutcome:
    """Solve the formulation called ``name`` (``baseline``, ``thermal`` or ``thermal_cabin``)."""
    fn = {"baseline": solve_baseline, "thermal": solve_thermal, "thermal_cabin": solve_thermal_cabin}
    if name not in fn:
        raise ScenarioError(f"unknown formulation {name!r}; choose from {', '.join(fn)}")
    return fn[name](params, scenario, grids, **kw)
