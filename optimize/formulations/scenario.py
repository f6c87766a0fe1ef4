"""DP scenario (drive, ambient, initial state, heater demand) and grids (each formulation's converged grid by
default; the paper's Table II on request)."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np

from calib.errors import ScenarioError
from calib.model.continuation import CONTINUATION_CYCLE
from calib.model.cycles import Cycle, load_cycle

FORMULATIONS = ("baseline", "thermal", "thermal_cabin")
#: Terminal conditions on the thermal states (``DPScenario.terminal``).
TERMINALS = ("free", "match", "valued", "continued")


#: Physical ranges of the scenario's numbers (a car on a road on Earth, a cabin heater of a passenger car): a
#: value outside is a typo or hostile input, refused before any table is built.
_TEMPERATURE = (-60.0, 200.0, "degC")
SCENARIO_RANGES = {
    "T_amb": (-60.0, 60.0, "degC"), "T_cl0": _TEMPERATURE, "T_cab0": (-60.0, 80.0, "degC"),
    "T_cl_min": _TEMPERATURE, "T_cl_max": _TEMPERATURE, "T_cab_ub": (-60.0, 80.0, "degC"),
    "T_cl_final_min": _TEMPERATURE, "T_cab_final_min": (-60.0, 80.0, "degC"),
    "Q_heat": (0.0, 20e3, "W"), "Q_heat_min": (0.0, 20e3, "W"), "Q_heat_max": (0.0, 20e3, "W"),
    "soc0": (0.0, 1.0, ""), "soc_min": (0.0, 1.0, ""), "soc_max": (0.0, 1.0, ""), "soc_tol": (0.0, 1.0, ""),
    "cab_lb_offset": (-50.0, 50.0, "K"), "duration_s": (0.0, 7 * 86400.0, "s"),
    "cab_terminal_g_per_K": (0.0, 1e4, "g/K"), "cont_soc_band": (0.0, 1.0, ""),
    "cont_soc_every": (1, 1000, ""), "cont_tcl_step": (0.0, 100.0, "K"), "cont_tcab_step": (0.0, 100.0, "K"),
}


# ---------------------------------------------------------------------------------------------------
# scenario and grids
# ---------------------------------------------------------------------------------------------------
@dataclass
class DPScenario:
    """A DP scenario (docs/optimization.md s.4 defaults). Plain fields: read/written as TOML/JSON.

    cycle: bundled cycle name or CSV path; ``duration_s`` truncates it (None: whole cycle).
    cab_lb_offset: the cabin lower bound is the 1500-W reference trajectory minus this (degC).
    soc_tol: tolerance of the charge-sustaining check on re-simulated results (``SOC_N >= SOC_0 - soc_tol``).
    terminal: the terminal condition on coolant and cabin (every formulation but ``continued``'s keeps
    ``SOC_N >= SOC_0``):

      * ``"valued"`` (default): a terminal cost equal to minus the fuel equivalent of the heat gained in
        coolant (and cabin, where it is a state) over the drive (:func:`calib.model.simulate.fuel_equivalents_g`,
        the valuation of the corrected fuel), so with ``SOC_N`` held at ``SOC_0`` the DP minimises the
        corrected fuel of its trajectory;
      * ``"match"``: final coolant (and, with the cabin as a state, cabin) at least the rule-based run's
        (``T_cl_final_min`` / ``T_cab_final_min``; None: those of the untuned rule-based controller);
      * ``"continued"``: a terminal cost ``C(x_N) - C(x_0)``, the fuel the rule-based controller burns over a
        common continuation drive (``cont_cycle``, default UDDS six times) from the final state, less that from the initial state,
        remaining end-state differences valued by ``fuel_equivalents_g``
        (:func:`calib.model.continuation.continuation_value`); it values charge too, so Thermal-DP and
        Thermal-Cabin-DP drop ``SOC_N >= SOC_0`` for the band ``|SOC_N - SOC_0| <= cont_soc_band`` (None:
        SOC_N free; Baseline-DP keeps ``SOC_N >= SOC_0`` and has no terminal cost). C is
        computed on a sub-grid (every ``cont_soc_every``-th SOC node, coolant every ``cont_tcl_step`` K,
        cabin every ``cont_tcab_step`` K) and interpolated multilinearly;
      * ``"free"``: the paper's: final coolant free; Thermal-Cabin-DP's final cabin at least the 1500-W
        reference's, as a soft cost of ``cab_terminal_g_per_K`` per kelvin below it.
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
    terminal: str = "valued"
    T_cl_final_min: float | None = None
    T_cab_final_min: float | None = None
    cont_cycle: str = CONTINUATION_CYCLE
    cont_soc_every: int = 5
    cont_tcl_step: float = 5.0
    cont_tcab_step: float = 2.0
    cont_soc_band: float | None = None

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("cycle", "terminal", "cont_cycle"):
                if not isinstance(v, str) or not v.strip():
                    raise ScenarioError(f"scenario field {f.name} = {str(v)[:40]!r}: give a name (or a CSV file)")
                continue
            if v is None:
                continue
            ok = isinstance(v, (int, float)) and not isinstance(v, bool)
            try:
                ok = ok and math.isfinite(float(v))
            except OverflowError:
                ok = False
            if not ok:
                shown = repr(v) if isinstance(v, float) else (str(v)[:40] + ("..." if len(str(v)) > 40 else ""))
                raise ScenarioError(f"scenario field {f.name} = {shown}: give a finite number")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ScenarioError(f"scenario field duration_s = {self.duration_s!r}: give a positive number of seconds")
        for lo, hi in (("soc_min", "soc_max"), ("T_cl_min", "T_cl_max"), ("Q_heat_min", "Q_heat_max")):
            if not getattr(self, lo) < getattr(self, hi):
                raise ScenarioError(f"scenario fields {lo} = {getattr(self, lo):g} and {hi} = {getattr(self, hi):g}: "
                                    f"{lo} must be below {hi}")
        if not (0.0 <= self.soc_min and self.soc_max <= 1.0):
            raise ScenarioError(f"scenario SOC window [{self.soc_min:g}, {self.soc_max:g}] must lie inside [0, 1]")
        # the specific checks above first (their messages say more); then every number's physical range
        for name, (lo, hi, unit) in SCENARIO_RANGES.items():
            v = getattr(self, name)
            if v is not None and not lo <= v <= hi:
                raise ScenarioError(f"scenario field {name} = {v:g}: outside the physical range [{lo:g}, {hi:g}]"
                                    + (f" {unit}" if unit else ""))
        if self.terminal not in TERMINALS:
            raise ScenarioError(f"terminal {self.terminal!r}: choose one of {', '.join(TERMINALS)}")
        if self.cont_soc_band is not None and not self.cont_soc_band >= 0:
            raise ScenarioError(f"cont_soc_band {self.cont_soc_band!r}: give a SOC band >= 0 (or None: SOC_N free)")
        if not (int(self.cont_soc_every) >= 1 and self.cont_tcl_step > 0 and self.cont_tcab_step > 0):
            raise ScenarioError("cont_soc_every must be a positive integer and cont_tcl_step, cont_tcab_step "
                                "positive (K)")

    @classmethod
    def from_dict(cls, d: dict) -> "DPScenario":
        names = {f.name for f in fields(cls)}
        bad = set(d) - names
        if bad:
            import difflib

            close = {b: difflib.get_close_matches(str(b), sorted(names), 1) for b in sorted(bad)}
            hints = [f"{b!r} (did you mean {c[0]!r}?)" if c else repr(b) for b, c in close.items()]
            known = "" if all(close.values()) else f"; known: {', '.join(sorted(names))}"
            raise ScenarioError(f"unknown scenario field(s) {', '.join(hints)}{known}")
        return cls(**d)

    def to_dict(self) -> dict:
        """The scenario as a TOML/JSON-able dict."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    def load_cycle(self, cycle=None) -> Cycle:
        """The drive cycle of the scenario (bundled name or CSV), cut to ``duration_s``."""
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
        """The same grids with every step halved (for convergence checks)."""
        return DPGrids(*(v / 2 for v in asdict(self).values()))

    def to_dict(self) -> dict:
        """The grid steps as a JSON-able dict."""
        return asdict(self)


#: A Thermal-Cabin-DP grid coarser than the paper's in coolant, cabin, battery power and heater, converged on
#: the default car and drive by the halving criterion (README "A converged grid for Thermal-Cabin-DP" gives
#: the figures and the command); ``iptm bench dp`` times it.
CABIN_CONVERGED_GRIDS = DPGrids(tcl=2.0, tcab=1.5, pbat=750.0, qheat=100.0)

#: Baseline-DP's default: the paper's SOC and battery-power steps halved. On the paper's steps halving every
#: step moves its corrected fuel by -0.115 % (default car) and -0.116 % (bundled calibrated car); from these,
#: by -0.055 % and -0.062 %. 147 states x 203 controls: about 2 s per solve instead of 0.6 s.
BASELINE_CONVERGED_GRIDS = DPGrids(soc=0.005, pbat=250.0)

#: The grid steps each formulation solves on (its state and control axes; the other steps are unused).
GRID_AXES = {"baseline": ("soc", "pbat"), "thermal": ("soc", "tcl", "pbat"),
             "thermal_cabin": ("soc", "tcl", "tcab", "pbat", "qheat")}


@dataclass(frozen=True)
class FormulationGrids:
    """One :class:`DPGrids` per formulation. The default (:data:`DEFAULT_GRIDS`) is each formulation's
    converged grid: Baseline-DP :data:`BASELINE_CONVERGED_GRIDS`, Thermal-DP the paper's Table II,
    Thermal-Cabin-DP :data:`CABIN_CONVERGED_GRIDS`; ``uniform(g)`` is one grid for all (the paper's set-up)."""

    baseline: DPGrids = field(default_factory=lambda: replace(BASELINE_CONVERGED_GRIDS))
    thermal: DPGrids = field(default_factory=DPGrids)
    thermal_cabin: DPGrids = field(default_factory=lambda: replace(CABIN_CONVERGED_GRIDS))

    @classmethod
    def uniform(cls, g: DPGrids) -> "FormulationGrids":
        """One grid for every formulation (the paper's set-up)."""
        return cls(g, g, g)

    @classmethod
    def coerce(cls, g) -> "FormulationGrids":
        """None -> the defaults; a :class:`DPGrids` -> that grid for every formulation."""
        if g is None:
            return cls()
        return g if isinstance(g, cls) else cls.uniform(g)

    def of(self, formulation: str) -> DPGrids:
        """The grid of ``formulation`` (``baseline``, ``thermal`` or ``thermal_cabin``)."""
        if formulation not in FORMULATIONS:
            raise ScenarioError(f"unknown formulation {formulation!r}; choose from {', '.join(FORMULATIONS)}")
        return getattr(self, formulation)

    def with_steps(self, **steps) -> "FormulationGrids":
        """The given steps (e.g. ``soc=0.02``) replace every formulation's own."""
        return FormulationGrids(*(replace(self.of(f), **steps) for f in FORMULATIONS))

    def halved(self) -> "FormulationGrids":
        """Every formulation's grid with every step halved (for convergence checks)."""
        return FormulationGrids(*(self.of(f).halved() for f in FORMULATIONS))

    def to_dict(self) -> dict:
        """``{formulation: {step: value}}``, JSON-able."""
        return {f: self.of(f).to_dict() for f in FORMULATIONS}

    def describe(self, formulations=FORMULATIONS) -> str:
        """Each formulation's steps on its own axes, e.g. ``baseline soc 0.005, pbat 250``."""
        return "; ".join(f + " " + ", ".join(f"{a} {getattr(self.of(f), a):g}" for a in GRID_AXES[f])
                         for f in formulations)


#: Each formulation's default grid.
DEFAULT_GRIDS = FormulationGrids()


def parse_grid_steps(spec) -> dict:
    """Grid steps given as ``"soc=0.01,tcl=1,tcab=1,pbat=500,qheat=50"`` or as a mapping (any subset) ->
    ``{name: step}``, checked: known names, positive numbers."""
    if isinstance(spec, str) or spec is None:
        items = []
        for part in (spec or "").split(","):
            if not part.strip():
                continue
            if "=" not in part:
                raise ScenarioError(f"grid spec {part!r}: expected name=step")
            items.append(tuple(s.strip() for s in part.split("=", 1)))
    else:
        items = list(dict(spec).items())
    vals = {}
    for k, v in items:
        if k not in DPGrids.__dataclass_fields__:
            raise ScenarioError(f"grid spec: unknown grid {k!r}; known: soc, tcl, tcab, pbat, qheat")
        try:
            if isinstance(v, bool):
                raise TypeError
            x = float(v)
        except (TypeError, ValueError, OverflowError):
            raise ScenarioError(f"grid spec: {k}={str(v)[:40]!r} is not a number") from None
        if not (x > 0 and math.isfinite(x)):
            raise ScenarioError(f"grid spec: {k} step must be a positive finite number")
        vals[k] = x
    return vals


def parse_grid_spec(spec: str | None, base=None):
    """A grid spec (:func:`parse_grid_steps`): the given steps replace those of ``base`` (a :class:`DPGrids`,
    default the paper's; or a :class:`FormulationGrids`, each formulation's)."""
    g = base or DPGrids()
    vals = parse_grid_steps(spec)
    return g.with_steps(**vals) if isinstance(g, FormulationGrids) else replace(g, **vals)


#: Most points on one grid axis (a SOC step of 1e-7 would ask for millions before anything is solved).
MAX_AXIS_POINTS = 20_000


def _grid(lo, hi, step, name: str = "grid"):
    if not (math.isfinite(lo) and math.isfinite(hi) and math.isfinite(step) and step > 0):
        raise ScenarioError(f"{name} {lo}:{step}:{hi}: the ends and the step must be finite, the step positive")
    span = (hi - lo) / step
    if span + 1 > MAX_AXIS_POINTS:
        raise ScenarioError(f"{name} {lo:g}:{step:g}:{hi:g} would have {span + 1:.3g} points (at most "
                            f"{MAX_AXIS_POINTS}): use a larger step")
    n = int(math.floor(span + 1e-9)) + 1
    if n < 2:
        raise ScenarioError(f"{name} {lo:g}:{step:g}:{hi:g} has fewer than two points: the step is larger than "
                            "the range")
    return lo + step * np.arange(n)


#: Budget of a DP problem's transition tables (steps x battery-power controls x SOC nodes, 8 bytes each: the
#: largest array of a problem), MB; IPTM_DP_MAX_TABLE_MB overrides it. Baseline-DP's convergence check on the
#: paper's drive (its converged grid halved) needs 948 MB on the default car
#: (:func:`optimize.formulations.solve.estimate_problem`).
DP_MAX_TABLE_MB = 2048.0


def check_table_size(n_steps: int, table_mb: float) -> None:
    """Refuse transition tables of ``table_mb`` MB above the budget (:data:`DP_MAX_TABLE_MB`), with the figures."""
    import os

    budget = float(os.environ.get("IPTM_DP_MAX_TABLE_MB", DP_MAX_TABLE_MB))
    if table_mb > budget:
        raise ScenarioError(
            f"the DP problem is too large: its transition tables ({n_steps} steps x battery-power controls x SOC "
            f"nodes) take {table_mb:,.0f} MB (budget {budget:g} MB): use a larger battery-power or SOC grid step, "
            "a shorter drive, or raise IPTM_DP_MAX_TABLE_MB")


def check_grid_axes(scen: "DPScenario", grids, params, formulations) -> None:
    """Every axis a formulation will build, checked before anything is solved or drawn (each refusal names the
    grid, its ends and step; :data:`MAX_AXIS_POINTS`), and the transition tables at least their fixed SOC grid
    needs (:func:`check_table_size`; the moving grid adds nodes, checked again where the problem is built).
    The cabin axis's span depends on the drive's comfort bounds; it is checked over the widest span a winter
    cabin grid takes (60 K)."""
    n_steps = None
    for f in formulations:
        if f not in FORMULATIONS:
            continue
        g = FormulationGrids.coerce(grids).of(f)
        socg = _grid(scen.soc_min, scen.soc_max, g.soc, "SOC grid (soc_min:soc:soc_max)")
        pg = _grid(float(params["P_bat_min_W"]), float(params["P_bat_max_W"]), g.pbat,
                   "battery-power grid (P_bat_min_W:pbat:P_bat_max_W)")
        if n_steps is None:
            n_steps = scen.load_cycle().n_steps
        check_table_size(n_steps, 8.0 * n_steps * (pg.size + 2) * (4 + socg.size) / 1e6)
        if f != "baseline":
            _grid(scen.T_cl_min, scen.T_cl_max, g.tcl, "coolant grid (T_cl_min:tcl:T_cl_max)")
        if f == "thermal_cabin":
            _grid(0.0, 60.0, g.tcab, "cabin grid (tcab over 60 K)")
            _grid(scen.Q_heat_min, scen.Q_heat_max, g.qheat, "heater grid (Q_heat_min:qheat:Q_heat_max)")

