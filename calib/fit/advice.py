"""Advice an engineer acts on: for parameters the logs informed weakly, or only in combination with
another, which drive (or which channel) would inform them. Rules read the subsystem fits' estimates,
confounded pairs and metrics; each piece of advice names the parameters and the reason."""
from __future__ import annotations

from calib.fit.toolkit import WEAK_INFORMED


def _weak(fit, name):
    e = fit.estimates.get(name)
    if e is None:
        return False
    if isinstance(e.informed, list):
        return all(x < WEAK_INFORMED for x in e.informed)
    return e.status in ("weak", "prior") or (e.informed is not None and e.informed < WEAK_INFORMED)


def _pair(fit, a, b):
    return any({x, y} == {a, b} for x, y, _ in fit.confounded)


def advise(fits) -> list[str]:
    """List of advice strings for a dict ``subsystem -> SubsystemFit``."""
    out = []
    th = fits.get("thermal")
    if th is not None and th.logs:
        weak_rad = [short for n, short in (("T_open_degC", "T_open"), ("k_rad_W_per_K", "k_rad")) if _weak(th, n)]
        if weak_rad:
            tmax = th.metrics.get("coolant_max_degC", float("nan"))
            e = th.estimates.get("T_open_degC")
            t_open = float(e.value) if e is not None else float("nan")
            names = " and ".join(weak_rad)
            one = len(weak_rad) == 1
            stay, come, them = ("stays", "comes", "it") if one else ("stay", "come", "them")
            if tmax >= t_open + 5.0:  # reached, yet not informative: the radiator is not the model's
                out.append(f"The coolant reaches {tmax:.0f} degC, above the thermostat ({t_open:.0f} degC), yet "
                           f"{names} {stay} weakly informed: the coolant up there does not follow a radiator that "
                           "opens with temperature (one that cools only at some vehicle speeds, or a thermostat that "
                           "never opens in these logs). Check the coolant trace above the thermostat; a steady "
                           "highway stretch after warm-up (15-20 min) would show how the radiator works.")
            else:
                out.append(f"No log reaches the thermostat (coolant max {tmax:.0f} degC): {names} {come} from the "
                           "prior. A drive that warms the engine fully (15-20 min of highway after warm-up) would "
                           f"determine {them}.")
        if _pair(th, "C_eng_J_per_K", "gamma_exh") or _weak(th, "gamma_exh") or _weak(th, "C_eng_J_per_K"):
            out.append("C_eng and gamma_exh are separated only by the heat the heater draws: a few minutes with the "
                       "heater off (engine warm, then on again) would separate C_eng from gamma_exh.")
        if _pair(th, "gamma_exh", "hA_eng_W_per_K") or _weak(th, "hA_eng_W_per_K"):
            out.append("hA_eng trades against gamma_exh: a stop of several minutes with the engine off and the coolant "
                       "warm (a cool-down) would determine the engine's heat loss hA_eng.")
        if th.estimates.get("kappa") is not None and th.estimates["kappa"].informed == 0.0:
            out.append("kappa comes from the prior: log the engine-bay temperature (bay_temp_degC) to separate "
                       "kappa from hA_eng.")
        for lg, used in th.used.items():
            if str(used.get("heater heat", "")).startswith("inferred"):
                out.append(f"{lg}: the heater heat was inferred from the cabin balance; logging heater_power_W (or "
                           "vent temperature and blower flow) would make the engine thermal fit independent of the "
                           "cabin parameters.")
    fu = fits.get("fuel")
    if fu is not None and fu.logs:
        e = fu.estimates.get("eta_ool")
        if e is not None and isinstance(e.informed, list):
            weak_hi = [j for j, x in enumerate(e.informed) if j > 0 and x < WEAK_INFORMED]
            if weak_hi:
                pmax = fu.metrics.get("engine_power_max_W", 0.0) / 1e3
                out.append(f"The warm fuel rate is informed up to about {pmax:.0f} kW of engine power; above it "
                           "it is the prior curve. A drive with hard accelerations (US06-like) with a warm engine "
                           "would inform it.")
        if fu.metrics.get("warm_on_samples", 0) < 60:
            out.append("Fewer than 60 s of warm engine running: the warm fuel rate and the cold correction f_cl "
                       "trade against each other; a drive that warms the engine (coolant >= 80 degC) would "
                       "separate them.")
        f = fu.estimates.get("f_cl")
        if f is not None and isinstance(f.informed, list) and f.informed and f.informed[0] < WEAK_INFORMED:
            out.append("f_cl at the coldest breakpoint comes mostly from the prior: a cold start at or below that "
                       "coolant temperature would determine it.")
        hot = fu.metrics.get("f_cl_hot_weak_degC")
        if hot:
            out.append(f"f_cl above the thermostat ({', '.join(f'{x:g}' for x in hot)} degC) comes mostly from "
                       "its prior (1): a drive whose coolant runs there (a long climb, a hot day) would "
                       "determine it.")
        if _weak(fu, "W_idle_g_per_s"):
            out.append("W_idle comes mostly from the prior: a minute of idling (stationary, engine running) would "
                       "determine it.")
    ca = fits.get("cabin")
    if ca is not None and ca.logs:
        if _pair(ca, "C_cab_J_per_K", "UA_cab_W_per_K") or _weak(ca, "UA_cab_W_per_K"):
            out.append("C_cab and UA_cab are not separated: a period with the heater off while the cabin cools "
                       "towards ambient would separate the heat capacity from the loss conductance.")
        if _weak(ca, "eps_hc"):
            out.append("eps_hc comes from the prior: log vent temperature, coolant temperature and blower flow at "
                       "full heating (the heater-core limit).")
    elif ca is not None and ca.message:
        out.append("Cabin parameters come from the prior: " + ca.message.split(" (")[0] + ".")
    ba = fits.get("battery")
    if ba is not None and ba.logs:
        if _weak(ba, "C_bat_Ah"):
            out.append("C_bat comes mostly from the prior: a drive with a wider SOC swing (a long climb or "
                       "electric-only driving) would determine it.")
        if _weak(ba, "R_int_tc_per_K"):
            out.append("The temperature coefficient of R_int comes from the prior: logs at battery temperatures at "
                       "least 10 K apart would determine it.")
        if _weak(ba, "U_hyst_V") or _pair(ba, "R_scale", "U_hyst_V"):
            out.append("The hysteresis U_hyst and the resistance are not separated: charging and discharging at "
                       "both low (a few kW) and high (over 15 kW) battery power would tell a loss that grows with "
                       "the current from one that grows with its square.")
        if any("inferred" in str(u.get("current", "")) for u in ba.used.values()):
            out.append("Battery current was inferred from power: logging bat_current_A and bat_voltage_V would "
                       "determine the OCV and resistance tables.")
    # any remaining strong pair the rules above do not cover
    known = {frozenset(p) for p in (("C_eng_J_per_K", "gamma_exh"), ("gamma_exh", "hA_eng_W_per_K"),
                                    ("C_cab_J_per_K", "UA_cab_W_per_K"), ("R_scale", "U_hyst_V"))}
    for f in fits.values():
        for a, b, r in f.confounded:
            if frozenset((a, b)) not in known and not a.startswith(("eta_", "d_")):
                out.append(f"{a} and {b} are confounded (posterior correlation {r:+.2f}): the logs determine a "
                           "combination of them; a drive exciting them differently would separate them.")
    return out
