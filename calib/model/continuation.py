"""Valuation of a drive's final state by a common continuation.

A drive that ends with more charge or warmer coolant leaves the next drive cheaper; how much cheaper is
what the model itself says when one reference controller drives on. The value of a state
``x = (SOC, T_cl, T_cab)`` is the fuel the rule-based controller (calib's default in
:func:`calib.model.simulate.simulate`) burns over a fixed continuation drive (default UDDS six times, at the
drive's ambient and heater demand) started from ``x``; the rule's SOC set point and the thermostat pull
different starting states together over it, and the end-state difference that remains is valued by
:func:`calib.model.simulate.fuel_equivalents_g`. The continuation-corrected fuel of a drive is then

    fuel + C(x_final) - C(x_initial),

which credits charge and heat only with the fuel the reference controller actually saves with them
(no separate prices for charge and heat made from the same gram, so no double credit).
"""
from __future__ import annotations

import numpy as np

from calib.errors import ScenarioError

#: The default continuation drive: UDDS six times (8,214 s). The rule's SOC recovery pulls the charge
#: together within one UDDS; the coolant (below the thermostat all the way at -10 degC with 1500 W of
#: heater) converges slowly, so the drive is long enough that the coolant difference left at its end is a
#: few kelvin at most (docs/optimization.md s.1 gives the measured sizes).
CONTINUATION_CYCLE = "+".join(["udds"] * 6)


def _mp(params):
    return params.model_params() if hasattr(params, "model_params") else params


def continuation_run(params, soc, T_cl, T_cab, *, T_amb, Q_heat, cycle=CONTINUATION_CYCLE, T_bat=None,
                     W_bl=None, rule_params=None) -> dict:
    """The reference controller driven over the continuation from each state (arrays broadcast together).

    Returns a dict of arrays of the broadcast shape: ``fuel_g`` (fuel over the continuation) and the end
    states ``soc_end``, ``T_cl_end``, ``T_cab_end``. One :func:`calib.model.simulate.simulate` call per
    state (about 0.12 s for UDDS six times). The trip goes on: the engine does not start again from cold
    (no catalyst heating).
    """
    from calib.model.cycles import load_cycle
    from calib.model.simulate import simulate

    cyc = load_cycle(cycle)
    s, tc, tb = np.broadcast_arrays(np.asarray(soc, float), np.asarray(T_cl, float), np.asarray(T_cab, float))
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(tc)) and np.all(np.isfinite(tb))):
        raise ScenarioError("continuation: every state (soc, T_cl, T_cab) must be a finite number")
    out = {k: np.empty(s.shape) for k in ("fuel_g", "soc_end", "T_cl_end", "T_cab_end")}
    for i in np.ndindex(s.shape):
        r = simulate(params, cyc, T_amb=T_amb, soc0=float(s[i]), T_cl0=float(tc[i]), T_cab0=float(tb[i]),
                     Q_heat=Q_heat, T_bat=T_bat, W_bl=W_bl, rule_params=rule_params, engine_start=False)
        out["fuel_g"][i] = r.fuel_g
        out["soc_end"][i], out["T_cl_end"][i], out["T_cab_end"][i] = r.soc[-1], r.T_cl[-1], r.T_cab[-1]
    return out


def continuation_value(params, soc, T_cl, T_cab, *, T_amb, Q_heat, ref, cycle=CONTINUATION_CYCLE, T_bat=None,
                       W_bl=None, rule_params=None, details=False):
    """Value C(x) (g) of final states x = (soc, T_cl, T_cab) (arrays, broadcast together): the fuel the
    rule-based controller burns over the continuation ``cycle`` from x, minus the fuel equivalent
    (:func:`calib.model.simulate.fuel_equivalents_g`) of how far its end state lies above the end state of
    the continuation from ``ref``.

    ``ref`` = (soc, T_cl, T_cab): the state whose continuation end is the common reference, normally the
    drive's initial state, so that ``C(x_final) - C(x_initial)`` is the continuation correction. A lower
    C is a more valuable state. ``details=True`` returns ``(C, run, ref_run)`` with the dicts of
    :func:`continuation_run` (the residual's size is ``run[...end] - ref_run[...end]``).
    """
    from calib.model.simulate import fuel_equivalents_g

    if len(tuple(ref)) != 3:
        raise ScenarioError(f"continuation: ref must be (soc, T_cl, T_cab), got {ref!r}")
    kw = dict(T_amb=T_amb, Q_heat=Q_heat, cycle=cycle, T_bat=T_bat, W_bl=W_bl, rule_params=rule_params)
    run = continuation_run(params, soc, T_cl, T_cab, **kw)
    ref_run = continuation_run(params, *ref, **kw)
    e0 = {k: float(ref_run[k]) for k in ("soc_end", "T_cl_end", "T_cab_end")}
    eq = fuel_equivalents_g(_mp(params), e0["soc_end"], run["soc_end"], e0["T_cl_end"], run["T_cl_end"],
                            e0["T_cab_end"], run["T_cab_end"])
    C = run["fuel_g"] - (np.asarray(eq["electric_g"]) + np.asarray(eq["coolant_g"]) + np.asarray(eq["cabin_g"]))
    C = float(C) if np.ndim(C) == 0 else C
    return (C, run, ref_run) if details else C


def continuation_corrected(res, *, Q_heat, T_amb=None, cycle=CONTINUATION_CYCLE, rule_params=None) -> dict:
    """Continuation-corrected fuel of a simulated drive ``res`` (:class:`calib.model.simulate.SimResult`):
    ``fuel + C(x_final) - C(x_initial)`` (:func:`continuation_value`, ``ref`` the initial state).

    ``Q_heat``: the heater demand of the continuation (the drive's); ``T_amb``: its ambient (default the
    drive's mean). Returns ``fuel_g``, ``fuel_continuation_g`` (the corrected figure),
    ``continuation_credit_g`` (``C(x_initial) - C(x_final)``: positive when the final state is worth
    more), ``residual_g`` (the part of it that comes from the end-state difference left after the
    continuation) and the continuation end states' differences ``residual_dsoc``, ``residual_dT_cl``,
    ``residual_dT_cab``.
    """
    if T_amb is None and res.info.get("T_amb_degC") is None:
        raise ScenarioError("continuation_corrected: the result records no ambient; pass T_amb")
    T = float(res.info["T_amb_degC"]) if T_amb is None else float(T_amb)
    x0 = (float(res.soc[0]), float(res.T_cl[0]), float(res.T_cab[0]))
    C, run, ref_run = continuation_value(res.mp, float(res.soc[-1]), float(res.T_cl[-1]), float(res.T_cab[-1]),
                                         T_amb=T, Q_heat=Q_heat, ref=x0, cycle=cycle, rule_params=rule_params,
                                         details=True)
    C0 = float(ref_run["fuel_g"])
    credit = C0 - C
    fuel = res.fuel_g
    return {"fuel_g": fuel, "fuel_continuation_g": fuel - credit, "continuation_credit_g": credit,
            "residual_g": float(run["fuel_g"]) - C,
            "residual_dsoc": float(run["soc_end"] - ref_run["soc_end"]),
            "residual_dT_cl": float(run["T_cl_end"] - ref_run["T_cl_end"]),
            "residual_dT_cab": float(run["T_cab_end"] - ref_run["T_cab_end"])}


def continuation_credit_per_gram(params, P_e: float, *, soc: float = 0.6, T_cl: float = 85.0, T_cab: float = 20.0,
                                 T_amb: float = -10.0, Q_heat: float = 1500.0, grams: float = 20.0,
                                 cycle=CONTINUATION_CYCLE) -> float:
    """Continuation credit (g) per gram of fuel burnt with the engine at power ``P_e`` (W) to charge the
    battery through the generator, its non-exhaust heat going to the coolant (the same gram as
    :func:`calib.model.simulate.credit_per_gram`, before battery and coolant losses).

    ``grams`` of such charge and heat are added to the state (soc, T_cl, T_cab) and the credit is
    ``(C(x) - C(x + made)) / grams``, evaluated by :func:`continuation_value` with ``ref = x``; a finite
    amount because the continuation's fuel moves in steps (engine starts) at the gram scale.
    """
    from calib.model.equations import ON, battery_ocv_r, coolant_heat_rate, fuel_rate

    if not grams > 0:
        raise ScenarioError("continuation_credit_per_gram: grams must be positive")
    p = _mp(params)
    W_f = fuel_rate(p, ON, P_e, T_cl)
    net, _ = coolant_heat_rate(p.gamma_exh, p.LHV * W_f, P_e, 0.0, 0.0)
    U, _ = battery_ocv_r(p, soc, p.T_bat_ref)
    dsoc_g = P_e * p.eta_mech * p.eta_em / (p.C_bat_As * U) / W_f
    dT_g = net / p.C_eng / W_f
    x = (soc, T_cl, T_cab)
    # both states in one call: the reference continuation is run once
    C0, C1 = continuation_value(params, np.array([soc, soc + grams * dsoc_g]), np.array([T_cl, T_cl + grams * dT_g]),
                                T_cab, T_amb=T_amb, Q_heat=Q_heat, ref=x, cycle=cycle)
    return float((C0 - C1) / grams)
