"""Reading a log into the arrays every fitter uses, and the compiled replay kernels (coolant, cabin,
fuel, full) that drive the model's equations with logged inputs. See :mod:`calib.fit.validate`."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from calib.model.equations import (CAT, IDLE, OFF, ON, battery, coolant_flows, cabin_rate, fuel_rate, power_split,
                                   traction_power)
from calib.units import RPM


#: Validated channels: name -> (log column, unit).
CHANNEL_METRICS = {
    "soc": ("soc", "-"),
    "coolant_temp": ("coolant_temp_degC", "degC"),
    "cabin_temp": ("cabin_temp_degC", "degC"),
    "fuel_rate": ("fuel_rate_g_per_s", "g/s"),
}


# --------------------------------------------------------------------------------------------------
# reading a log into arrays
# --------------------------------------------------------------------------------------------------
def _col(df, name):
    if name in df.columns:
        return df[name].to_numpy(dtype=float)
    return np.full(len(df), np.nan)


def _fill(a, default=np.nan):
    """Linear interpolation over NaN (held flat at the ends); ``default`` when all NaN."""
    a = np.asarray(a, dtype=float)
    ok = np.isfinite(a)
    if not ok.any():
        return np.full(a.shape, default)
    if ok.all():
        return a.copy()
    idx = np.arange(a.size)
    return np.interp(idx, idx[ok], a[ok])


#: A gap in a logged input is bridged (interpolated, or the nearer sample held) only when it is short: at most
#: FILL_FACTOR times the channel's own sampling interval (the median spacing of its logged bins), and never
#: less than MIN_FILL_S (the resampler's own default gap). Longer gaps stay unknown: a fitter leaves such bins
#: out, it never reads them as zero.
FILL_FACTOR = 2.5
MIN_FILL_S = 5.0


def native_interval(a, dt=1.0) -> float:
    """The channel's sampling interval on the table (s): the median spacing of its finite bins (inf with
    fewer than two). A channel polled every 10 s and binned without interpolation gives 10 s; one the
    resampler already interpolated gives the table step."""
    k = np.flatnonzero(np.isfinite(np.asarray(a, float)))
    return float(np.median(np.diff(k))) * dt if k.size >= 2 else np.inf


def gap_limit(a, dt=1.0) -> float:
    """The longest gap (s, from one logged bin to the next) :func:`fill_short` bridges for this channel."""
    ni = native_interval(a, dt)
    return max(FILL_FACTOR * ni, MIN_FILL_S) if np.isfinite(ni) else MIN_FILL_S


def fill_short(a, dt=1.0, limit_s=None, nearest=False):
    """``a`` with its short gaps bridged and its long ones left NaN.

    A NaN run between two finite bins at most ``limit_s`` apart (default :func:`gap_limit`) takes the linear
    interpolation of the two. With ``nearest`` (a state such as the engine running or not) it takes the value
    of the nearer one, and each sample also holds for half the limit into a longer gap and beyond the first
    and last sample (the state it reports, as far as a poll reaches). Everything else stays NaN: nothing is
    invented across a long gap, nor (for values) before the first or after the last sample.
    """
    a = np.asarray(a, float)
    ok = np.isfinite(a)
    if ok.all() or not ok.any():
        return a.copy()
    lim = gap_limit(a, dt) if limit_s is None else float(limit_s)
    k = np.flatnonzero(ok)
    i = np.flatnonzero(~ok)
    out = a.copy()
    j = np.searchsorted(k, i)  # k[j - 1] < i < k[j]
    prev = np.where(j > 0, k[np.maximum(j - 1, 0)], -1)
    nxt = np.where(j < k.size, k[np.minimum(j, k.size - 1)], -1)
    inner = (prev >= 0) & (nxt >= 0)
    span = (nxt - prev) * dt
    sel = inner & (span <= lim + 1e-9)
    if sel.any():
        ii, p0, p1 = i[sel], prev[sel], nxt[sel]
        if nearest:
            out[ii] = np.where(ii - p0 <= p1 - ii, a[p0], a[p1])
        else:
            w = (ii - p0) / (p1 - p0)
            out[ii] = (1.0 - w) * a[p0] + w * a[p1]
    if nearest:
        near_prev = ~sel & (prev >= 0) & ((i - prev) * dt <= 0.5 * lim + 1e-9)
        near_next = ~sel & (nxt >= 0) & ((nxt - i) * dt <= 0.5 * lim + 1e-9)
        out[i[near_next]] = a[nxt[near_next]]
        out[i[near_prev]] = a[prev[near_prev]]  # the earlier sample where both are near (a gap just over the limit)
    return out


def known_runs(known, min_len=1):
    """``[(start, stop)]`` of the runs of True in ``known`` with at least ``min_len`` bins."""
    k = np.asarray(known, bool)
    d = np.diff(np.concatenate([[0], k.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops) if b - a >= min_len]


#: Shortest run of bins with every input known that an output-error fit simulates (s): the state cannot be
#: carried across a bin whose input is unknown, so each run starts from its own initial temperature.
MIN_SEGMENT_S = 60.0


def input_segments(known, T_out, dt=1.0, min_s=MIN_SEGMENT_S, min_obs=3):
    """``[(start, stop)]`` of the runs of bins where every input of an output-error replay is known, at least
    ``min_s`` long and with at least ``min_obs`` logged outputs (finite ``T_out``)."""
    ok = np.isfinite(np.asarray(T_out, float))
    return [(a, b) for a, b in known_runs(known, max(int(round(min_s / dt)), 2)) if ok[a:b].sum() >= min_obs]


#: A bin at the catalyst-heating speed counts as catalyst heating within this multiple of ``t_cat_s`` after
#: the engine first turns in the log (the engine control heats the catalyst once, after a cold start).
CAT_WINDOW = 2.0


def catalyst_heating(n_rpm, no_output, mp, dt=1.0, T_cl0=None):
    """True where a log shows catalyst heating (:mod:`calib.model.catalyst`): the engine turns within 10 % of
    the catalyst-heating speed with no output (``no_output``), in the first ``CAT_WINDOW t_cat_s`` after it
    first turns in the log. All False for a car without catalyst heating (``t_cat_s`` 0) and for a log whose
    coolant at the start, ``T_cl0`` (None: not logged), is at or above ``T_cat_degC``."""
    n = np.asarray(n_rpm, float)
    out = np.zeros(n.shape, bool)
    n_cat = mp.w_cat / RPM
    turning = np.flatnonzero(np.nan_to_num(n) >= N_STOPPED_RPM)
    if mp.t_cat <= 0.0 or not turning.size or (T_cl0 is not None and np.isfinite(T_cl0) and T_cl0 >= mp.T_cat):
        return out
    k0 = turning[0]
    k1 = min(n.size, k0 + int(math.ceil(CAT_WINDOW * mp.t_cat / dt)) + 1)
    with np.errstate(invalid="ignore"):
        out[k0:k1] = (np.abs(n[k0:k1] - n_cat) < 0.1 * n_cat) & np.asarray(no_output, bool)[k0:k1]
    return out


def engine_mode(n_rpm, tau_Nm, n_idle_rpm=1000.0, cat=None):
    """Engine mode per sample from logged speed and torque: 1 off, 2 idle, 3 on, 4 catalyst heating,
    0 unknown/mixed.

    Off: speed below 150 rpm. Idle: speed within 15 % of the idle speed and torque below 2 N m. On: torque
    above 2 N m and speed above 500 rpm. Catalyst heating where ``cat`` says so (:func:`catalyst_heating`).
    Anything else (a 1 s bin that straddles a start or stop) is 0.
    """
    n = np.asarray(n_rpm, float)
    tq = np.asarray(tau_Nm, float)
    mode = np.zeros(n.shape, dtype=np.int64)
    mode[n < 150.0] = OFF
    mode[(np.abs(n - n_idle_rpm) < 0.15 * n_idle_rpm) & (np.abs(tq) < 2.0)] = IDLE
    mode[(tq >= 2.0) & (n > 500.0)] = ON
    if cat is not None:
        mode[np.asarray(cat, bool)] = CAT
    mode[~(np.isfinite(n) & np.isfinite(tq))] = 0
    return mode


def stable_mode(mode):
    """True where the mode is known and the same at k-1, k and k+1 (bins not straddling a transition)."""
    m = np.asarray(mode)
    s = m > 0
    s[1:] &= m[1:] == m[:-1]
    s[:-1] &= m[:-1] == m[1:]
    return s


def operating_point(n_rpm, tau_Nm, mode, stable, mp):
    """Split every 1 s bin into engine-on (power ``P_on``), idle and off fractions.

    A resampled bin holds the *means* of speed and torque over the bin, so ``mean(n) * mean(tau)`` is
    not the engine power when the operating point changed within it (an engine start or stop, or a
    controller that toggles the engine every second). The engine is taken to follow the model's optimal
    operating line (OOL) when at least half of the engine-on bins have their mean speed within 0.5 % of
    ``w_ool(n tau)``. Then:

    - a bin on the line is one operating point, its power read from its mean speed along the line;
    - a bin near the line (torque within 10 % of the line's at its mean speed) mixes nearby on-line
      points: its mean power is read from its mean speed;
    - a bin far off the line is a mixture: the engine ran on the line for a fraction ``f`` of the bin and was
      off or idling (as a neighbour bin) for the rest; ``f`` and the power solve
      ``n_mean = f w_ool(P) + (1 - f) n_other`` and ``tau_mean = f P / w_ool(P)``; when no such
      solution exists the bin mixes two on-line points and its power is read from its mean speed.

    An engine that does not follow the line (a real engine with its own calibration) keeps
    ``P = n tau``, with the mixture solution only for bins next to an off/idle bin.

    Returns
    -------
    f_on, P_on, f_idle : ndarray
    """
    w = np.asarray(n_rpm, float) * RPM
    tq = np.asarray(tau_Nm, float)
    n = w.size
    f_on = np.zeros(n)
    P_on = np.zeros(n)
    f_idle = np.zeros(n)
    valid = np.isfinite(w) & np.isfinite(tq)
    onb = valid & (tq >= 2.0) & (w > 500 * RPM)
    increasing = bool(np.all(np.diff(mp.w_ool) > 0))
    dev = np.full(n, np.inf)
    dev[onb] = np.abs(np.interp(w[onb] * tq[onb], mp.P_ool, mp.w_ool) / w[onb] - 1.0)
    follows = increasing and onb.sum() >= 10 and np.mean(dev[onb] < OOL_TOL) >= 0.5
    for k in range(n):
        wk, tk = w[k], tq[k]
        if not valid[k] or wk < 50 * RPM:
            continue
        if tk < 1.0:
            f_idle[k] = min(wk / mp.w_idle, 1.0)
            continue
        nb = [mode[j] for j in (k - 1, k + 1) if 0 <= j < n]
        if follows:
            P_w = np.interp(wk, mp.w_ool, mp.P_ool)  # power on the line at the mean speed
            if dev[k] < OOL_TOL or abs(wk * tk / max(P_w, 1.0) - 1.0) < 0.1:
                # on the line, or two nearby on-line points: the mean speed gives the mean power
                f_on[k], P_on[k] = 1.0, P_w
                continue
        elif (stable[k] and mode[k] == ON) or not any(m in (OFF, IDLE) for m in nb):
            f_on[k], P_on[k] = 1.0, wk * tk
            continue
        w_o = mp.w_idle if IDLE in nb else 0.0
        f, P = _mixture(wk, tk, w_o, mp)
        if f < 0:
            f_on[k] = 1.0
            P_on[k] = np.interp(wk, mp.w_ool, mp.P_ool) if follows else wk * tk
            continue
        f_on[k], P_on[k] = f, P
        if w_o > 0:
            f_idle[k] = 1.0 - f
    return f_on, P_on, f_idle


def _mixture(wk, tk, w_o, mp):
    """(f, P) of a bin mixing the OOL point P (fraction f) with speed w_o at zero torque; (-1, 0) if none."""

    def g(f):
        om = (wk - (1.0 - f) * w_o) / f
        P = tk * om / f
        return om - np.interp(P, mp.P_ool, mp.w_ool), P

    # the root with the largest on-fraction (and a feasible power): scan down from f = 1
    prev_f, prev_g = 1.0, g(1.0)[0]
    lo = hi = -1.0
    for fc in np.linspace(1.0, 0.05, 96)[1:]:
        gc, Pc = g(fc)
        if Pc > mp.P_e_max:
            break
        if gc * prev_g <= 0.0:
            lo, hi = fc, prev_f
            break
        prev_f, prev_g = fc, gc
    if lo < 0:
        return -1.0, 0.0
    glo = g(lo)[0]
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        gm = g(mid)[0]
        if gm * glo > 0:
            lo, glo = mid, gm
        else:
            hi = mid
    f = 0.5 * (lo + hi)
    return f, g(f)[1]


OOL_TOL = 0.005


@dataclass
class LogArrays:
    """One log as numpy arrays on its uniform time base (NaN where not logged)."""

    name: str
    dt: float
    t: np.ndarray
    ch: dict = field(default_factory=dict)  # raw channels (NaN where missing)
    mode: np.ndarray = None
    stable: np.ndarray = None
    P_e: np.ndarray = None  # W
    Q_heat: np.ndarray = None  # W, heat drawn by the heater core (logged or from vent temp)
    T_in: np.ndarray = None  # heater inlet air
    heater_source: str = ""
    f_on: np.ndarray = None  # fraction of each bin with the engine on, at power P_on
    P_on: np.ndarray = None
    f_idle: np.ndarray = None  # fraction of each bin with the engine turning without output (idle or catalyst heating)
    f_cat: np.ndarray = None  # the part of f_idle heating the catalyst (fuel W_cat instead of the idle fuel)

    engine_source: str = ""  # how the engine operating point was obtained ("" when it could not be)
    battery_source: str = ""  # how the battery terminal power was obtained
    P_bat: np.ndarray = None  # W, battery terminal power (logged, V*I, or NaN)
    known: np.ndarray = None  # bins whose engine state a logged cue gives (False: unknown, left out of fits)
    inferred: dict = field(default_factory=dict)  # input -> how it was inferred from a balance
    sampled: dict = field(default_factory=dict)  # channel -> rows that hold a logged sample (where recorded)

    def logged(self, name) -> np.ndarray:
        """Channel ``name`` in the rows that hold one of its samples: as :attr:`ch`, with the rows the resampler
        filled by interpolation NaN where the log records which rows hold samples (``DriveLog.sampled``).
        Fitters take their outputs (fuel rate, coolant, cabin temperature, SOC) from here: residuals only where
        the output was logged."""
        x = self.ch[name]
        m = self.sampled.get(name)
        if m is None or len(m) != len(x):
            return x
        return np.where(np.asarray(m, bool), x, np.nan)

    def has(self, *names) -> bool:
        return all(np.isfinite(self.ch.get(n, np.array([np.nan]))).any() for n in names)

    def inputs(self) -> dict:
        """What the replay/fits take as inputs and where each came from ("" = not available)."""
        return {"engine": self.engine_source, "battery power": self.battery_source,
                "heater": self.heater_source}


#: Fuel rate above which an engine counts as running when only the fuel rate says so (g/s).
FUEL_RUNNING_G_PER_S = 0.03
#: Engine power above which a logged engine power counts as "on" (below it: idle when fuel flows).
P_ON_MIN_W = 500.0

LOG_CHANNELS = ["speed_mps", "bat_current_A", "bat_voltage_V", "bat_power_W", "soc", "bat_temp_degC",
                "engine_speed_rpm", "engine_torque_Nm", "engine_power_W", "fuel_rate_g_per_s",
                "coolant_temp_degC", "bay_temp_degC", "ambient_temp_degC", "cabin_temp_degC", "heater_power_W",
                "vent_temp_degC", "blower_flow_kg_per_s", "grade_rad"]


@njit(cache=True)
def engine_power_from_balance(p, v, P_bat, grade, dt):
    """Engine power from the power balance at the wheels (s.2 inverted): traction demand from the logged
    speed and grade, less what the motor delivers from the logged battery power (less auxiliaries)."""
    n = v.shape[0]
    P = np.zeros(n)
    for k in range(n):
        vn = v[k + 1] if k + 1 < n else v[k]
        Pt = traction_power(p, v[k], vn, grade[k], dt)
        Pbm = P_bat[k] - p.P_aux
        P_em = p.eta_em * Pbm if Pbm >= 0.0 else Pbm / p.eta_em
        Pe = (Pt - P_em) / p.eta_mech
        P[k] = min(max(Pe, 0.0), p.P_e_max)
    return P


@njit(cache=True)
def current_from_power(p, soc, P_bat, T_bat):
    """Battery current from terminal power and the OCV/resistance tables (eq. 1 solved for I); NaN where
    the power exceeds what the pack can give."""
    n = soc.shape[0]
    I = np.empty(n)
    for k in range(n):
        I[k] = battery(p, soc[k], P_bat[k], T_bat[k])[0]
    return I


#: Engine speed below which a logged engine speed says the engine is stopped (rpm).
N_STOPPED_RPM = 150.0
#: Values of ``heater=`` (:func:`log_arrays`, :func:`calib.fit.driver.calibrate`): None reads the heater heat
#: from what the log has (logged, vent temperature and blower flow, the cabin balance) and estimates it where
#: the log has none of these; "off" declares it zero wherever it is not logged; "estimate" estimates it
#: wherever it is not logged (never inferred from the cabin balance).
HEATER_CHOICES = (None, "off", "estimate")
#: ``LogArrays.heater_source`` of a heater declared off.
HEATER_OFF = "none: declared off (heater='off')"


def _nearest_distance(ok):
    """Per bin, the distance (in bins) to the nearest True of ``ok`` (inf without any)."""
    k = np.flatnonzero(ok)
    n = ok.size
    if not k.size:
        return np.full(n, np.inf)
    i = np.arange(n)
    j = np.clip(np.searchsorted(k, i), 0, k.size - 1)
    d = np.abs(k[j] - i).astype(float)
    jp = np.maximum(j - 1, 0)
    return np.minimum(d, np.abs(k[jp] - i))


def running_cue(ch, dt=1.0):
    """Whether the engine runs, bin by bin, from every cue the log has.

    Cues: engine speed (running at or above :data:`N_STOPPED_RPM`, else stopped), fuel rate (running above
    :data:`FUEL_RUNNING_G_PER_S`, else stopped; a fuel rate estimated from MAF counts the same), engine power
    (running above :data:`P_ON_MIN_W`; below it, it cannot tell idle from off). Each cue counts where it was
    logged and, from its nearest sample, across its short gaps (:func:`fill_short`): a channel polled every
    10 s still says what the engine did between two polls, and a long dropout says nothing. A bin is running
    where any cue says so, stopped where the cues that reach it all say stopped, unknown (0) where none
    reaches it: a bin is never "off" for want of a sample.

    Returns
    -------
    state : ndarray of int
        +1 running, -1 stopped, 0 unknown.
    cues : list of str
        The channels that gave a cue.
    """
    n = len(next(iter(ch.values())))
    run = np.zeros(n, bool)
    stop_seen = np.zeros(n, bool)
    cues = []
    for name, on_above in (("engine_speed_rpm", N_STOPPED_RPM - 1e-9), ("fuel_rate_g_per_s", FUEL_RUNNING_G_PER_S),
                           ("engine_power_W", P_ON_MIN_W)):
        x = ch.get(name)
        if x is None or not np.isfinite(x).any():
            continue
        cues.append(name)
        ok = np.isfinite(x)
        c = np.full(n, np.nan)
        c[ok] = np.where(x[ok] > on_above, 1.0, -1.0)
        c = fill_short(c, dt, gap_limit(x, dt), nearest=True)
        run |= c == 1.0
        if name != "engine_power_W":  # a low engine power says nothing about idle or off
            stop_seen |= c == -1.0
    state = np.where(run, 1, np.where(stop_seen, -1, 0)).astype(np.int64)
    return state, cues


def log_arrays(log, mp, cabin_balance=True, heater=None) -> LogArrays:
    """Extract the arrays the fitters and the replay need from a :class:`calib.drivelog.DriveLog`.

    Inputs a log may give in several ways, in order of preference:

    - engine operating point: speed x torque; else the logged engine power (on above :data:`P_ON_MIN_W`);
      else *inferred* from the power balance (traction demand of the logged speed minus the motor's share of
      the battery power; on above :data:`P_ON_MIN_W` where the engine runs). Whether the engine runs comes
      from every cue the log has (:func:`running_cue`: engine speed, fuel rate, engine power); a bin no cue
      reaches is unknown (mode 0, ``known`` False), never "off";
    - battery terminal power: ``bat_power_W``; else voltage x current;
    - heater heat: ``heater_power_W``; else ``W_bl c_p (T_vent - T_in)``; else, with ``heater`` None and
      ``cabin_balance``, *inferred* from the cabin heat balance (eq. 10 solved for the heater heat with the
      given cabin parameters); with ``heater="off"`` zero (declared); otherwise none (``heater_source`` "").

    Inputs are bridged across short gaps only (:func:`fill_short`); across a long one they stay NaN. Everything
    inferred is named in ``la.inferred``.
    """
    if heater not in HEATER_CHOICES:
        from calib.errors import IptmError

        raise IptmError(f"heater={heater!r}: give 'off' (the heater did not run), 'estimate' (estimate its heat) "
                        "or None (read it from the log where it can be)")
    df = log.data
    ch = {n: _col(df, n) for n in LOG_CHANNELS}
    t = df.index.to_numpy(dtype=float)
    dt = float(log.dt)
    la = LogArrays(name=log.label() if hasattr(log, "label") else "log", dt=dt, t=t, ch=ch,
                   sampled=dict(getattr(log, "sampled", None) or {}))
    n_idle = mp.w_idle / RPM
    # battery power
    if la.has("bat_power_W"):
        la.P_bat = fill_short(ch["bat_power_W"], dt)
        la.battery_source = "bat_power_W"
    elif la.has("bat_current_A", "bat_voltage_V"):
        la.P_bat = fill_short(ch["bat_current_A"], dt) * fill_short(ch["bat_voltage_V"], dt)
        la.battery_source = "bat_voltage_V x bat_current_A"
    else:
        la.P_bat = np.full(t.size, np.nan)
    # engine operating point
    if la.has("engine_speed_rpm", "engine_torque_Nm"):
        with np.errstate(invalid="ignore"):
            cat = catalyst_heating(ch["engine_speed_rpm"], np.abs(ch["engine_torque_Nm"]) < 2.0, mp, dt,
                                   first_valid_mean(ch["coolant_temp_degC"], 5, np.nan))
        la.mode = engine_mode(ch["engine_speed_rpm"], ch["engine_torque_Nm"], n_idle, cat)
        la.stable = stable_mode(la.mode)
        la.P_e = np.where(la.mode == ON, ch["engine_speed_rpm"] * RPM * ch["engine_torque_Nm"], 0.0)
        la.P_e[~np.isfinite(la.P_e)] = np.nan
        la.f_on, la.P_on, la.f_idle = operating_point(ch["engine_speed_rpm"], ch["engine_torque_Nm"], la.mode,
                                                      la.stable, mp)
        la.f_cat = np.where(la.mode == CAT, la.f_idle, 0.0)
        la.engine_source = "engine_speed_rpm x engine_torque_Nm"
        la.known = np.isfinite(ch["engine_speed_rpm"]) & np.isfinite(ch["engine_torque_Nm"])
    else:
        P = None
        if la.has("engine_power_W"):
            P = fill_short(ch["engine_power_W"], dt)
            la.engine_source = "engine_power_W"
        elif la.has("speed_mps") and la.battery_source:
            grade = _fill(ch["grade_rad"], 0.0)  # grade 0 unless logged (docs/model.md s.1)
            v = fill_short(ch["speed_mps"], dt)
            P = engine_power_from_balance(mp, np.nan_to_num(v), np.nan_to_num(la.P_bat), grade, dt)
            bad = ~np.isfinite(v) | ~np.isfinite(la.P_bat)
            bad[:-1] |= ~np.isfinite(v[1:])
            P[bad] = np.nan
            la.engine_source = "inferred from the power balance (speed_mps, " + la.battery_source + ")"
            la.inferred["engine power"] = ("traction demand of the logged speed minus the motor's share of the "
                                           "battery power (road load, mass and efficiencies from the parameter set)")
        if P is None:
            la.mode = np.zeros(t.size, np.int64)
            la.P_e = np.full(t.size, np.nan)
            la.known = np.zeros(t.size, bool)
        else:
            # the cues where they were logged: a polled channel's own rate sets how far each poll reaches
            state, cues = running_cue({n: la.logged(n) for n in ch}, dt)
            logged_power = la.engine_source == "engine_power_W"
            if logged_power:
                on = P > P_ON_MIN_W
            elif cues:
                on = (P > P_ON_MIN_W) & (state > 0)
            else:
                on = P > 2000.0
            idle = (state > 0) & ~on & np.isfinite(P)
            if logged_power and not (set(cues) - {"engine_power_W"}):
                off = ~on & np.isfinite(P)
                la.inferred["engine mode"] = (f"on where engine_power_W > {P_ON_MIN_W:g} W; idle cannot be told from "
                                              "off (no fuel rate or engine speed logged)")
            elif not cues:
                off = ~on & np.isfinite(P)
                la.inferred["engine mode"] = ("on where the inferred engine power exceeds 2 kW (no fuel rate or engine "
                                              "speed logged)")
            else:
                off = state < 0
                la.inferred["engine mode"] = (
                    f"running where {' or '.join(cues)} says so (engine speed >= {N_STOPPED_RPM:g} rpm, fuel rate > "
                    f"{FUEL_RUNNING_G_PER_S:g} g/s, engine power > {P_ON_MIN_W:g} W; each held from its nearest "
                    f"sample across short gaps); on above {P_ON_MIN_W:g} W of engine power, else idle")
            la.mode = np.where(on, ON, np.where(idle, IDLE, np.where(off, OFF, 0))).astype(np.int64)
            if la.has("engine_speed_rpm"):
                # running without output at the catalyst-heating speed after the start: catalyst heating
                cat = catalyst_heating(fill_short(ch["engine_speed_rpm"], dt), idle, mp, dt,
                                       first_valid_mean(ch["coolant_temp_degC"], 5, np.nan))
                if cat.any():
                    la.mode[cat] = CAT
                    la.inferred["catalyst heating"] = (f"{int(cat.sum()) * dt:.0f} s running without output at "
                                                       f"{mp.w_cat / RPM:.0f} rpm after the start")
            la.P_e = np.where(on, P, np.where(off | idle, 0.0, np.nan))
            la.known = la.mode > 0
            unknown = int((~la.known).sum())
            if unknown and cues:
                la.inferred["engine mode"] += (f"; {unknown} bin(s) ({unknown * dt:.0f} s) that no cue reaches are "
                                               "unknown and left out")
        la.stable = stable_mode(la.mode)
        la.f_on = (la.mode == ON).astype(float)
        la.P_on = np.where(la.mode == ON, np.nan_to_num(la.P_e), 0.0)
        la.f_idle = np.isin(la.mode, (IDLE, CAT)).astype(float)
        la.f_cat = (la.mode == CAT).astype(float)
    T_amb = ch["ambient_temp_degC"]
    T_cab = fill_short(ch["cabin_temp_degC"], dt)
    # the heater inlet air: recirculated cabin air and fresh air; without a cabin reading, the ambient
    T_in = mp.recirc * T_cab + (1.0 - mp.recirc) * T_amb if la.has("cabin_temp_degC") else T_amb.copy()
    la.T_in = T_in
    if np.isfinite(ch["heater_power_W"]).any():
        la.Q_heat = fill_short(ch["heater_power_W"], dt)
        la.heater_source = "heater_power_W"
    elif np.isfinite(ch["vent_temp_degC"]).any() and np.isfinite(ch["blower_flow_kg_per_s"]).any():
        Ti = fill_short(T_in, dt)
        la.Q_heat = np.maximum(fill_short(ch["blower_flow_kg_per_s"], dt) * mp.cp_air
                               * (fill_short(ch["vent_temp_degC"], dt) - Ti), 0.0)
        la.heater_source = "vent_temp_degC + blower_flow_kg_per_s"
    elif heater == "off":
        la.Q_heat = np.zeros(t.size)
        la.heater_source = HEATER_OFF
    elif heater is None and cabin_balance and la.has("cabin_temp_degC", "ambient_temp_degC"):
        la.Q_heat = heater_from_cabin(mp, t, ch["cabin_temp_degC"], ch["ambient_temp_degC"])
        la.heater_source = "inferred from the cabin heat balance"
        la.inferred["heater power"] = ("C_cab dT_cab/dt - UA_cab (T_amb - T_cab) - Q_sun from the logged cabin "
                                       "and ambient temperatures (60 s smoothing; cabin parameters from the set)")
    else:
        la.Q_heat = np.full(t.size, np.nan)
    return la


def logged_column(log, name) -> np.ndarray:
    """Column ``name`` of a log (NaN where absent) in the rows that hold one of its samples, where the log
    records them (``DriveLog.sampled``); see :meth:`LogArrays.logged`."""
    x = _col(log.data, name)
    m = (getattr(log, "sampled", None) or {}).get(name)
    return x if m is None or len(m) != len(x) else np.where(np.asarray(m, bool), x, np.nan)


def filled_note(log, name) -> str:
    """A warning when the resampler filled ``name`` into many more rows than it has samples and the log does not
    say which rows hold them (then interpolated values count as logged ones); "" otherwise."""
    if name in (getattr(log, "sampled", None) or {}):
        return ""
    kept = (getattr(log.meta, "channel_counts", None) or {}).get(name, {}).get("kept")
    if not kept or name not in log.data:
        return ""
    rows = int(np.isfinite(log.data[name].to_numpy(dtype=float)).sum())
    if rows <= 1.5 * kept + 5:
        return ""
    return (f"{name}: {kept} samples filled into {rows} rows by interpolation, and the log does not record which rows "
            "hold them: the interpolated values are used as if logged")


def fuel_label(log) -> str:
    """How the log's fuel rate was obtained: the channel, and the estimate's description where it is one
    (fuel from the MAF, ``LogMeta.estimated``), so no fit presents an estimate as a measured rate."""
    how = (getattr(log.meta, "estimated", None) or {}).get("fuel_rate_g_per_s")
    return f"fuel_rate_g_per_s ({how})" if how else "fuel_rate_g_per_s"


def heater_from_cabin(mp, t, T_cab, T_amb, window_s=60.0):
    """Heater heat from the cabin balance (eq. 10 solved for Q_heat), >= 0. The cabin temperature is
    smoothed over ``window_s`` (a local linear fit's slope) so its quantisation does not dominate the
    derivative. NaN where a window reaches into a long gap of either temperature."""
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    # NaN across long gaps of either temperature: the window's sums carry it, so no heat is inferred there
    Tc = fill_short(T_cab, dt)
    Ta = fill_short(T_amb, dt)
    m = max(3, int(round(window_s / dt)) | 1)
    k = np.arange(m) - m // 2
    # slope of a centred least-squares line = convolution with k / sum(k^2)
    w = k[::-1] / (np.sum(k * k) * dt)
    pad = np.pad(Tc, m // 2, mode="edge")
    slope = np.convolve(pad, w, mode="valid")
    sm = np.convolve(pad, np.ones(m) / m, mode="valid")
    Q = mp.C_cab * slope - mp.UA_cab * (Ta - sm) - mp.Q_sun
    return np.maximum(Q, 0.0)


def first_valid_mean(a, n=5, default=np.nan):
    """Mean of the first ``n`` valid samples (less sensitive to noise than one sample)."""
    a = np.asarray(a, float)
    i = np.flatnonzero(np.isfinite(a))
    return float(np.mean(a[i[:n]])) if i.size else default


# --------------------------------------------------------------------------------------------------
# compiled output-error / replay loops
# --------------------------------------------------------------------------------------------------
@njit(cache=True)
def coolant_replay(p, T0, dt, T_amb, W_f, P_e, Q_heat):
    """Coolant temperature (eq. 3) from logged fuel rate, engine power, heater heat and ambient."""
    n = T_amb.shape[0]
    T = np.empty(n)
    T[0] = T0
    for k in range(n - 1):
        d = coolant_flows(p, T[k], T_amb[k], p.LHV * W_f[k], P_e[k], Q_heat[k])[0]
        T[k + 1] = T[k] + dt * d
    return T


@njit(cache=True)
def coolant_replay_heater(p, T0, dt, T_amb, W_f, P_e, Q_heat, q_heat, dT_full):
    """:func:`coolant_replay` with an unlogged heater drawing ``q_heat`` (W) once the simulated coolant is
    ``dT_full`` (K) above the ambient, and in proportion below (a heater core passes heat in proportion to
    the coolant's excess over the air it heats), on top of ``Q_heat``."""
    n = T_amb.shape[0]
    T = np.empty(n)
    T[0] = T0
    for k in range(n - 1):
        x = (T[k] - T_amb[k]) / dT_full
        q = Q_heat[k] + q_heat * min(max(x, 0.0), 1.0)
        d = coolant_flows(p, T[k], T_amb[k], p.LHV * W_f[k], P_e[k], q)[0]
        T[k + 1] = T[k] + dt * d
    return T


@njit(cache=True)
def cabin_replay(p, T0, dt, T_amb, Q_heat):
    """Cabin temperature (eq. 10) from logged heater heat and ambient."""
    n = T_amb.shape[0]
    T = np.empty(n)
    T[0] = T0
    for k in range(n - 1):
        d = cabin_rate(p, T[k], T_amb[k], Q_heat[k])[0]
        T[k + 1] = T[k] + dt * d
    return T


@njit(cache=True)
def fuel_replay(p, mode, P_e, T_cl):
    """Fuel rate (eqs. 4-5) for logged engine modes and powers at given coolant temperatures."""
    n = mode.shape[0]
    W = np.empty(n)
    for k in range(n):
        W[k] = fuel_rate(p, mode[k], P_e[k], T_cl[k]) if mode[k] > 0 else np.nan
    return W


def full_replay(p, dt, soc0, T_cl0, T_cab0, f_on, P_on, f_idle, P_bat, T_bat, T_amb, Q_heat, f_cat=None):
    """SOC, coolant, cabin and fuel rate from logged inputs (the validation simulation). ``f_cat``: the part of
    ``f_idle`` heating the catalyst (:attr:`LogArrays.f_cat`; None: none)."""
    f_cat = np.zeros(np.shape(f_on)) if f_cat is None else np.asarray(f_cat, float)
    return _full_replay(p, dt, soc0, T_cl0, T_cab0, f_on, P_on, f_idle, P_bat, T_bat, T_amb, Q_heat, f_cat)


@njit(cache=True)
def _full_replay(p, dt, soc0, T_cl0, T_cab0, f_on, P_on, f_idle, P_bat, T_bat, T_amb, Q_heat, f_cat):
    n = f_on.shape[0]
    soc = np.empty(n)
    T_cl = np.empty(n)
    T_cab = np.empty(n)
    W = np.empty(n)
    soc[0], T_cl[0], T_cab[0] = soc0, T_cl0, T_cab0
    for k in range(n):
        W[k] = (f_on[k] * fuel_rate(p, ON, P_on[k], T_cl[k]) + (f_idle[k] - f_cat[k]) * fuel_rate(p, IDLE, 0.0, T_cl[k])
                + f_cat[k] * fuel_rate(p, CAT, 0.0, T_cl[k]))
        P_e = f_on[k] * P_on[k]
        if k == n - 1:
            break
        I, V, U, R, code = battery(p, soc[k], P_bat[k], T_bat[k])
        if not np.isfinite(I):
            I = P_bat[k] / U
        soc[k + 1] = soc[k] - I * dt / p.C_bat_As
        d_cl = coolant_flows(p, T_cl[k], T_amb[k], p.LHV * W[k], P_e, Q_heat[k])[0]
        T_cl[k + 1] = T_cl[k] + dt * d_cl
        d_cab = cabin_rate(p, T_cab[k], T_amb[k], Q_heat[k])[0]
        T_cab[k + 1] = T_cab[k] + dt * d_cab
    return soc, T_cl, T_cab, W


@njit(cache=True)
def _split_battery_power(p, v, P_e, dt):
    """Battery terminal power from the power split when V and I are not logged."""
    n = v.shape[0]
    P = np.empty(n)
    for k in range(n):
        vn = v[k + 1] if k + 1 < n else v[k]
        Pt = traction_power(p, v[k], vn, 0.0, dt)
        if P_e[k] > 0.0:
            P_em = Pt - p.eta_mech * P_e[k]
            Pbm = P_em / p.eta_em if P_em >= 0.0 else P_em * p.eta_em
        else:
            Pbm = power_split(p, OFF, 0.0, Pt)[1]
        P[k] = Pbm + p.P_aux
    return P
