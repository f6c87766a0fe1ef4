"""The three DP formulations of the paper (spec/optimization.md s.1-2) on the generic engine.

``solve_baseline``, ``solve_thermal`` and ``solve_thermal_cabin`` take any parameter set (the default
2017 Prius, or a calibration artifact loaded with :meth:`calib.params.ParameterSet.load`), a
:class:`DPScenario` (TOML-friendly: plain fields) and a :class:`DPGrids` (default: the paper's Table II).
Each returns a :class:`DPOutcome` whose ``sim`` is a :class:`calib.simulate.SimResult` obtained by
re-simulating the forward pass's controls through :func:`calib.model.step` from the true initial state, so
fuel, final states, starts, idle time, energy balance and corrected fuel come from ``.summary()`` exactly
as for the rule-based controller.

Formulations
    * **Baseline-DP**: state SOC; controls e_mode in {off, idle, on} and, when on, ``P_bat`` on the grid
      ``P_bat_min : dP : P_bat_max`` (the battery-terminal power, ``P_bat_mg = P_bat - P_aux``); off and
      idle have one control each (``P_bat_mg`` set by the demand). Stage cost: the warm fuel rate
      (model parameters with ``f_cl = 1``). Its own optimum is simulated with ``f_cl = 1``
      (``outcome.sim``); its control sequence (e_mode, P_bat_mg) re-simulated on the full thermal model
      with the scenario's heater demand is ``outcome.on_thermal`` ("Baseline-DP on the thermal model").
    * **Thermal-DP**: states SOC, T_cl; same controls; ``Q_heat`` is the scenario's demand (1500 W)
      delivered up to the heater-core limit :func:`calib.model.heater_limit`. The heater limit needs the
      cabin temperature, which is not a state here: the 1500-W reference cabin trajectory (below) is used
      as an exogenous input (the limit only binds below about 25 degC coolant at -10 degC ambient; the
      re-simulation uses the true cabin state).
    * **Thermal-Cabin-DP**: states SOC, T_cl, T_cab; controls as above times ``Q_heat_cmd`` on
      ``Q_min : dQ : Q_max``; delivered heat ``min(Q_cmd, heater_limit(T_cl, T_cab, ...))``. Cabin
      constraint ``T_cab_k >= T_cab^LB(k)`` (default: the 1500-W reference trajectory minus
      ``cab_lb_offset`` = 1 degC) and ``T_cab <= T_cab_ub`` (default 22 degC); terminal
      ``T_cab_N >=`` the reference's final value. The T_cab grid is ``floor(min LB) : dT : T_cab_ub``.

Reference cabin trajectory: the cabin under a constant 1500-W demand (``DPScenario.Q_heat``), heater
limited by the coolant of the same drive under the (untuned) rule-based controller: one 12-ms simulation.

Common choices
    * Integrator: the model's explicit Euler step (Ts of the cycle, 1 s by default).
    * Terminal set ``SOC_N >= SOC_0`` by the engine's level-set boundary method (Elbert 2013), with
      ``level_tol`` = :data:`LEVEL_TOL` = 1e-3 grid steps (1e-5 in SOC). A tolerance of 0 does not work:
      under multilinear interpolation the level of a node below SOC_0 decays geometrically (each step
      moves a fraction of a cell) but never reaches exactly 0, so the forward pass would never let SOC
      drop below the SOC_0 node and the battery would not be used as a buffer.
    * Thermal-Cabin terminal condition ``T_cab_N >= T_cab,1500W(N)``: a terminal cost of
      ``DPScenario.cab_terminal_g_per_K`` (default 10 g/K, 3.5 times the fuel equivalent of cabin heat used
      by the corrected fuel, 2.8 g/K, so ending colder never pays) per degC below it, not a level set.
      Why: the cabin moves ~0.005 degC per step on the paper's 1-degC grid, so under multilinear
      interpolation a level (or a steep penalty) at the terminal kink decays only ~0.5 % per step
      backwards and forbids any excursion below the terminal value. Even with this soft cost, the
      kink's interpolation diffusion makes an excursion look more expensive than it is on the 1-degC
      grid: on the paper grid Thermal-Cabin-DP keeps 1500 W; a finer cabin grid (``tcab=0.1``) lets it
      shift heat, at a small gain in this warm-coolant scenario.
    * Speed: :func:`build_tables` computes once, for every step and power control, feasibility, engine
      power, warm fuel rate, battery power and the next SOC at every SOC node (the battery square root
      leaves the inner loop); the engine's ``precompute`` hook copies step k's slice into ``tab``.
      ``f_cl``, engine-bay loss and radiator heat are tabulated per T_cl node. In the backward pass the
      transition uses the grid indices ``ix``; in the forward pass (``ix = -1``) it evaluates the same
      equations at the true state.
    * Parameters reach the compiled code as one flat float64 vector (:func:`pack_params`): the engine's
      parallel kernel cannot take the ``ModelParams`` namedtuple (numba's parfor lowering rejects a struct
      holding arrays: "scalar type ModelParams given for non scalar argument").
    * One compiled transition (:func:`hev_transition`) serves all three formulations (the state count is
      read from the parameters), so the engine's kernels compile once.
    * Thermal-DP and Thermal-Cabin-DP use fused backward kernels (:mod:`optimize._fused`) by default and
      the engine's forward pass; they give the same value functions and trajectory as the generic engine
      (``engine="generic"``), cross-checked in ``tests/test_formulations.py``.
    * State constraints (SOC, T_cl and T_cab boxes, the cabin lower-bound trajectory) are a documented
      penalty, :data:`PENALTY_G_PER_STEP` g of fuel per grid step of violation, with the engine's
      ``clip=True`` lookup, not +inf: with +inf, a grid node that cannot avoid leaving the box (e.g. SOC
      0.8 while braking: the motor must regenerate) poisons its neighbours through interpolation, one cell
      per event, until after ~40 braking events no SOC node is finite (the level-set method of the engine
      covers terminal sets only). Re-simulated results are checked to stay inside the boxes.
"""
from __future__ import annotations

import math
import os
import resource
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace

# numba's OpenMP threading layer spins actively at every barrier; the DP kernels hit one or two barriers per
# time step, and on a shared (over-subscribed) 2-core machine the spinning made the 2-thread Thermal-DP
# backward pass 10x slower than 1 thread (5-12 s vs 0.65 s). Passive waiting removes that. It must be set
# before the OpenMP runtime starts (the first parallel kernel call); an explicit user setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from calib.cycles import Cycle, load_cycle
from calib.errors import ScenarioError
from calib.model import IDLE, OFF, ON, battery_ocv_r, f_cold, fuel_map, power_split, radiator, \
    traction_power

from .dp import DPProblem, DPResult, backward_pass, forward_pass

__all__ = ["DPScenario", "DPGrids", "DPOutcome", "parse_grid_spec", "solve_baseline", "solve_thermal",
           "solve_thermal_cabin", "solve_formulation", "FORMULATIONS", "replay", "peak_rss_mb"]

FORMULATIONS = ("baseline", "thermal", "thermal_cabin")


# ---------------------------------------------------------------------------------------------------
# scenario and grids
# ---------------------------------------------------------------------------------------------------
@dataclass
class DPScenario:
    """A DP scenario (spec/optimization.md s.4 defaults). Plain fields: read/written as TOML/JSON.

    cycle: bundled cycle name or CSV path; ``duration_s`` truncates it (None: whole cycle).
    cab_lb_offset: the cabin lower bound is the 1500-W reference trajectory minus this (degC).
    soc_tol: tolerance of the charge-sustaining check on re-simulated results (``SOC_N >= SOC_0 - soc_tol``).
    """

    cycle: str = "artemis_urban"
    T_amb: float = -10.0
    soc0: float = 0.6
    T_cl0: float = 70.0
    T_cab0: float = 20.0
    Q_heat: float = 1500.0
    Q_heat_min: float = 1200.0
    Q_heat_max: float = 1800.0
    soc_min: float = 0.4
    soc_max: float = 0.8
    T_cl_min: float = 0.0
    T_cl_max: float = 100.0
    cab_lb_offset: float = 1.0
    T_cab_ub: float = 22.0
    duration_s: float | None = None
    soc_tol: float = 1e-3
    cab_terminal_g_per_K: float = 10.0

    @classmethod
    def from_dict(cls, d: dict) -> "DPScenario":
        names = {f.name for f in fields(cls)}
        bad = set(d) - names
        if bad:
            raise ScenarioError(f"unknown scenario field(s) {sorted(bad)}; known: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    def load_cycle(self, cycle=None) -> Cycle:
        cyc = load_cycle(self.cycle if cycle is None else cycle)
        if self.duration_s is not None:
            n = int(round(self.duration_s / cyc.Ts))
            if n < 1:
                raise ScenarioError("duration_s must be at least one step")
            n = min(n, cyc.n_steps)
            cyc = Cycle(f"{cyc.name}[0:{n * cyc.Ts:g}s]", cyc.t[: n + 1].copy(), cyc.v[: n + 1].copy(),
                        None if cyc.grade is None else cyc.grade[: n + 1].copy())
        return cyc


@dataclass
class DPGrids:
    """Grid steps (paper Table II): SOC (-), T_cl (degC), T_cab (degC), P_bat (W), Q_heat (W)."""

    soc: float = 0.01
    tcl: float = 1.0
    tcab: float = 1.0
    pbat: float = 500.0
    qheat: float = 50.0

    def halved(self) -> "DPGrids":
        return DPGrids(*(v / 2 for v in asdict(self).values()))

    def to_dict(self) -> dict:
        return asdict(self)


def parse_grid_spec(spec: str | None, base: DPGrids | None = None) -> DPGrids:
    """``"soc=0.01,tcl=1,tcab=1,pbat=500,qheat=50"`` (any subset) -> :class:`DPGrids`."""
    g = base or DPGrids()
    if not spec:
        return g
    vals = {}
    for part in spec.split(","):
        if not part.strip():
            continue
        if "=" not in part:
            raise ScenarioError(f"grid spec {part!r}: expected name=step")
        k, v = (s.strip() for s in part.split("=", 1))
        if k not in DPGrids.__dataclass_fields__:
            raise ScenarioError(f"grid spec: unknown grid {k!r}; known: soc, tcl, tcab, pbat, qheat")
        try:
            x = float(v)
        except ValueError:
            raise ScenarioError(f"grid spec: {k}={v!r} is not a number") from None
        if not x > 0:
            raise ScenarioError(f"grid spec: {k} step must be positive")
        vals[k] = x
    return replace(g, **vals)


def _grid(lo, hi, step):
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    if n < 2:
        raise ScenarioError(f"grid {lo}:{step}:{hi} has fewer than two points")
    return lo + step * np.arange(n)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB; ru_maxrss, process-wide peak)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# ---------------------------------------------------------------------------------------------------
# compiled transition
# ---------------------------------------------------------------------------------------------------
# cfg layout (float64 array in the params tuple)
_C_NX, _C_NQ, _C_TAMB, _C_TS, _C_TBAT, _C_WBL = 0, 1, 2, 3, 4, 5
_C_SLO, _C_SHI, _C_SH, _C_TLO, _C_THI, _C_TH, _C_CHI, _C_CH, _C_PEN = 6, 7, 8, 9, 10, 11, 12, 13, 14

# array descriptors (offset, length) in the flat parameter vector, then the model scalars
_A_SOCG, _A_FCLG, _A_LOSSG, _A_SOCBP, _A_UOC, _A_SOCBPR, _A_RINT, _A_TFCL, _A_FCL, _A_BIG = range(16, 36, 2)
_MS0 = 40
_HEADER = 64

#: Penalty (g of fuel) per grid step of state-constraint violation (see :func:`hev_transition`), also the
#: Thermal-Cabin terminal cost per grid step below the 1500-W final cabin temperature.
PENALTY_G_PER_STEP = 1000.0
#: Level-set tolerance (grid steps): levels at or below it count as "terminal set reachable".
LEVEL_TOL = 1e-3
# model scalars (float64 array): the generic engine's parallel kernel cannot take the ModelParams namedtuple
# (numba's parfor gufunc rejects a struct holding arrays), so the transition gets plain arrays.
_MS = ("R_tc", "T_bat_ref", "C_bat_As", "kappa", "hA_eng", "T_open", "k_rad", "Q_rad_max", "eps_hc", "cp_air",
       "recirc", "LHV", "gamma_exh", "C_eng", "UA_cab", "C_cab", "Q_sun")
(_R_TC, _TBREF, _CBAT, _KAPPA, _HA, _TOPEN, _KRAD, _QRADMAX, _EPS, _CP, _RECIRC, _LHV, _GAMMA, _CENG, _UACAB,
 _CCAB, _QSUN) = range(len(_MS))
# tab columns per power control
_T_OK, _T_PE, _T_WF, _T_PBAT, _T_SOC0 = 0, 1, 2, 3, 4


@njit(cache=True)
def build_tables(mp, pc, socg, P_trac, Ts, T_bat):  # pragma: no cover - compiled
    """(N, n_p, 4 + n_soc): per step and power control: feasible, P_e, warm fuel (g/s), P_bat and the
    next SOC at every SOC node (NaN: infeasible). Uses the model functions of :mod:`calib.model`."""
    N = P_trac.shape[0]
    nsoc = socg.shape[0]
    out = np.empty((N, pc.shape[0], _T_SOC0 + nsoc))
    Us = np.empty(nsoc)
    Rs = np.empty(nsoc)
    for i in range(nsoc):
        Us[i], Rs[i] = battery_ocv_r(mp, socg[i], T_bat)
    for k in range(N):
        for ip in range(pc.shape[0]):
            e = int(pc[ip, 0])
            P_e, Pbm, P_em, P_brake, ok = power_split(mp, e, pc[ip, 1], P_trac[k])
            P_bat = Pbm + mp.P_aux
            if P_bat < mp.P_bat_min or P_bat > mp.P_bat_max:
                ok = False
            out[k, ip, _T_OK] = 1.0 if ok else 0.0
            out[k, ip, _T_PE] = P_e
            if e == OFF:
                wf = 0.0
            elif e == IDLE:
                wf = mp.W_idle
            else:
                wf = fuel_map(mp, P_e)
            out[k, ip, _T_WF] = wf
            out[k, ip, _T_PBAT] = P_bat
            for i in range(nsoc):
                sn = np.nan
                if ok:
                    # calib.model.battery's current, with U_oc and R_int of the node precomputed
                    disc = Us[i] * Us[i] - 4.0 * Rs[i] * P_bat
                    if disc >= 0.0:
                        I = 2.0 * P_bat / (Us[i] + math.sqrt(disc))
                        sn = socg[i] - I * Ts / mp.C_bat_As
                out[k, ip, _T_SOC0 + i] = sn
    return out


@njit(inline="always", cache=True)
def _arr(p, a):
    o = int(p[a])
    return p[o: o + int(p[a + 1])]


def pack_params(cfg, ms, arrays) -> np.ndarray:
    """One flat float64 vector: header (cfg, descriptors, model scalars) then the arrays.

    A flat array (rather than a tuple holding the ModelParams namedtuple) because numba's parallel
    backward kernel rejects a struct with arrays as a prange argument, and because a tuple of arrays
    costs reference-count traffic on every transition call."""
    n = _HEADER + sum(a.size for a in arrays)
    P = np.zeros(n)
    P[: cfg.size] = cfg
    P[_MS0: _MS0 + ms.size] = ms
    o = _HEADER
    for j, a in enumerate(arrays):
        P[16 + 2 * j] = o
        P[17 + 2 * j] = a.size
        P[o: o + a.size] = a.ravel()
        o += a.size
    return P


@njit(cache=True)
def hev_precompute(k, w_k, p, tab):  # pragma: no cover - compiled
    """Per step: copy step k's slice of the per-step per-control table."""
    o = int(p[_A_BIG])
    n0 = tab.shape[0]
    n1 = tab.shape[1]
    o += k * n0 * n1
    for i in range(n0):
        for j in range(n1):
            tab[i, j] = p[o + i * n1 + j]


@njit(inline="always", cache=True)
def _soc_next(p, soc, P_bat, Ts):
    """Off-grid SOC step (forward pass): calib.model.battery with the tables of p; NaN if no real root."""
    U = np.interp(soc, _arr(p, _A_SOCBP), _arr(p, _A_UOC))
    R = np.interp(soc, _arr(p, _A_SOCBPR), _arr(p, _A_RINT)) * math.exp(-p[_MS0 + _R_TC] * (p[_C_TBAT] - p[_MS0 + _TBREF]))
    disc = U * U - 4.0 * R * P_bat
    if disc < 0.0:
        return np.nan
    I = 2.0 * P_bat / (U + math.sqrt(disc))
    return soc - I * Ts / p[_MS0 + _CBAT]


@njit(cache=True)
def hev_transition(k, x, u, w_k, p, tab, iu, ix, x_next):  # pragma: no cover - compiled
    """x = (soc[, T_cl[, T_cab]]), u = (e_mode, P_bat_mg, Q_heat_cmd); w_k = (P_trac, T_cab_ref_k, T_cab_LB_k+1).

    Returns the fuel (g) of the step, inf if infeasible. Same equations as :func:`calib.model.step`."""
    nq = int(p[_C_NQ])
    ip = iu // nq
    if tab[ip, _T_OK] == 0.0:
        return np.inf
    Ts = p[_C_TS]
    soc = x[0]
    if ix[0] >= 0:
        sn = tab[ip, _T_SOC0 + ix[0]]
    else:
        sn = _soc_next(p, soc, tab[ip, _T_PBAT], Ts)
    if not (sn == sn):
        return np.inf
    x_next[0] = sn
    pen = 0.0
    if sn < p[_C_SLO]:
        pen += (p[_C_SLO] - sn) / p[_C_SH]
    elif sn > p[_C_SHI]:
        pen += (sn - p[_C_SHI]) / p[_C_SH]
    nx = int(p[_C_NX])
    wf = tab[ip, _T_WF]
    if nx == 1:
        return wf * Ts + p[_C_PEN] * pen
    T_cl = x[1]
    T_amb = p[_C_TAMB]
    if ix[1] >= 0:
        fcl = p[int(p[_A_FCLG]) + ix[1]]
        loss = p[int(p[_A_LOSSG]) + ix[1]]
    else:
        fcl = np.interp(T_cl, _arr(p, _A_TFCL), _arr(p, _A_FCL))
        T_com = T_amb + p[_MS0 + _KAPPA] * (T_cl - T_amb)
        q_rad = 0.0
        if T_cl > p[_MS0 + _TOPEN]:
            q_rad = p[_MS0 + _KRAD] * (T_cl - p[_MS0 + _TOPEN])
            if q_rad > p[_MS0 + _QRADMAX]:
                q_rad = p[_MS0 + _QRADMAX]
        loss = p[_MS0 + _HA] * (T_cl - T_com) + q_rad
    W_f = wf * fcl
    if nx == 3:
        T_cab = x[2]
    else:
        T_cab = w_k[1]
    T_in = p[_MS0 + _RECIRC] * T_cab + (1.0 - p[_MS0 + _RECIRC]) * T_amb
    q_lim = p[_MS0 + _EPS] * p[_C_WBL] * p[_MS0 + _CP] * (T_cl - T_in)
    q = u[2]
    if q > q_lim:
        q = q_lim
    if q < 0.0:
        q = 0.0
    Q_fuel = p[_MS0 + _LHV] * W_f
    P_e = tab[ip, _T_PE]
    Q_exh = p[_MS0 + _GAMMA] * (Q_fuel - P_e)
    tn = T_cl + Ts * (Q_fuel - P_e - Q_exh - loss - q) / p[_MS0 + _CENG]
    x_next[1] = tn
    if tn < p[_C_TLO]:
        pen += (p[_C_TLO] - tn) / p[_C_TH]
    elif tn > p[_C_THI]:
        pen += (tn - p[_C_THI]) / p[_C_TH]
    if nx == 3:
        tc = T_cab + Ts * (q + p[_MS0 + _UACAB] * (T_amb - T_cab) + p[_MS0 + _QSUN]) / p[_MS0 + _CCAB]
        x_next[2] = tc
        if tc < w_k[2]:
            pen += (w_k[2] - tc) / p[_C_CH]
        elif tc > p[_C_CHI]:
            pen += (tc - p[_C_CHI]) / p[_C_CH]
    return W_f * Ts + p[_C_PEN] * pen


# ---------------------------------------------------------------------------------------------------
# outcome
# ---------------------------------------------------------------------------------------------------
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

    @property
    def evals_per_second(self) -> float:
        return self.n_evaluations / self.t_backward if self.t_backward > 0 else float("nan")

    @property
    def fuel_g(self) -> float:
        return self.sim.fuel_g

    def charge_sustaining(self, soc_tol: float | None = None) -> bool:
        tol = self.scenario.get("soc_tol", 1e-3) if soc_tol is None else soc_tol
        ok = self.sim.soc[-1] >= self.sim.soc[0] - tol
        if self.on_thermal is not None:
            ok = ok and self.on_thermal.soc[-1] >= self.on_thermal.soc[0] - tol
        return bool(ok)

    def describe(self) -> dict:
        return {"formulation": self.formulation, "fuel_g": self.sim.fuel_g, "dp_cost_g": self.dp_cost,
                "predicted_cost_g": self.predicted_cost, "feasible": bool(self.dp.feasible),
                "t_backward_s": self.t_backward, "t_forward_s": self.t_forward, "t_total_s": self.t_total,
                "n_evaluations": self.n_evaluations, "evals_per_second": self.evals_per_second,
                "n_states": self.n_states, "n_controls": self.n_controls, "peak_rss_mb": self.peak_rss_mb,
                "grids": self.grids, **self.extra}


class _Replay:
    """Open-loop controller replaying a control sequence (for :func:`calib.simulate.simulate`)."""

    def __init__(self, e_mode, P_bat_mg, Q_cmd, name):
        self.e, self.p, self.q, self.name = e_mode, P_bat_mg, Q_cmd, name

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        return int(self.e[k]), float(self.p[k]), float(self.q[k])

    def describe(self):
        return self.name


def replay(params, cycle, e_mode, P_bat_mg, Q_cmd, scen: DPScenario, name: str):
    """Re-simulate a control sequence through :func:`calib.model.step` from the scenario's initial state."""
    from calib.simulate import simulate

    return simulate(params, cycle, _Replay(e_mode, P_bat_mg, Q_cmd, name), T_amb=scen.T_amb, soc0=scen.soc0,
                    T_cl0=scen.T_cl0, T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)


# ---------------------------------------------------------------------------------------------------
# problem assembly
# ---------------------------------------------------------------------------------------------------
def _mp(params):
    return params.model_params() if hasattr(params, "model_params") else params


def reference_cabin(params, cycle: Cycle, scen: DPScenario) -> np.ndarray:
    """Cabin trajectory (N+1,) under a constant ``Q_heat`` demand (heater-limited; rule-based coolant)."""
    from calib.simulate import simulate

    res = simulate(params, cycle, T_amb=scen.T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0, T_cab0=scen.T_cab0,
                   Q_heat=scen.Q_heat)
    return res.T_cab.copy()


def _power_controls(mp, grids: DPGrids) -> np.ndarray:
    P_bat = _grid(mp.P_bat_min, mp.P_bat_max, grids.pbat)
    rows = [(OFF, 0.0), (IDLE, 0.0)] + [(ON, pb - mp.P_aux) for pb in P_bat]
    return np.array(rows, dtype=np.float64)


def _traction(mp, cyc: Cycle) -> np.ndarray:
    N, Ts = cyc.n_steps, cyc.Ts
    grade = cyc.grade if cyc.grade is not None else np.zeros(N + 1)
    return np.array([traction_power(mp, cyc.v[k], cyc.v[k + 1], grade[k], Ts) for k in range(N)])


def _t_cl_tables(mp, tclg, T_amb):
    fcl = np.array([f_cold(mp, t) for t in tclg])
    T_com = T_amb + mp.kappa * (tclg - T_amb)
    loss = mp.hA_eng * (tclg - T_com) + np.array([radiator(mp, t) for t in tclg])
    return fcl, loss


@dataclass
class _Built:
    prob: DPProblem
    x0: np.ndarray
    cyc: Cycle
    extra: dict
    mp: object = None


def build_problem(params, scen: DPScenario, grids: DPGrids, nx: int, *, heater: float | None = None,
                  warm: bool = False, cycle=None) -> _Built:
    """Assemble the :class:`DPProblem` of a formulation with ``nx`` states (1, 2 or 3)."""
    mp = _mp(params)
    if warm:
        mp = mp._replace(f_cl=np.ones_like(mp.f_cl))
    cyc = scen.load_cycle(cycle)
    N, Ts = cyc.n_steps, cyc.Ts
    if not (scen.soc_min <= scen.soc0 <= scen.soc_max):
        raise ScenarioError(f"soc0 {scen.soc0} outside the SOC grid [{scen.soc_min}, {scen.soc_max}]")
    socg = _grid(scen.soc_min, scen.soc_max, grids.soc)
    tclg = _grid(scen.T_cl_min, scen.T_cl_max, grids.tcl)
    fclg, lossg = _t_cl_tables(mp, tclg, scen.T_amb)
    pc = _power_controls(mp, grids)
    P_trac = _traction(mp, cyc)
    extra = {}
    w = np.zeros((N, 3))
    w[:, 0] = P_trac
    terminal = None
    grid_list = [socg]
    bounds = [(scen.soc0, None)]
    x0 = [scen.soc0]
    if nx >= 2:
        if not (scen.T_cl_min <= scen.T_cl0 <= scen.T_cl_max):
            raise ScenarioError(f"T_cl0 {scen.T_cl0} outside the coolant grid")
        grid_list.append(tclg)
        bounds.append((None, None))
        x0.append(scen.T_cl0)
    if nx >= 2:
        ref = reference_cabin(params, cyc, scen)
        w[:, 1] = ref[:-1]
        extra["T_cab_ref_final"] = float(ref[-1])
        extra["T_cab_ref_mean"] = float(np.mean(ref))
    if nx == 3:
        lb = ref - scen.cab_lb_offset
        lb[0] = min(lb[0], scen.T_cab0)
        w[:, 2] = lb[1:]
        lo = math.floor(float(np.min(lb)) + 1e-9)
        hi = max(scen.T_cab_ub, float(ref[-1]), scen.T_cab0)
        if hi - lo < grids.tcab:
            hi = lo + grids.tcab
        tcabg = _grid(lo, hi, grids.tcab)
        if tcabg[-1] < hi - 1e-9:
            tcabg = np.append(tcabg, tcabg[-1] + grids.tcab)
        grid_list.append(tcabg)
        bounds.append((None, None))
        T_term = float(ref[-1])
        h_cab = float(tcabg[1] - tcabg[0])
        rate = float(scen.cab_terminal_g_per_K)
        terminal = lambda X: rate * np.maximum(T_term - X[:, 2], 0.0)  # noqa: E731
        x0.append(scen.T_cab0)
        Q = _grid(scen.Q_heat_min, scen.Q_heat_max, grids.qheat)
        extra.update(T_cab_lb_min=float(np.min(lb)), T_cab_ub=float(tcabg[-1]),
                     T_cab_terminal_min=float(ref[-1]))
    else:
        Q = np.array([scen.Q_heat if heater is None else heater])
    nq = Q.size
    controls = np.column_stack([np.repeat(pc, nq, axis=0), np.tile(Q, pc.shape[0])])
    cfg = np.zeros(16)
    cfg[_C_SLO], cfg[_C_SHI], cfg[_C_SH] = socg[0], socg[-1], socg[1] - socg[0]
    cfg[_C_TLO], cfg[_C_THI], cfg[_C_TH] = tclg[0], tclg[-1], tclg[1] - tclg[0]
    if nx == 3:
        cfg[_C_CHI], cfg[_C_CH] = scen.T_cab_ub, grids.tcab
    cfg[_C_PEN] = PENALTY_G_PER_STEP
    cfg[_C_NX], cfg[_C_NQ], cfg[_C_TAMB], cfg[_C_TS] = nx, nq, scen.T_amb, Ts
    cfg[_C_TBAT], cfg[_C_WBL] = mp.T_bat_ref, mp.W_bl
    ms = np.array([float(getattr(mp, n)) for n in _MS])
    big = build_tables(mp, pc, socg, P_trac, float(Ts), float(mp.T_bat_ref))
    c = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    p = pack_params(cfg, ms, [socg, fclg, lossg, c(mp.soc_bp), c(mp.U_oc), c(mp.soc_bp_R), c(mp.R_int),
                              c(mp.T_fcl), c(mp.f_cl), big])
    prob = DPProblem(grids=grid_list, controls=controls, N=N, transition=hev_transition, w=w, params=p,
                     terminal_bounds=bounds, terminal_cost=terminal, boundary="levelset", clip=True,
                     level_tol=LEVEL_TOL, precompute=hev_precompute,
                     table_shape=(pc.shape[0], _T_SOC0 + socg.size))
    return _Built(prob, np.array(x0), cyc, extra, mp)


def _solve(b: _Built, engine: str):
    if engine == "fused" and b.prob.n_x >= 2:
        from ._fused import backward_pass_fused

        vf = backward_pass_fused(b.prob)
    else:
        vf = backward_pass(b.prob)
    res = forward_pass(b.prob, vf, b.x0)
    return res


def _outcome(name, params, b, res, scen, grids, sim, t0, on_thermal=None):
    if not res.feasible:
        raise ScenarioError(f"{name}: no feasible charge-sustaining solution on these grids (steps completed "
                            f"{res.steps_completed}/{b.prob.N}, terminal level {res.terminal_level:.3g})")
    return DPOutcome(formulation=name, sim=sim, dp=res, dp_cost=float(res.cost),
                     predicted_cost=float(res.predicted_cost[0]), t_backward=res.t_backward,
                     t_forward=res.t_forward, t_total=time.perf_counter() - t0,
                     n_evaluations=int(res.n_evaluations), n_states=b.prob.n_states,
                     n_controls=b.prob.n_controls, peak_rss_mb=peak_rss_mb(), grids=grids.to_dict(),
                     scenario=scen.to_dict(), on_thermal=on_thermal, extra=b.extra)


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


def solve_baseline(params, scenario: DPScenario | None = None, grids: DPGrids | None = None, *,
                   threads: int | None = 1) -> DPOutcome:
    """Baseline-DP (SOC only, f_cl = 1). ``.sim``: its own optimum (f_cl = 1); ``.on_thermal``: its
    controls re-simulated on the full thermal model with the scenario's heater demand.

    Solved by the generic engine on one thread by default: 41 states per step are too few to pay for a
    parallel region per step."""
    scen, grids = scenario or DPScenario(), grids or DPGrids()
    t0 = time.perf_counter()
    b = build_problem(params, scen, grids, 1, warm=True)
    with _threads(threads):
        res = _solve(b, "generic")
    mp_warm = b.mp
    e, pbm = res.u[:, 0], res.u[:, 1]
    q = np.full(b.prob.N, scen.Q_heat)
    sim = replay(mp_warm, b.cyc, e, pbm, q, scen, "Baseline-DP (f_cl = 1)")
    sim.info["params"] = params.meta.get("name", "") if hasattr(params, "meta") else ""
    on = replay(params, b.cyc, e, pbm, q, scen, "Baseline-DP policy on the thermal model")
    return _outcome("baseline", params, b, res, scen, grids, sim, t0, on_thermal=on)


def solve_thermal(params, scenario: DPScenario | None = None, grids: DPGrids | None = None, *,
                  heater: float | None = None, warm: bool = False, engine: str = "fused",
                  threads: int | None = None) -> DPOutcome:
    """Thermal-DP (SOC, T_cl). ``heater`` overrides the scenario's demand (e.g. 0 W); ``warm=True``
    sets f_cl = 1 (with heater 0 W it must reproduce Baseline-DP)."""
    scen, grids = scenario or DPScenario(), grids or DPGrids()
    t0 = time.perf_counter()
    b = build_problem(params, scen, grids, 2, heater=heater, warm=warm)
    with _threads(threads):
        res = _solve(b, engine)
    mp_used = b.mp
    q = res.u[:, 2]
    sim = replay(mp_used if warm else params, b.cyc, res.u[:, 0], res.u[:, 1], q, scen, "Thermal-DP")
    out = _outcome("thermal", params, b, res, scen, grids, sim, t0)
    out.extra["engine"] = engine
    return out


def solve_thermal_cabin(params, scenario: DPScenario | None = None, grids: DPGrids | None = None, *,
                        engine: str = "fused", threads: int | None = None) -> DPOutcome:
    """Thermal-Cabin-DP (SOC, T_cl, T_cab; Q_heat a control). ``engine``: "fused" (default) or "generic"."""
    scen, grids = scenario or DPScenario(), grids or DPGrids()
    t0 = time.perf_counter()
    b = build_problem(params, scen, grids, 3)
    with _threads(threads):
        res = _solve(b, engine)
    sim = replay(params, b.cyc, res.u[:, 0], res.u[:, 1], res.u[:, 2], scen, "Thermal-Cabin-DP")
    out = _outcome("thermal_cabin", params, b, res, scen, grids, sim, t0)
    out.extra["engine"] = engine
    return out


def solve_formulation(name: str, params, scenario=None, grids=None, **kw) -> DPOutcome:
    fn = {"baseline": solve_baseline, "thermal": solve_thermal, "thermal_cabin": solve_thermal_cabin}
    if name not in fn:
        raise ScenarioError(f"unknown formulation {name!r}; choose from {', '.join(fn)}")
    return fn[name](params, scenario, grids, **kw)
