"""The stock-like rule-based energy management (docs/optimization.md s.3).

A load-levelling controller in the style of Liu & Peng (2005): the engine turns on above a wheel-power
threshold, below a SOC threshold, or when the battery alone cannot meet the demand; when on it runs at
demand plus a SOC-recovery term, never below a load-levelling minimum; it turns off below a lower threshold
(hysteresis) once it has run a minimum time. Thermal rules: below ``T_idle_degC`` the engine idles rather
than stopping (Tashiro 2016), and while heat is requested it keeps running until the coolant reaches
``T_heat_on_degC`` (the production Prius keeps its engine on while the coolant is cold and the heater or
defroster is on; docs/cold_start.md). The heater requests a fixed demand.

Cold start as the production car runs it (docs/cold_start.md): catalyst heating after a cold start belongs
to the plant (:mod:`calib.model.catalyst`; the simulator runs it before this controller's commands apply);
during the warm-up (a drive started with the coolant below ``T_warm_degC``, until it first reaches it) the SOC
target is ``soc_warmup`` and an engine held on by the thermal rules charges towards it rather than idling; a
warm engine cooled later by the heater is not warming up (it runs for heat by the thermal rules, not to
charge); above the SOC target the start threshold rises by ``k_on_W`` per unit SOC, so the charge is spent.

It lives in ``calib`` because it is also the plant's own controller when logs are synthesised; the
per-scenario threshold tuning lives in :mod:`optimize.tuning`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

from calib.model.equations import IDLE, OFF, ON, battery_ocv_r

#: share of the battery's matched-load power U^2/(4 R) the controller asks of a cold pack: at that point
#: the terminal voltage is half the open-circuit voltage, and the simulator refuses anything beyond it
DELIVERABLE_SHARE = 0.9


@dataclass
class RuleParams:
    """Thresholds of the rule-based controller (tuned per scenario by :mod:`optimize.tuning`)."""

    P_on_W: float = 9000.0  # wheel power above which the engine starts
    P_off_W: float = 4000.0  # wheel power below which it may stop (hysteresis)
    soc_low: float = 0.50  # engine forced on below this SOC
    soc_target: float = 0.60  # SOC-recovery set point
    k_soc_W: float = 150e3  # recovery gain: W of extra engine power per unit SOC below target
    P_e_min_W: float = 10000.0  # load levelling: engine never runs below this (W)
    t_min_on_s: float = 8.0  # minimum on-time
    T_idle_degC: float = 40.0  # thermal rule: idle instead of off below this coolant temperature
    T_heat_on_degC: float = 55.0  # heat requested: the engine keeps running below this coolant temperature
    Q_heat_W: float = 1500.0  # heater demand
    k_on_W: float = 100e3  # start threshold rises by this many W per unit SOC above target (spend a surplus)
    soc_warmup: float = 0.72  # SOC target while the coolant is below T_warm_degC (charge during warm-up)
    T_warm_degC: float = 70.0  # coolant temperature that ends the warm-up

    def to_dict(self) -> dict:
        """The thresholds as a JSON-able dict."""
        return asdict(self)


class RuleBasedController:
    """Callable ``(k, soc, T_cl, T_cab, P_trac) -> (e_mode, P_bat_mg, Q_heat_cmd)`` with memory.

    Parameters
    ----------
    mp : ModelParams
        Compiled parameters (for efficiencies and limits).
    rp : RuleParams
    T_bat : float, optional
        Battery temperature (degC; default the resistance table's reference). The simulator sets
        :attr:`T_bat` every step from the drive's battery temperature: a cold pack's internal resistance
        limits what it can deliver below ``P_bat_max`` (:meth:`discharge_limit_W`).
    """

    def __init__(self, mp, rp: RuleParams | None = None, T_bat: float | None = None):
        self.mp = mp
        self.rp = rp or RuleParams()
        self.T_bat = float(mp.T_bat_ref if T_bat is None else T_bat)
        self.reset()

    def reset(self) -> None:
        """Forget the engine state and timers (call before a new drive)."""
        self.on = False
        self.on_time = 0.0
        # heat the climate control asks for this step; a wrapper that sets its own request (a cabin
        # thermostat) assigns it before calling, so the engine-on rule sees the real request
        self.heat_request_W = self.rp.Q_heat_W
        # warm-up phase: decided at the drive's first step, over once the coolant reaches T_warm_degC
        self.warming_up = None

    def describe(self) -> str:
        """The controller's name and thresholds, one line."""
        return "rule-based " + ", ".join(f"{k}={v:g}" for k, v in self.rp.to_dict().items())

    def discharge_limit_W(self, soc) -> float:
        """Terminal power the battery can give at ``soc`` and :attr:`T_bat`: ``P_bat_max``, or for a cold
        pack :data:`DELIVERABLE_SHARE` of its matched-load power ``(U_oc - U_hyst)^2 / (4 R_int)``."""
        p = self.mp
        U, R = battery_ocv_r(p, soc, self.T_bat)
        U = max(U - p.U_hyst, 0.0)
        return min(p.P_bat_max, DELIVERABLE_SHARE * U * U / (4.0 * R))

    def __call__(self, k, soc, T_cl, T_cab, P_trac, Ts=1.0):
        p, r = self.mp, self.rp
        bat_only = (P_trac / p.eta_em if P_trac > 0 else 0.0) + p.P_aux
        P_bat_hi = self.discharge_limit_W(soc)
        must = bat_only > 0.95 * P_bat_hi or soc < r.soc_low
        held = self.keep_running(T_cl)
        if self.warming_up is None or T_cl >= r.T_warm_degC:
            self.warming_up = bool(self.warming_up is None and T_cl < r.T_warm_degC)
        target = max(r.soc_target, r.soc_warmup) if self.warming_up else r.soc_target
        # while the engine must run anyway to warm up, it charges the battery towards the warm-up target
        charge = held and self.warming_up and soc < target
        if self.on:
            # a charging engine keeps running at a standstill, not while braking (regeneration charges then)
            stop = P_trac < 0.0 or (not charge and (P_trac == 0.0 or (P_trac < r.P_off_W
                                                                       and self.on_time >= r.t_min_on_s)))
            if stop and not must:
                self.on = False
        elif must or P_trac > r.P_on_W + r.k_on_W * max(soc - target, 0.0) or (charge and P_trac >= 0.0):
            self.on, self.on_time = True, 0.0
        if self.on:
            self.on_time += Ts
            P_chg = r.k_soc_W * (target - soc)
            P_e = (max(P_trac, 0.0) + P_chg) / p.eta_mech
            P_e = min(max(P_e, r.P_e_min_W), p.P_e_max)
            P_em = P_trac - p.eta_mech * P_e
            P_bat_mg = P_em / p.eta_em if P_em >= 0.0 else P_em * p.eta_em
            lo, hi = p.P_bat_min - p.P_aux, P_bat_hi - p.P_aux
            P_bat_mg = min(max(P_bat_mg, lo), hi)
            P_em = P_bat_mg * p.eta_em if P_bat_mg >= 0.0 else P_bat_mg / p.eta_em
            if P_trac - P_em > 0.0:
                return ON, P_bat_mg, r.Q_heat_W
            # hard braking while forced on: nothing left for the engine to do, so it idles
            return IDLE, 0.0, r.Q_heat_W
        return (IDLE if held else OFF), 0.0, r.Q_heat_W

    def keep_running(self, T_cl) -> bool:
        """Whether the thermal rules forbid stopping the engine at coolant temperature ``T_cl``."""
        r = self.rp
        return T_cl < r.T_idle_degC or (self.heat_request_W > 0.0 and T_cl < r.T_heat_on_degC)


class RuleWrapper:
    """Base of a controller that wraps the rule-based one as ``self.rule`` (a climate control around it): the
    battery temperature the simulator sets on the wrapper reaches the rule's cold-battery limit."""

    rule: RuleBasedController

    @property
    def T_bat(self) -> float:
        """Battery temperature, passed to the rule-based controller (the simulator sets it each step)."""
        return self.rule.T_bat

    @T_bat.setter
    def T_bat(self, value: float) -> None:
        self.rule.T_bat = value
