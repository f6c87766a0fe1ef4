"""Drive plans: the drive (road or dynamometer) that most informs the parameters a calibration left weak.

A candidate drive is a sequence of standard-cycle segments and stops (road: parts of cycles cut at a
standstill; dyno: whole cycles), a heater schedule (the climate control runs, except in windows where the
driver switches the heater off) and a start state (coolant soak temperature; the cabin starts at the
ambient). The rule-based controller the car runs (:class:`calib.synth.HvacController`) decides engine and
battery in a simulation of the calibrated model; a drive the car cannot follow (the simulator refuses a
step) or that lets the cabin fall below a comfort floor once it was comfortable is infeasible.

Each feasible candidate is scored the way the calibration would weigh its log: the output-error replay of
each targeted subsystem (coolant temperature from the logged fuel, engine power and heater heat; cabin
temperature from the logged heater heat), linearised at the artifact's posterior mean by central
differences, with the noise sd the calibration fitted (:mod:`calib.design.oed`), the coolant above the
prior regulation limit left out and the replay restarted after it, as :func:`calib.fit.thermal.fit_thermal`
does, and one initial temperature per replay run as a nuisance parameter. The prior is the artifact's
posterior; the predicted posterior sd of the targets comes from ``(P0^-1 + F)^-1`` with the subsystem's
other parameters marginalised.

The search is exhaustive over a finite space (:func:`candidates`): stage 1 scores every segment
sequence with the climate control running throughout and the first soak; stage 2 scores the best
:data:`STAGE2_KEEP` sequences with every heater schedule and every soak.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from calib.design.oed import CRITERIA, Infeasible, d_criterion, fisher, marginal_posterior, sd_criterion, search
from calib.design.prior import CHANNEL, DESIGNABLE, ArtifactPrior, subsystem_of
from calib.errors import IptmError, ParameterError
from calib.model.equations import ON

#: Road segments: a standard cycle cut between two standstills (cycle, start s, end s).
ROAD_SEGMENTS = {
    "udds_bag1": ("udds", 0, 505), "udds_bag2": ("udds", 505, 1369), "hwfet": ("hwfet", 0, 765),
    "us06": ("us06", 0, 600), "nycc": ("nycc", 0, 598), "artemis_urban": ("artemis_urban", 0, 993),
    "wltc_high": ("wltc_high_3b", 0, 454), "wltc_extrahigh": ("wltc_extrahigh_3", 0, 322),
}
#: Stops (s): the car stands with the engine as the controller decides (a cool-down when it is warm).
STOPS = {"stop_120": 120, "stop_300": 300, "stop_600": 600}
#: Parametrised cruises: (speed km/h, seconds at that speed), reached from a standstill at
#: :data:`ACCEL_MPS2` and braked back to one at :data:`DECEL_MPS2` (a steady load holds the coolant at the
#: thermostat).
CRUISES = {"cruise_60": (60.0, 300), "cruise_90": (90.0, 300), "cruise_110": (110.0, 300)}
ACCEL_MPS2 = 1.0
DECEL_MPS2 = 1.3
#: Dynamometer: whole standard cycles.
DYNO_CYCLES = ("udds", "hwfet", "us06", "nycc", "artemis_urban", "wltc_city_3b", "wltc_high_3b", "wltc_extrahigh_3")
#: Heater schedules: name -> windows (start, end) as fractions of the drive where the heater is off.
HEATER_SCHEDULES = {
    "auto": (),
    "off 300 s at 25 %": ((0.25, None),), "off 300 s at 50 %": ((0.50, None),), "off 300 s at 75 %": ((0.75, None),),
    "off 180 s at 30 % and 70 %": ((0.30, 180.0), (0.70, 180.0)),
}
HEATER_OFF_S = 300.0
#: Longest standstill a road plan ends with (the rest of the time budget, parked and logging).
MAX_PAD_S = 330.0
#: Most segment sequences stage 1 scores (a long plan drops its longest sequences to stay within it).
MAX_SEQUENCES = 600
#: Sequences carried from stage 1 to stage 2 of the search.
STAGE2_KEEP = 6
#: Comfort: once the cabin has reached the set point minus this (K), it may not fall below the floor.
COMFORT_REACHED_K = 3.0
COMFORT_MIN_DEGC = 16.0
T_SET = 21.0
SOC0 = 0.6

_FIELD = {"C_eng_J_per_K": "C_eng", "gamma_exh": "gamma_exh", "hA_eng_W_per_K": "hA_eng", "T_open_degC": "T_open",
          "k_rad_W_per_K": "k_rad", "C_cab_J_per_K": "C_cab", "UA_cab_W_per_K": "UA_cab", "Q_sun_W": "Q_sun"}


@dataclass(frozen=True)
class Design:
    """One candidate drive.

    ``segments`` names :data:`ROAD_SEGMENTS` / :data:`STOPS` keys (road) or :data:`DYNO_CYCLES` (dyno);
    ``pad_s`` parked seconds at the end (to the time budget); ``heater`` a :data:`HEATER_SCHEDULES` key;
    ``T_cl0`` the coolant at the start (soak), ``T_amb`` the ambient (dyno: the cell, the soak temperature).
    """

    segments: tuple
    pad_s: float
    heater: str
    T_cl0: float
    T_amb: float
    dyno: bool = False

    def describe(self) -> str:
        """One line: the segments, the parked end, the heater schedule and the start state."""
        seq = " + ".join(self.segments) + (f" + parked {self.pad_s:.0f} s" if self.pad_s > 0 else "")
        start = (f"cell soak {self.T_amb:g} degC" if self.dyno else
                 f"ambient {self.T_amb:g} degC, coolant at start {self.T_cl0:g} degC")
        return f"{seq}; heater {self.heater}; {start}"


def _segment(name, dyno):
    from calib.model.cycles import load_cycle

    if dyno or (name not in ROAD_SEGMENTS and name not in STOPS and name not in CRUISES):
        return load_cycle(name).v[:-1]  # its n_steps seconds; the last sample is the next segment's first
    if name in STOPS:
        return np.zeros(STOPS[name])
    if name in CRUISES:
        return cruise(*CRUISES[name])
    cyc, a, b = ROAD_SEGMENTS[name]
    return load_cycle(cyc).v[a:b]


def cruise(kph: float, hold_s: int) -> np.ndarray:
    """Speed (m/s, 1 s) of a cruise: from a standstill at :data:`ACCEL_MPS2` to ``kph``, held ``hold_s``,
    braked at :data:`DECEL_MPS2` to a standstill (ends at zero)."""
    v = kph / 3.6
    up = np.minimum(np.arange(int(math.ceil(v / ACCEL_MPS2))) * ACCEL_MPS2, v)
    down = np.maximum(v - np.arange(1, int(math.ceil(v / DECEL_MPS2)) + 1) * DECEL_MPS2, 0.0)
    return np.concatenate([up, np.full(hold_s, v), down])


def build_cycle(design: Design):
    """The design's speed trace as a :class:`calib.model.cycles.Cycle` (1 s) and the segment name of each
    sample."""
    from calib.model.cycles import Cycle

    parts, labels = [], []
    for name in design.segments:
        v = _segment(name, design.dyno)
        parts.append(v)
        labels += [name] * v.size
    pad = int(round(design.pad_s))
    if pad:
        parts.append(np.zeros(pad))
        labels += ["parked"] * pad
    v = np.concatenate(parts + [np.zeros(1)])
    labels.append(labels[-1])
    return Cycle("plan: " + " + ".join(design.segments), np.arange(v.size, dtype=float), v), labels


def heater_windows(design: Design, duration_s: float) -> list:
    """The heater-off windows (start, end) in s of a design."""
    out = []
    for frac, length in HEATER_SCHEDULES[design.heater]:
        t0 = frac * duration_s
        out.append((t0, min(t0 + (length or HEATER_OFF_S), duration_s)))
    return out


def simulate_design(params, design: Design, T_set: float = T_SET):
    """Simulate a design with the calibrated model under the car's rule-based controller and climate control
    (cabin at the ambient at the start, battery at the ambient, SOC :data:`SOC0`). Returns (SimResult,
    segment labels, heater-off windows)."""
    cyc, labels = build_cycle(design)
    windows = heater_windows(design, float(cyc.t[-1]))
    return simulate_cycle(params, cyc, design.T_amb, design.T_cl0, windows, T_set), labels, windows


def simulate_cycle(params, cycle, T_amb: float, T_cl0: float, heater_off=(), T_set: float = T_SET):
    """Simulate any speed trace as a plan would be: rule-based controller and climate control (heater off in
    the windows ``heater_off``), cabin and battery at the ambient at the start, SOC :data:`SOC0`."""
    from calib.model.rulebased import RuleParams
    from calib.model.simulate import simulate
    from calib.synth import HvacController

    ctrl = HvacController(params.model_params(), RuleParams(), T_set=T_set, heater_off=list(heater_off))
    return simulate(params, cycle, ctrl, T_amb=T_amb, soc0=SOC0, T_cl0=T_cl0, T_cab0=T_amb, T_bat=T_amb)


def comfort_violation(T_cab, T_set=T_SET, floor=COMFORT_MIN_DEGC) -> str:
    """Why a cabin trace is not comfortable (empty when it is): once it reached ``T_set - 3`` K it must stay
    at or above ``floor``."""
    reached = np.flatnonzero(T_cab >= T_set - COMFORT_REACHED_K)
    if reached.size and float(np.min(T_cab[reached[0]:])) < floor:
        return f"cabin falls to {float(np.min(T_cab[reached[0]:])):.1f} degC after reaching comfort (floor {floor:g})"
    return ""


def _runs(ok, min_len):
    from calib.fit.replay import known_runs

    return known_runs(ok, min_len)


def sim_inputs(sim) -> dict:
    """What a log of a simulated drive would give the replays, on the N+1 sample times: ``T_amb``, fuel rate
    ``W``, engine power ``P`` (0 when the engine is not on), heater heat ``Q``, and the states ``T_cl``,
    ``T_cab``."""
    f = sim.flows
    last = lambda a: np.append(a, a[-1])  # noqa: E731 - flows (N) onto the N+1 sample times
    return {"T_amb": np.full(sim.t.size, float(sim.info["T_amb_degC"])), "W": last(f["W_f"]),
            "P": last(np.where(sim.e_mode == ON, f["P_e"], 0.0)), "Q": last(np.maximum(f["Q_heat"], 0.0)),
            "T_cl": np.asarray(sim.T_cl, float), "T_cab": np.asarray(sim.T_cab, float)}


def log_inputs(log, params) -> dict:
    """The same arrays from a drive log, as the thermal and cabin fits read it (NaN where unknown)."""
    from calib.fit.replay import fill_short, log_arrays
    from calib.fit.thermal import fuel_input

    la = log_arrays(log, params.model_params())
    P = la.f_on * la.P_on
    P[~la.known] = np.nan
    Q = np.maximum(la.Q_heat, 0.0) if la.Q_heat is not None else np.full(la.known.size, np.nan)
    n = la.known.size
    nan = np.full(n, np.nan)
    return {"T_amb": fill_short(la.ch["ambient_temp_degC"], la.dt), "W": fuel_input(la), "P": P, "Q": Q,
            "T_cl": la.logged("coolant_temp_degC") if log.has("coolant_temp_degC") else nan,
            "T_cab": la.logged("cabin_temp_degC") if log.has("cabin_temp_degC") else nan}


def subsystem_information(params, inputs, sub, names, steps, noise_sd, T_reg=None):
    """Fisher information of one subsystem's replay (thermal: coolant; cabin: cabin temperature) over a
    drive (``inputs``: :func:`sim_inputs` or :func:`log_inputs`, 1 s) on the parameters ``names`` (of that
    subsystem) and its nuisance parameters: one initial temperature per replay run (flat prior), and the
    calibration uncertainties the fit propagates into its posterior sd: the logged inputs' scale (fuel
    rate, engine power, heater heat; prior sd :data:`calib.fit.toolkit.INPUT_REL_SD`) and the temperature
    sensor's offset (prior sd :data:`calib.fit.toolkit.T_SENSOR_SD`). A parameter that trades against an
    input's scale (``Q_sun`` against the heater heat's) is then predicted to gain little from more of the
    same data. A run is a stretch of at least 60 s with every input known (and, thermal, the coolant at or
    below ``T_reg``); only samples with the output known carry information.

    Returns (F, nuisance prior variances): ``F`` is square over ``names`` then the nuisances (``inf``: flat).
    """
    from calib.fit.replay import MIN_SEGMENT_S, cabin_replay, coolant_replay
    from calib.fit.toolkit import INPUT_REL_SD, T_SENSOR_SD

    mp0 = params.model_params()
    T_amb, W, P, Q = inputs["T_amb"], inputs["W"], inputs["P"], inputs["Q"]
    if sub == "thermal":
        y = inputs["T_cl"]
        known = np.isfinite(T_amb) & np.isfinite(W) & np.isfinite(P) & np.isfinite(Q)
        hot = y > T_reg if T_reg is not None else np.zeros(y.size, bool)
        scales = ("fuel rate", "engine power", "heater heat")

        def replay(mp, T0, a, b, sc=(1.0, 1.0, 1.0)):
            return coolant_replay(mp, T0, 1.0, T_amb[a:b], sc[0] * W[a:b], sc[1] * P[a:b], sc[2] * Q[a:b])
    else:
        y = inputs["T_cab"]
        known = np.isfinite(T_amb) & np.isfinite(Q)
        hot = np.zeros(y.size, bool)
        scales = ("heater heat",)

        def replay(mp, T0, a, b, sc=(1.0,)):
            return cabin_replay(mp, T0, 1.0, T_amb[a:b], sc[0] * Q[a:b])
    runs = [(a, b) for a, b in _runs(known & ~hot, int(MIN_SEGMENT_S)) if np.isfinite(y[a:b]).sum() >= 3]
    k, m, nr = len(names), len(scales), len(runs)
    # order: parameters, run initial temperatures, input scales, sensor offset
    n = k + nr + m + 1
    F = np.zeros((n, n))
    h_s = 1e-3
    for r, (a, b) in enumerate(runs):
        seen = np.isfinite(y[a:b])
        T0 = float(y[a:b][seen][0])
        S = np.empty((b - a, k + 1 + m + 1))
        for j, nm in enumerate(names):
            h = steps[nm]
            up = replay(mp0._replace(**{_FIELD[nm]: float(params[nm]) + h}), T0, a, b)
            dn = replay(mp0._replace(**{_FIELD[nm]: float(params[nm]) - h}), T0, a, b)
            S[:, j] = (up - dn) / (2 * h)
        S[:, k] = (replay(mp0, T0 + 0.01, a, b) - replay(mp0, T0 - 0.01, a, b)) / 0.02
        for i in range(m):
            up, dn = [1.0] * m, [1.0] * m
            up[i], dn[i] = 1.0 + h_s, 1.0 - h_s
            S[:, k + 1 + i] = (replay(mp0, T0, a, b, up) - replay(mp0, T0, a, b, dn)) / (2 * h_s)
        S[:, k + 1 + m] = 1.0  # a sensor offset moves every reading
        idx = list(range(k)) + [k + r] + list(range(k + nr, n))
        F[np.ix_(idx, idx)] += fisher(S[seen], noise_sd)
    var = [math.inf] * nr + [INPUT_REL_SD ** 2] * m + [T_SENSOR_SD ** 2]
    return F, var


@dataclass
class Planner:
    """Designs drives for ``targets`` on an artifact's posterior (see the module docstring)."""

    prior: ArtifactPrior
    targets: list
    criterion: str = "d"
    T_set: float = T_SET
    comfort_min: float = COMFORT_MIN_DEGC

    def __post_init__(self):
        if self.criterion not in CRITERIA:
            raise ParameterError(f"criterion {self.criterion!r}: use one of {', '.join(CRITERIA)}")
        allowed = [n for names in DESIGNABLE.values() for n in names]
        for t in self.targets:
            if subsystem_of(t) is None:
                raise ParameterError(f"--target {t}: a drive plan can target {', '.join(allowed)} (the parameters of "
                                     "the coolant and cabin replays)")
            if t not in self.prior.sd:
                raise ParameterError(f"--target {t}: {self.prior.path} holds no posterior sd for it (held fixed "
                                     "by the calibration?); calibrate it or choose another target")
        if not self.targets:
            raise ParameterError(f"{self.prior.path}: no designable parameter has a posterior sd to reduce")
        self.subs = sorted({subsystem_of(t) for t in self.targets})
        # every estimated parameter of a targeted subsystem takes part (a target's sd depends on them)
        self.names = {s: [n for n in DESIGNABLE[s] if n in self.prior.sd] for s in self.subs}
        allp = [n for s in self.subs for n in self.names[s]]
        self.cov0 = self.prior.cov(allp)
        self.allp = allp
        ps = self.prior.params
        self.steps = {n: max(0.01 * self.prior.sd[n], 1e-6 * abs(float(ps[n])), 1e-9) for n in allp}
        from calib.fit.thermal import regulation_limit

        # the thermal fit leaves out the coolant above the limit of its *prior* thermostat and radiator
        pri = {n: ps.param(n).prior_value for n in ("T_open_degC", "k_rad_W_per_K")}
        base = ps.with_values(**{n: float(v) for n, v in pri.items() if isinstance(v, (int, float))})
        self.T_reg = regulation_limit(base)

    def predict(self, sim=None, inputs=None) -> dict:
        """Predicted posterior of the targets after logging the simulated drive ``sim`` (or a drive given as
        replay ``inputs``, :func:`log_inputs`): ``cov`` (targets), ``sd``."""
        inputs = sim_inputs(sim) if inputs is None else inputs
        blocks = []
        for s in self.subs:
            blocks.append((s, *subsystem_information(self.prior.params, inputs, s, self.names[s], self.steps,
                                                     self.prior.noise[s][0], self.T_reg if s == "thermal" else None)))
        n = len(self.allp)
        nuis = sum(len(v) for _, _, v in blocks)
        Fall = np.zeros((n + nuis, n + nuis))
        P0 = np.zeros((n + nuis, n + nuis))
        P0[:n, :n] = self.cov0
        off_p, off_n = 0, n
        for s, F, var in blocks:
            k = len(self.names[s])
            ip = list(range(off_p, off_p + k)) + list(range(off_n, off_n + len(var)))
            Fall[np.ix_(ip, ip)] += F
            P0[range(off_n, off_n + len(var)), range(off_n, off_n + len(var))] = var
            off_p += k
            off_n += len(var)
        idx = [self.allp.index(t) for t in self.targets]
        cov = marginal_posterior(P0, Fall, idx)
        return {"cov": cov, "sd": {t: float(math.sqrt(max(cov[i, i], 0.0))) for i, t in enumerate(self.targets)}}

    def score(self, cov) -> float:
        """The criterion (smaller is better): ``d``, the log of the volume ratio of the targets' posterior
        ellipsoid after and before the plan (``log det`` of the covariances, the D-optimal criterion on the
        targets with the rest marginalised); ``sd``, the mean ratio of predicted to current sd."""
        if self.criterion == "d":
            idx = [self.allp.index(t) for t in self.targets]
            return d_criterion(cov) - d_criterion(self.cov0[np.ix_(idx, idx)])
        return sd_criterion(cov, [self.prior.sd[t] for t in self.targets])

    def evaluate(self, design: Design):
        """(criterion, details) of a design, or :class:`calib.design.oed.Infeasible` with the reason: the car
        cannot follow it, or the cabin falls below the comfort floor after it was comfortable."""
        try:
            sim, labels, windows = simulate_design(self.prior.params, design, self.T_set)
        except IptmError as exc:
            raise Infeasible(f"the car cannot follow it: {exc}") from None
        why = comfort_violation(sim.T_cab, self.T_set, self.comfort_min)
        if why:
            raise Infeasible(why)
        pred = self.predict(sim)
        return self.score(pred["cov"]), {"sim": sim, "labels": labels, "windows": windows, **pred}


def sequences(budget_s: float, dyno: bool) -> list:
    """Segment sequences a plan may drive within ``budget_s`` (the rest parked): road, 1-4 segments of
    :data:`ROAD_SEGMENTS`, :data:`CRUISES` and :data:`STOPS` (no two stops in a row, no drive segment
    twice, not ending with a stop, at most :data:`MAX_PAD_S` left to park; for a long plan the longest
    sequences are dropped until at most :data:`MAX_SEQUENCES` remain); dyno, 1-3 different
    :data:`DYNO_CYCLES`, any remainder parked."""
    from calib.model.cycles import load_cycle

    if dyno:
        length = {c: load_cycle(c).n_steps for c in DYNO_CYCLES}
        out = []
        for r in (1, 2, 3):
            for seq in itertools.permutations(DYNO_CYCLES, r):
                tot = sum(length[c] for c in seq)
                if tot <= budget_s:
                    out.append((seq, budget_s - tot))
        return out
    length = ({k: b - a for k, (_, a, b) in ROAD_SEGMENTS.items()} | dict(STOPS)
              | {k: cruise(*c).size for k, c in CRUISES.items()})
    names = list(length)
    by_r = {}
    for r in (1, 2, 3, 4):
        by_r[r] = []
        for seq in itertools.product(names, repeat=r):
            if any(a in STOPS and b in STOPS for a, b in zip(seq, seq[1:])):
                continue
            drives = [s for s in seq if s not in STOPS]
            if not drives or len(set(drives)) < len(drives) or seq[-1] in STOPS:
                continue  # a stop at the end is the parked pad
            tot = sum(length[s] for s in seq)
            if tot <= budget_s and budget_s - tot <= MAX_PAD_S:
                by_r[r].append((seq, budget_s - tot))
    r_max = 4
    while r_max > 1 and sum(len(by_r[r]) for r in range(1, r_max + 1)) > MAX_SEQUENCES:
        r_max -= 1
    return [x for r in range(1, r_max + 1) for x in by_r[r]]


@dataclass
class Plan:
    """The chosen design, its simulation, the predicted posterior sd, and how the search went."""

    design: Design
    sim: object
    labels: list
    windows: list
    sd_now: dict
    sd_pred: dict
    criterion: str
    value: float
    searched: dict
    noise: dict
    ranking: list

    def table(self) -> list[dict]:
        """Per target: sd now (the artifact's posterior), predicted sd after the plan, their ratio."""
        return [{"name": n, "sd_now": self.sd_now[n], "sd_predicted": self.sd_pred[n],
                 "ratio": self.sd_pred[n] / self.sd_now[n]} for n in self.sd_now]


def make_plan(prior: ArtifactPrior, targets, *, minutes: float = 20.0, ambient: float | None = None, soaks=None,
              dyno: bool = False, criterion: str = "d", heater: bool = True, T_set: float = T_SET,
              comfort_min: float = COMFORT_MIN_DEGC, sequences_override=None, progress=None) -> Plan:
    """Search the design space and return the best :class:`Plan`.

    Parameters
    ----------
    prior : ArtifactPrior
    targets : list of str
        Designable parameters (:data:`calib.design.prior.DESIGNABLE`).
    minutes : float
        Length of the plan (the last part parked if the segments do not fill it).
    ambient : float
        Road: the forecast ambient (degC). Dyno: unused (the cell is at the soak temperature).
    soaks : list of float
        Road: candidate coolant temperatures at the start (default: the ambient, a cold soak). Dyno:
        candidate cell soak temperatures (required).
    heater : bool
        Whether the plan may switch the heater off (False: the climate control runs throughout, for a car
        whose heater the driver cannot switch off).
    sequences_override : list of (segments, pad_s), optional
        A smaller space (tests).
    progress : callable(done, total), optional
    """
    budget = float(minutes) * 60.0
    if not (math.isfinite(budget) and 360.0 <= budget <= 3600.0):
        raise ParameterError(f"--minutes {minutes}: give 6 to 60 minutes")
    if dyno:
        if not soaks:
            raise ParameterError("--dyno: give the candidate cell soak temperatures with --soak-degC")
        starts = [(float(s), float(s)) for s in soaks]
    else:
        if ambient is None:
            raise ParameterError("give the forecast ambient temperature with --ambient (degC)")
        if not math.isfinite(float(ambient)):
            raise ParameterError(f"--ambient {ambient}: give the forecast ambient as a number of degC")
        starts = [(float(s), float(ambient)) for s in (soaks or [ambient])]
    for T_cl0, T_amb in starts:
        if not (-40.0 <= T_amb <= 45.0 and T_amb - 0.01 <= T_cl0 <= 110.0):
            raise ParameterError(f"soak {T_cl0:g} degC at ambient {T_amb:g} degC: the ambient must be within -40 to "
                                 "45 degC and the coolant at the start between the ambient and 110 degC")
    planner = Planner(prior, list(targets), criterion, T_set, comfort_min)
    seqs = sequences_override if sequences_override is not None else sequences(budget, dyno)
    if not seqs:
        raise ParameterError(f"--minutes {minutes}: no sequence of the design space fills it (road: at most 4 "
                             f"segments and {MAX_PAD_S:.0f} s parked at the end; dyno: at most 3 cycles); give "
                             "a shorter plan")
    heaters = list(HEATER_SCHEDULES) if heater else ["auto"]
    done, total = [0], [len(seqs) + STAGE2_KEEP * len(heaters) * len(starts) - 1]

    def ev(d):
        done[0] += 1
        if progress:
            progress(done[0], max(total[0], done[0]))
        value, _ = planner.evaluate(d)
        return value, None  # the simulations are not kept (hundreds of them): the best is simulated again

    T_cl0, T_amb = starts[0]
    stage1 = search([Design(tuple(s), float(p), "auto", T_cl0, T_amb, dyno) for s, p in seqs], ev)
    keep = [s.design for s in stage1 if not s.infeasible][:STAGE2_KEEP]
    if not keep:
        raise IptmError("no feasible plan: every candidate drive broke a constraint (first: "
                        f"{stage1[0].infeasible}); try a longer plan or another ambient")
    cand2 = [Design(d.segments, d.pad_s, h, c, a, dyno) for d in keep for h in heaters for c, a in starts
             if not (h == "auto" and (c, a) == starts[0])]
    total[0] = len(seqs) + len(cand2)
    stage2 = search(cand2, ev)
    allc = [s for s in stage1 + stage2 if not s.infeasible]
    allc.sort(key=lambda s: s.value)
    best = allc[0]
    n_inf = sum(bool(s.infeasible) for s in stage1 + stage2)
    searched = {"stage1_sequences": len(seqs), "stage2_candidates": len(cand2), "infeasible": n_inf,
                "heater_schedules": heaters, "starts": starts}
    _, info = planner.evaluate(best.design)
    return Plan(best.design, info["sim"], info["labels"], info["windows"],
                {t: prior.sd[t] for t in planner.targets}, info["sd"], criterion, best.value, searched,
                {s: prior.noise[s] for s in planner.subs},
                [(s.design.describe(), s.value) for s in allc[:5]])


def plan_frame(plan: Plan):
    """The plan as a table a driver's display or a dyno plays: ``time_s``, ``speed_kph``, ``heater_on``
    (1: climate control running, 0: heater off), ``segment``, and the model's prediction (``engine_on``,
    ``coolant_degC``, ``cabin_degC``, ``soc``)."""
    import pandas as pd

    s = plan.sim
    heat = np.ones(s.t.size, int)
    for a, b in plan.windows:
        heat[(s.t >= a) & (s.t < b)] = 0
    e = np.append(s.e_mode, s.e_mode[-1])
    return pd.DataFrame({"time_s": s.t, "speed_kph": np.round(s.v * 3.6, 3), "heater_on": heat,
                         "segment": plan.labels, "engine_on": (e == ON).astype(int),
                         "coolant_degC": np.round(s.T_cl, 2), "cabin_degC": np.round(s.T_cab, 2),
                         "soc": np.round(s.soc, 4)})


def header_lines(plan: Plan) -> list[str]:
    """What the plan is, for the CSV header and the terminal."""
    out = [f"drive plan: {plan.design.describe()}",
           f"duration {plan.sim.t[-1] / 60:.1f} min; criterion {plan.criterion} = {plan.value:.4g} "
           + ("(log of the targets' posterior volume after over before)" if plan.criterion == "d" else
              "(mean predicted sd over sd now)"),
           "predicted posterior sd after driving it (prior: the artifact's posterior):"]
    for r in plan.table():
        change = f"{100 * (1 - r['ratio']):.0f} % lower" if r["ratio"] <= 0.995 else "no change"
        out.append(f"  {r['name']}: {r['sd_now']:.4g} -> {r['sd_predicted']:.4g} ({change})")
    for s, (sd, how) in plan.noise.items():
        out.append(f"noise of the {s} replay ({CHANNEL[s]}): {sd:.3g} degC, {how}")
    return out


def write_plan_csv(plan: Plan, path) -> None:
    """Write the plan CSV (``#`` header lines, then :func:`plan_frame`) atomically."""
    from calib.fileio import atomic_path

    text = "".join(f"# {line}\n" for line in header_lines(plan)) + plan_frame(plan).to_csv(index=False)
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def plot_plan(plan: Plan, path=None):
    """Speed and heater schedule, predicted coolant and cabin, and the targets' sd now and predicted."""
    import matplotlib.pyplot as plt

    s = plan.sim
    fig, ax = plt.subplots(3, 1, figsize=(10, 8.5), gridspec_kw={"height_ratios": [2, 2, 1.4]})
    m = s.t / 60
    ax[0].plot(m, s.v * 3.6, lw=0.9, color="k")
    for a, b in plan.windows:
        ax[0].axvspan(a / 60, b / 60, color="tab:blue", alpha=0.15, label="heater off")
    edges = [0] + [i for i in range(1, len(plan.labels)) if plan.labels[i] != plan.labels[i - 1]]
    for i in edges:
        ax[0].axvline(m[i], color="0.6", lw=0.6)
        ax[0].text(m[i], ax[0].get_ylim()[1] * 0.95, " " + plan.labels[i], fontsize=7, va="top", rotation=90)
    ax[0].set_ylabel("speed (km/h)")
    ax[0].set_title(plan.design.describe(), fontsize=9)
    if plan.windows:
        h, lab = ax[0].get_legend_handles_labels()
        ax[0].legend(h[:1], lab[:1], loc="upper right", fontsize=8)
    ax[1].plot(m, s.T_cl, label="coolant (model)")
    ax[1].plot(m, s.T_cab, label="cabin (model)")
    ax[1].axhline(plan.design.T_amb, color="0.5", ls=":", label="ambient")
    ax[1].set_ylabel("degC")
    ax[1].set_xlabel("time (min)")
    ax[1].legend(fontsize=8, loc="lower right")
    rows = plan.table()
    x = np.arange(len(rows))
    ax[2].bar(x - 0.2, [1.0] * len(rows), 0.4, label="now (artifact posterior)", color="0.7")
    ax[2].bar(x + 0.2, [r["ratio"] for r in rows], 0.4, label="predicted after the plan", color="tab:green")
    ax[2].set_xticks(x, [r["name"] for r in rows], fontsize=8)
    ax[2].set_ylabel("sd / sd now")
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    if path is not None:
        from calib.fileio import save_figure

        save_figure(fig, path)
    return fig
