"""Controllers that know the route: what a navigation system knows at departure, never the speed trace.

A :class:`Route` is the planned trip's length, optionally its road classes along the way (``urban``,
``suburban``, ``highway``, given as classes or as speed limits) and the forecast ambient, from a small TOML or
JSON file (:func:`load_route`) or just a length (:meth:`Route.from_length`).

:class:`RouteECMSController` is the thermal ECMS of :mod:`optimize.causal.ecms` with its co-states scheduled
by the distance to go ``D`` (km; distance driven is integrated from the speed the controller tracks)::

    s  = s_base(d) + s_i + k(D) * (SOC_target - SOC - r v^2),   k(D) = max(k_end * min(1, d_near / D), k_min)
    mu = mu0 + k_mu * max(T_cl_target - T_cl, 0) * min(1, D / d_heat)

- The electric co-state moves towards the value that ends the trip at the target: far from the end a SOC
  error costs little (there is distance left to spend or recover it), so the gain is weak and the co-state
  nearly constant, as Pontryagin's principle asks; within ``d_near`` of the end the gain is the causal
  ECMS's. ``k_min`` bounds how far the SOC may stray should the trip end early. ``s_i`` integrates the SOC
  error over distance (``k_i`` per unit SOC and km) so the base level learns the drive's charge-sustaining
  co-state.
- The coolant co-state values warming a cold engine by the distance left to use the warmth: over the last
  ``d_heat`` km, heat is worth only its base price.
- ``s_base``: ``s0`` (length only), or with road classes the distance-weighted mean, over the rest of the
  route, of per-class co-states (:func:`class_costates`, the constant co-state that sustains the charge on
  the training cycle of each class at the forecast ambient: what the road classes predict of the demand).

With ``k_end = k_min = k_i = k_mu = 0`` the co-states are constant and the controller is the constant
co-state ECMS of :func:`optimize.causal.hindsight.tune_ecms_on_drive` (``tests/test_causal_route.py``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from calib.errors import IptmError
from optimize.causal.controllers import ECMSController
from optimize.causal.ecms import ECMSParams, ecms_choice

ROAD_CLASSES = ("urban", "suburban", "highway")
#: A segment given by its speed limit takes the first class whose bound (km/h) the limit does not exceed.
SPEED_LIMIT_CLASS_KPH = (("urban", 60.0), ("suburban", 90.0), ("highway", math.inf))
#: The training cycle whose charge-sustaining co-state stands for each class (:func:`class_costates`);
#: suburban, between the two, takes their mean.
CLASS_CYCLE = {"urban": "udds", "highway": "hwfet"}
#: Plausible forecast ambient (degC).
AMBIENT_RANGE = (-40.0, 50.0)
MAX_LENGTH_KM = 2000.0
#: What :class:`RouteECMSController` is told of the route: nothing, the length, or the length and classes.
KNOWLEDGE = ("none", "length", "route")


def _class_of_limit(kph: float) -> str:
    return next(c for c, hi in SPEED_LIMIT_CLASS_KPH if kph <= hi)


@dataclass(frozen=True)
class Segment:
    start_km: float
    end_km: float
    road_class: str


@dataclass(frozen=True)
class Route:
    """A planned trip: ``length_km``, ``segments`` (contiguous, from 0 to the length; may be empty) and
    ``ambient_degC`` (the forecast, or None)."""

    length_km: float
    segments: tuple = ()
    ambient_degC: float | None = None
    source: str = ""

    @classmethod
    def from_length(cls, km, where: str = "--route-length-km") -> "Route":
        return cls(_length(km, where), (), None, where)

    @classmethod
    def from_dict(cls, d: dict, where: str = "route") -> "Route":
        """Validate a route table: ``length_km``, optional ``ambient_degC`` and ``[[segment]]`` tables with
        ``from_km``, ``to_km`` and ``class`` or ``speed_limit_kph``."""
        if not isinstance(d, dict):
            raise IptmError(f"{where}: a route is a table with length_km (and optionally segment, ambient_degC)")
        unknown = sorted(set(d) - {"length_km", "segment", "ambient_degC", "name"})
        if unknown:
            raise IptmError(f"{where}: unknown field(s) {', '.join(unknown)}; a route has length_km, "
                            "ambient_degC and [[segment]] tables (from_km, to_km, class or speed_limit_kph)")
        if "length_km" not in d:
            raise IptmError(f"{where}: length_km missing: give the planned trip's length in km")
        length = _length(d["length_km"], f"{where}: length_km")
        amb = d.get("ambient_degC")
        if amb is not None:
            amb = _number(amb, f"{where}: ambient_degC")
            if not AMBIENT_RANGE[0] <= amb <= AMBIENT_RANGE[1]:
                raise IptmError(f"{where}: ambient_degC {amb:g} outside {AMBIENT_RANGE[0]:g} to "
                                f"{AMBIENT_RANGE[1]:g} degC; give the forecast in degC")
        raw = d.get("segment", [])
        if not isinstance(raw, list) or not all(isinstance(s, dict) for s in raw):
            raise IptmError(f"{where}: segment must be a list of tables ([[segment]] in TOML)")
        segs, at = [], 0.0
        for i, s in enumerate(raw, 1):
            w = f"{where}: segment {i}"
            bad = sorted(set(s) - {"from_km", "to_km", "class", "speed_limit_kph"})
            if bad:
                raise IptmError(f"{w}: unknown field(s) {', '.join(bad)}; a segment has from_km, to_km and "
                                "class or speed_limit_kph")
            for k in ("from_km", "to_km"):
                if k not in s:
                    raise IptmError(f"{w}: {k} missing")
            a, b = _number(s["from_km"], f"{w}: from_km"), _number(s["to_km"], f"{w}: to_km")
            if abs(a - at) > 1e-6:
                raise IptmError(f"{w}: from_km {a:g} but the route so far ends at {at:g} km; segments must be "
                                "in order, from 0, without gaps or overlaps")
            if not b > a:
                raise IptmError(f"{w}: to_km {b:g} must exceed from_km {a:g}")
            if ("class" in s) == ("speed_limit_kph" in s):
                raise IptmError(f"{w}: give exactly one of class ({', '.join(ROAD_CLASSES)}) or speed_limit_kph")
            if "class" in s:
                c = s["class"]
                if c not in ROAD_CLASSES:
                    raise IptmError(f"{w}: class {c!r}; choose one of {', '.join(ROAD_CLASSES)}")
            else:
                lim = _number(s["speed_limit_kph"], f"{w}: speed_limit_kph")
                if not 5.0 <= lim <= 200.0:
                    raise IptmError(f"{w}: speed_limit_kph {lim:g} outside 5 to 200 km/h")
                c = _class_of_limit(lim)
            segs.append(Segment(a, b, c))
            at = b
        if segs and abs(at - length) > 1e-6 * max(1.0, length):
            raise IptmError(f"{where}: the segments end at {at:g} km but length_km is {length:g}; "
                            "segments must cover the whole route")
        return cls(length, tuple(segs), amb, where)

    def scaled(self, factor: float) -> "Route":
        """The same route announced ``factor`` times as long (segments stretched alike): a wrong length."""
        segs = tuple(Segment(s.start_km * factor, s.end_km * factor, s.road_class) for s in self.segments)
        return replace(self, length_km=self.length_km * factor, segments=segs)

    def length_only(self) -> "Route":
        return replace(self, segments=())

    def class_shares(self, from_km: float = 0.0) -> dict:
        """Share of each road class in the route beyond ``from_km`` (empty when no classes are known)."""
        out = {}
        for s in self.segments:
            d = max(0.0, s.end_km - max(s.start_km, from_km))
            if d > 0:
                out[s.road_class] = out.get(s.road_class, 0.0) + d
        tot = sum(out.values())
        return {c: v / tot for c, v in out.items()} if tot > 0 else {}

    def describe(self) -> str:
        cls = ", ".join(f"{c} {100 * v:.0f} %" for c, v in self.class_shares().items())
        return (f"route {self.length_km:.2f} km" + (f" ({cls})" if cls else "")
                + (f", forecast {self.ambient_degC:g} degC" if self.ambient_degC is not None else ""))


def _number(x, where: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise IptmError(f"{where}: {x!r} is not a finite number")
    return float(x)


def _length(km, where: str) -> float:
    v = _number(km, where)
    if not 0.0 < v <= MAX_LENGTH_KM:
        raise IptmError(f"{where}: {v:g} km; the trip length must be above 0 and at most {MAX_LENGTH_KM:g} km")
    return v


def load_route(path) -> Route:
    """A :class:`Route` from a TOML or JSON file (one clear error naming the file and field if it is bad)."""
    from calib.fileio import read_config

    return Route.from_dict(read_config(path, IptmError, "route file"), str(path))


def route_from_args(route_file=None, length_km=None) -> Route | None:
    """The route of the command line: a file, a length, or neither (None). Both given is refused."""
    if route_file and length_km is not None:
        raise IptmError("give --route FILE or --route-length-km KM, not both (a route file has its length)")
    if route_file:
        return load_route(route_file)
    return Route.from_length(length_km) if length_km is not None else None


def route_of_cycle(cycle, piece_km: float = 1.0) -> Route:
    """A stand-in for the map of a drive that has none (the bundled cycles): its length, and for every piece of
    ``piece_km`` the class of the speed limit taken as the highest speed reached on it
    (:data:`SPEED_LIMIT_CLASS_KPH`). It reveals that speed per piece, not the stops or the trace; a real map
    knows the limit whether or not the car reaches it."""
    from calib.model.cycles import load_cycle

    c = load_cycle(cycle)
    v = np.asarray(c.v, float)
    d = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * c.Ts)]) / 1e3
    L = float(d[-1])
    edges = list(np.arange(0.0, L, piece_km)) + [L]
    if len(edges) > 2 and edges[-1] - edges[-2] < 0.25 * piece_km:  # no sliver at the end
        edges.pop(-2)
    segs = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (d >= a) & (d <= b)
        c_ = _class_of_limit(float(v[m].max() * 3.6) if m.any() else 0.0)
        if segs and segs[-1].road_class == c_:
            segs[-1] = Segment(segs[-1].start_km, b, c_)
        else:
            segs.append(Segment(a, b, c_))
    return Route(L, tuple(segs), None, f"{c.name} (classes from its speeds)")


def ended_early(cycle, fraction: float, decel_mps2: float = 1.0):
    """``cycle`` cut where ``fraction`` of its distance is driven, then braked to a stop at ``decel_mps2``: a
    trip that ends before the planned destination (a trip ends standing, with the stop's regeneration)."""
    from calib.model.cycles import Cycle, load_cycle

    if not 0.0 < fraction < 1.0:
        raise IptmError(f"ended_early: fraction {fraction!r} must be between 0 and 1 (exclusive)")
    c = load_cycle(cycle)
    v = np.asarray(c.v, float)
    d = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * c.Ts)])
    k = int(np.searchsorted(d, fraction * d[-1]))
    tail = np.arange(v[k] - decel_mps2 * c.Ts, 0.0, -decel_mps2 * c.Ts)
    vv = np.concatenate([v[: k + 1], tail, [0.0]])
    return Cycle(f"{c.name} (ends at {100 * fraction:g} % of its distance)", np.arange(vv.size) * c.Ts, vv)


@dataclass
class RouteECMSParams:
    """Schedule of :class:`RouteECMSController` (see the module docstring). Defaults chosen on the training
    cycles only (``docs/route_aware.md``, section "Selection")."""

    s0: float = 0.8
    k_end: float = 40.0  # per unit SOC, within d_near of the end (the causal ECMS's k_s)
    d_near_km: float = 0.5
    k_min: float = 15.0
    k_i: float = 1.0  # per unit SOC and km
    mu0: float = 0.0
    k_mu: float = 0.03
    d_heat_km: float = 2.0
    soc_target: float = 0.6
    T_cl_target_degC: float = 80.0
    Q_heat_W: float = 1500.0
    pbat_step_W: float = 500.0
    regen_fraction: float = 0.6

    def to_dict(self) -> dict:
        return asdict(self)

    def ecms(self) -> ECMSParams:
        return ECMSParams(s0=self.s0, k_s=0.0, mu0=self.mu0, k_mu=0.0, soc_target=self.soc_target,
                          T_cl_target_degC=self.T_cl_target_degC, Q_heat_W=self.Q_heat_W,
                          pbat_step_W=self.pbat_step_W, regen_fraction=self.regen_fraction)


class RouteECMSController(ECMSController):
    """The thermal ECMS with co-states scheduled by distance to go (module docstring). ``class_s``: the
    per-class co-states (:func:`class_costates`), used when the route has classes."""

    def __init__(self, mp, route: Route, rp: RouteECMSParams | None = None, T_amb: float = -10.0,
                 class_s: dict | None = None, T_bat=None, W_bl=None):
        rp = rp or RouteECMSParams()
        super().__init__(mp, rp.ecms(), T_amb, T_bat, W_bl)
        self.route, self.rp = route, rp
        self.class_s = dict(class_s or {})
        if route.segments:
            missing = {s.road_class for s in route.segments} - set(self.class_s)
            if missing:
                raise IptmError(f"route-aware ECMS: no co-state for road class(es) {', '.join(sorted(missing))}; "
                                "build them with class_costates()")
        # s_base at the start of each segment onwards: the length-weighted mean over what is left
        self._seg_end = np.array([s.end_km for s in route.segments])
        self._seg_s = np.array([self.class_s[s.road_class] for s in route.segments]) if route.segments else None
        self.reset()

    def reset(self) -> None:
        super().reset()
        self.d_km = 0.0
        self.s_i = 0.0

    def describe(self) -> str:
        return ("route-aware ECMS (" + self.route.describe() + "; "
                + ", ".join(f"{k}={v:g}" for k, v in self.rp.to_dict().items()) + ")")

    def s_base(self, d_km: float) -> float:
        if self._seg_s is None:
            return self.rp.s0
        i = int(np.searchsorted(self._seg_end, d_km, side="right"))
        if i >= self._seg_s.size:  # past the announced end: the last class
            return float(self._seg_s[-1])
        start = np.concatenate([[0.0], self._seg_end[:-1]])
        w = self._seg_end[i:] - np.maximum(start[i:], d_km)
        return float(np.dot(w, self._seg_s[i:]) / w.sum())

    def co_states(self, soc: float, T_cl: float) -> tuple[float, float]:
        rp = self.rp
        togo = max(self.route.length_km - self.d_km, 0.0)
        k = rp.k_end * (1.0 if togo <= rp.d_near_km else rp.d_near_km / togo)
        err = rp.soc_target - soc - self.kin * self.v * self.v
        s = self.s_base(self.d_km) + self.s_i + max(k, rp.k_min) * err
        w_heat = 1.0 if togo >= rp.d_heat_km else (togo / rp.d_heat_km if rp.d_heat_km > 0 else 0.0)
        mu = rp.mu0 + rp.k_mu * max(rp.T_cl_target_degC - T_cl, 0.0) * w_heat
        return s, mu, err

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        s, mu, err = self.co_states(soc, T_cl)
        v0 = self.v
        u, self.v = ecms_choice(self.mp, soc, T_cl, T_cab, P_trac, self.controls, self.Q_heat, self.T_amb,
                                self.T_bat, self.W_bl, Ts, s, self.k_el, mu, self.k_cl, self.v, self.work)
        dd = 0.5 * (v0 + self.v) * Ts / 1e3
        self.d_km += dd
        self.s_i += self.rp.k_i * err * dd
        return self._emit(u, k, soc, T_cl, T_cab, P_trac, Ts)


def sustaining_costate(params, cycle, rp: RouteECMSParams, T_amb: float, *, soc0: float = 0.6, T_cl0: float = 70.0,
                       T_cab0: float = 20.0, lo: float = 0.1, hi: float = 2.0, tol: float = 0.005) -> float:
    """The constant electric co-state (``mu0`` held, no feedback) that ends ``cycle`` at ``soc0``: bisection,
    a dearer battery ending higher."""
    from calib.model.simulate import simulate

    mp = params.model_params() if hasattr(params, "model_params") else params
    const = replace(rp, k_end=0.0, k_min=0.0, k_i=0.0, k_mu=0.0, soc_target=soc0)

    def dsoc(s):
        ctrl = RouteECMSController(mp, Route.from_length(1.0, "bisection"), replace(const, s0=s), T_amb)
        r = simulate(params, cycle, ctrl, T_amb=T_amb, soc0=soc0, T_cl0=T_cl0, T_cab0=T_cab0, Q_heat=rp.Q_heat_W)
        return r.soc[-1] - soc0

    a, b = lo, hi
    while b - a > tol:
        m = 0.5 * (a + b)
        if dsoc(m) < 0.0:
            a = m
        else:
            b = m
    return 0.5 * (a + b)


def class_costates(params, rp: RouteECMSParams, T_amb: float, **kw) -> dict:
    """Per road class, the co-state that sustains the charge on the class's training cycle (:data:`CLASS_CYCLE`)
    at ``T_amb`` (the forecast ambient); suburban takes the mean of urban and highway."""
    out = {c: sustaining_costate(params, cyc, rp, T_amb, **kw) for c, cyc in CLASS_CYCLE.items()}
    out["suburban"] = 0.5 * (out["urban"] + out["highway"])
    return out


def make_route_controller(params, route: Route | None, *, knowledge: str = "route", T_amb: float,
                          Q_heat: float = 1500.0, soc_target: float = 0.6, rp: RouteECMSParams | None = None,
                          class_s: dict | None = None):
    """The controller for what is known at departure (:data:`KNOWLEDGE`): ``none`` is the causal ECMS
    (:class:`~optimize.causal.controllers.ECMSController`); ``length`` the route-aware ECMS told the length
    only; ``route`` also the road classes (per-class co-states built at the route's forecast ambient, else
    at ``T_amb``, unless ``class_s`` is given)."""
    if knowledge not in KNOWLEDGE:
        raise IptmError(f"route knowledge {knowledge!r}; choose one of {', '.join(KNOWLEDGE)}")
    mp = params.model_params() if hasattr(params, "model_params") else params
    if knowledge == "none":
        return ECMSController(mp, replace(ECMSParams(), Q_heat_W=Q_heat, soc_target=soc_target), T_amb)
    if route is None:
        raise IptmError("the route-aware ECMS needs a route: give --route FILE or --route-length-km KM")
    rp = replace(rp or RouteECMSParams(), Q_heat_W=Q_heat, soc_target=soc_target)
    if knowledge == "length" or not route.segments:
        return RouteECMSController(mp, route.length_only(), rp, T_amb)
    if class_s is None:
        amb = T_amb if route.ambient_degC is None else route.ambient_degC
        class_s = class_costates(params, rp, amb, soc0=soc_target)
    return RouteECMSController(mp, route, rp, T_amb, class_s)


def drive_route(params, scen, cycle, route, knowledge, rp=None, class_s=None):
    """Drive ``cycle`` from ``scen``'s initial state and ambient under :func:`make_route_controller`."""
    from calib.model.simulate import simulate

    ctrl = make_route_controller(params, route, knowledge=knowledge, T_amb=scen.T_amb, Q_heat=scen.Q_heat,
                                 soc_target=scen.soc0, rp=rp, class_s=class_s)
    return simulate(params, cycle, ctrl, T_amb=scen.T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0, T_cab0=scen.T_cab0,
                    Q_heat=scen.Q_heat)


#: The selection grid (``docs/route_aware.md``, "Selection") and its training runs.
SELECT_GRID = {"s0": (0.8,), "d_near_km": (0.5,), "k_min": (10.0, 15.0), "k_i": (0.0, 1.0),
               "regen_fraction": (0.4, 0.6)}
SELECT_BAND, SELECT_ROBUST_BAND = 0.0075, 0.02
#: Announced length over the true one, and the share of the distance driven when the trip ends early.
LENGTH_ERRORS, ENDS_EARLY_AT = (0.8, 1.2), 0.6


def _select_one(job: tuple) -> dict:
    """Every training run of one setting of :data:`SELECT_GRID` with the per-class co-states of each ambient
    (see :func:`select_schedule`)."""
    from calib.model.params import default_parameters

    from optimize.causal.compare import AMBIENTS, TRAIN_CYCLES, VALUATIONS, valuation_scenario, valued_fuel
    from optimize.formulations.scenario import DPScenario

    setting, class_s = job
    ps = default_parameters()
    rp = replace(RouteECMSParams(), **setting)
    runs = []
    for T in AMBIENTS:
        cs = class_s[T]
        for c in TRAIN_CYCLES:
            base = replace(DPScenario(), cycle=c, T_amb=T)
            cyc = base.load_cycle()
            route = route_of_cycle(cyc)
            for kn in KNOWLEDGE:
                sim = drive_route(ps, base, cyc, route, kn, rp, cs)
                r = {"cycle": c, "T_amb": T, "knowledge": kn, "dsoc": float(sim.soc[-1] - base.soc0),
                     **{v: float(valued_fuel(sim, valuation_scenario(base, v), v)[0]) for v in VALUATIONS}}
                if kn != "none":
                    rob = [drive_route(ps, base, cyc, route.scaled(f), kn, rp, cs) for f in LENGTH_ERRORS]
                    rob.append(drive_route(ps, base, ended_early(cyc, ENDS_EARLY_AT), route, kn, rp, cs))
                    r["robust_dsoc"] = [float(x.soc[-1] - base.soc0) for x in rob]
                runs.append(r)
    return {"setting": setting, "runs": runs}


def select_schedule(grid: dict | None = None, workers: int = 2) -> dict:
    """Choose :class:`RouteECMSParams`' schedule on the training cycles only: among the settings of ``grid``
    (default :data:`SELECT_GRID`) whose ``length`` and ``route`` runs all end within :data:`SELECT_BAND` of
    SOC_0 with the exact length, and within :data:`SELECT_ROBUST_BAND` with the length announced wrong
    (:data:`LENGTH_ERRORS`) or the trip ending early (:data:`ENDS_EARLY_AT`), the least mean valued fuel
    relative to the causal ECMS (both valuations). Returns every setting's figures and ``chosen``."""
    import itertools
    from concurrent.futures import ProcessPoolExecutor

    from calib.model.params import default_parameters
    from optimize.causal.compare import AMBIENTS, VALUATIONS

    grid = grid or SELECT_GRID
    settings = [dict(zip(grid, vals)) for vals in itertools.product(*grid.values())]
    # the class co-states hold the schedule off, so no setting of the grid changes them
    class_s = {T: class_costates(default_parameters(), RouteECMSParams(), T) for T in AMBIENTS}
    with ProcessPoolExecutor(workers) as ex:
        res = list(ex.map(_select_one, [(s, class_s) for s in settings]))
    rows = []
    for r in res:
        ref = {(x["cycle"], x["T_amb"]): x for x in r["runs"] if x["knowledge"] == "none"}
        mine = [x for x in r["runs"] if x["knowledge"] != "none"]
        rel = [100.0 * (x[v] / ref[(x["cycle"], x["T_amb"])][v] - 1.0) for x in mine for v in VALUATIONS]
        worst = max(abs(x["dsoc"]) for x in mine)
        worst_rob = max(abs(d) for x in mine for d in x["robust_dsoc"])
        rows.append({**r["setting"], "fuel_vs_causal_pct": float(np.mean(rel)), "max_abs_dsoc": worst,
                     "max_abs_dsoc_robust": worst_rob,
                     "eligible": bool(worst <= SELECT_BAND and worst_rob <= SELECT_ROBUST_BAND)})
    ok = [r for r in rows if r["eligible"]]
    return {"rows": rows, "chosen": min(ok, key=lambda r: r["fuel_vs_causal_pct"]) if ok else None,
            "class_costates": {str(T): v for T, v in class_s.items()}}
