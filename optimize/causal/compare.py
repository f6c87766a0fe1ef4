"""Causal strategies on drives they were not built from, against the DP optimum and tuned rule-based.

For every ambient: the demand Markov chain is estimated from the training drives only
(:data:`TRAIN_CYCLES` plus any training logs), the SDP policy is built for that ambient, and on each
held-out cycle (by default :data:`TEST_CYCLES`) the table compares, in corrected fuel
(:meth:`calib.model.simulate.SimResult.summary`, ``fuel_corrected_g``: fuel minus the fuel equivalent of
the changes of SOC, coolant and cabin heat), the SDP and ECMS controllers with Thermal-DP
(:func:`optimize.solve_thermal`, which knows the whole drive) and the rule-based controller tuned for
that very drive (:func:`optimize.tune_rule_based`). The rule-based baseline thus also knows the drive
(through its tuning); the causal controllers use fixed settings for every drive. A second rule-based row,
``rule_train``, has its thresholds tuned once per ambient on the training cycles
(:func:`optimize.tune_rule_on_drives`): a rule that does not know the drive either, the baseline an
engineer could deploy.

``valuation="continuation"`` compares instead on the continuation-corrected fuel
(:func:`calib.model.continuation.continuation_corrected`: fuel plus the continuation value of the final
minus the initial state, the rule-based controller's fuel over a common next drive), with Thermal-DP
solved with the ``continued`` terminal condition, i.e. minimising that same figure.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from optimize.causal.controllers import ECMSController, SDPController
from optimize.causal.ecms import ECMSParams
from optimize.causal.markov import DemandMarkov
from optimize.causal.sdp import SDPConfig, build_policy

#: Drives the statistics are built from (and the only ones used to choose the controllers' settings).
TRAIN_CYCLES = ("udds", "hwfet", "us06")
#: Published drives, never used to build or tune anything: three urban cycles, the urban half of WLTC and
#: two real-world GPS-logged drives (a 5-min suburban trip, an 18-min highway commute).
TEST_CYCLES = ("artemis_urban", "nycc", "manhattan", "wltc_city_3b", "tsdc_trip_42648", "cmap_chicago_commute")
#: Real GPS-logged trips of the CMAP survey, cut by a rule fixed in advance (studies/extract_cmap_trips;
#: calib/data/cycles/README.md): the first qualifying trip of eight vehicles other than the commute's.
#: They were first simulated after the SDP's settings were last chosen (those settings were revised after
#: results on :data:`TEST_CYCLES` had been seen, so those are no longer a clean test of them).
CMAP_TRIP1 = ("cmap_4107032_1_20070522", "cmap_4108468_1_20070624", "cmap_4108468_2_20070621",
              "cmap_4109114_1_20070517", "cmap_4111928_1_20070519", "cmap_4112082_1_20070703",
              "cmap_4115957_1_20070409", "cmap_4116813_2_20070405")
#: The second qualifying trip of the seven :data:`CMAP_TRIP1` vehicles that made one (``--nth 2``).
#: With ``learn_from=CMAP_TRIP1`` it tests a chain that has also seen each car's earlier trip.
CMAP_TRIP2 = ("cmap_4107032_1_20070526_2131", "cmap_4108468_1_20070624_2007", "cmap_4108468_2_20070621_1833",
              "cmap_4109114_1_20070519_1252", "cmap_4111928_1_20070519_1723", "cmap_4112082_1_20070705_0717",
              "cmap_4115957_1_20070409_2006")
#: The third qualifying trip of the four vehicles that made one (``--nth 3``), for a chain that learnt each
#: car's two earlier trips with settings chosen again for it.
CMAP_TRIP3 = ("cmap_4108468_1_20070625_0810", "cmap_4108468_2_20070627_1507", "cmap_4111928_1_20070522_1636",
              "cmap_4112082_1_20070705_1419")
#: The WLTC high and extra-high phases and the one CMAP trip left that meets the rule (the fourth of
#: vehicle 4108468_1, ``--nth 4``), driven by no controller before the study of the ECMS tuned on each
#: drive (:mod:`optimize.causal.hindsight`).
WLTC_HIGH_CMAP_TRIP4 = ("wltc_high_3b", "wltc_extrahigh_3", "cmap_4108468_1_20070625_1220")
#: The drive sets ``iptm bench causal --drives`` compares on, named by source and content.
DRIVE_SETS = {"test-cycles": TEST_CYCLES, "cmap-trip1": CMAP_TRIP1, "cmap-trip2": CMAP_TRIP2,
              "cmap-trip3": CMAP_TRIP3, "wltc-high-cmap-trip4": WLTC_HIGH_CMAP_TRIP4}


def drives_of(sets, what: str = "drive set") -> tuple:
    """The drives of the named :data:`DRIVE_SETS` (a list, or names joined by commas), in order."""
    names = [x for x in (sets.split(",") if isinstance(sets, str) else sets) if x]
    bad = [x for x in names if x not in DRIVE_SETS]
    if bad:
        from calib.errors import IptmError

        raise IptmError(f"{what} {','.join(bad)}: choose among {', '.join(DRIVE_SETS)}")
    return tuple(c for x in names for c in DRIVE_SETS[x])


#: The settings ``studies/causal_select/causal_select.py`` chooses (the chain's ``alpha``, the rest :class:`SDPConfig` fields).
SELECTED = ("alpha", "w_soc_g_per_s", "soc_bias", "regen_fraction", "regen_slope_per_mps")
#: The causal strategies of a comparison (``sdp_own``: the SDP on a chain that also learnt ``learn_from``;
#: ``rule_train``: the rule-based controller tuned on the training cycles).
CAUSAL = ("sdp", "ecms", "sdp_own", "rule_train")
AMBIENTS = (-10.0, 0.0)
GOAL_GAP_PCT = 3.0
SOC_TOL = 0.01
#: How final states are valued (:func:`compare_causal`).
VALUATIONS = ("corrected", "continuation")


@dataclass
class CausalComparison:
    """Rows per (cycle, ambient, strategy), the Markov validation and the build / step timings."""

    rows: list
    markov: DemandMarkov
    validation: list
    policies: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    valuation: str = "corrected"
    soc_band: float = SOC_TOL
    learn_from: tuple = ()
    validation_own: list = field(default_factory=list)  # the ``learn_from`` chain against the held-out drives
    rules_train: dict = field(default_factory=dict)  # per ambient, the thresholds of ``rule_train``

    def table(self) -> pd.DataFrame:
        return pd.DataFrame(self.rows)

    def goals(self) -> dict:
        df = self.table()
        c = df[df.strategy.isin(CAUSAL)]
        out = {}
        for s, g in c.groupby("strategy"):
            within, better = g.gap_to_dp_pct <= GOAL_GAP_PCT, g.vs_rule_pct > 0
            sustaining = g.dsoc.abs() <= SOC_TOL
            out[s] = {"runs": int(len(g)), "max_gap_to_dp_pct": float(g.gap_to_dp_pct.max()),
                      "within_3pct": int(within.sum()), "within_3pct_all": bool(within.all()),
                      "better_than_rule": int(better.sum()), "better_than_rule_all": bool(better.all()),
                      "better_than_rule_train": int((g.vs_rule_train_pct > 0).sum()),
                      "charge_sustaining": int(sustaining.sum()), "charge_sustaining_all": bool(sustaining.all()),
                      "dsoc_range": (float(g.dsoc.min()), float(g.dsoc.max()))}
        return out

    def format(self) -> str:
        df = self.table()
        cols = ["cycle", "T_amb", "strategy", "fuel_g", "fuel_corrected_g", "credit_g", "soc_final", "T_cl_final",
                "gap_to_dp_pct", "vs_rule_pct", "vs_rule_train_pct"]
        with pd.option_context("display.width", 200, "display.max_columns", 20):
            txt = df[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}" if abs(v) < 2 else f"{v:.2f}")
        what = ("continuation-corrected (fuel + C(x_N) - C(x_0), Thermal-DP with the 'continued' terminal, "
                f"|SOC_N - SOC_0| <= {self.soc_band:g})"
                if self.valuation == "continuation" else "corrected (fuel minus fuel equivalents of stored energy)")
        lines = [f"fuel_corrected_g: {what}; credit_g = fuel_g - fuel_corrected_g", txt, ""]
        for s, g in self.goals().items():
            n = g["runs"]
            lines.append(f"{s}: within {GOAL_GAP_PCT:g} % of DP on {g['within_3pct']}/{n} runs (max gap "
                         f"{g['max_gap_to_dp_pct']:.2f} %: goal {'met' if g['within_3pct_all'] else 'NOT met'}); "
                         f"better than tuned rule-based on {g['better_than_rule']}/{n} "
                         f"({'met' if g['better_than_rule_all'] else 'NOT met'}), than the rule tuned on the "
                         f"training cycles on {g['better_than_rule_train']}/{n}; charge sustaining "
                         f"(|dSOC| <= {SOC_TOL}) on {g['charge_sustaining']}/{n} "
                         f"({'met' if g['charge_sustaining_all'] else 'NOT met'}; dSOC {g['dsoc_range'][0]:+.4f} to "
                         f"{g['dsoc_range'][1]:+.4f})")
        return "\n".join(lines)


def valuation_scenario(base, valuation: str, soc_band: float | None = None):
    """``base`` as the comparison solves it under ``valuation``: for ``continuation``, Thermal-DP with the
    ``continued`` terminal held to ``|SOC_N - SOC_0| <= soc_band`` (default :data:`SOC_TOL`)."""
    from dataclasses import replace

    if valuation != "continuation":
        return base
    # the DP ends in the band the causal controllers must end in: free, it banks charge made at its
    # engine's marginal efficiency, which the continuation (rule-based) uses at a better rate
    return replace(base, terminal="continued", cont_soc_band=SOC_TOL if soc_band is None else soc_band)


def valued_fuel(sim, scen, valuation) -> tuple:
    """(corrected fuel, residual of the continuation or nan) of a run under the valuation."""
    if valuation == "continuation":
        from calib.model.continuation import continuation_corrected

        c = continuation_corrected(sim, Q_heat=scen.Q_heat, T_amb=scen.T_amb, cycle=scen.cont_cycle)
        return c["fuel_continuation_g"], c["residual_g"]
    return sim.summary()["fuel_corrected_g"], np.nan


def _row(cycle, T_amb, strategy, sim, dp_corr, rule_corr, t_s, corr, residual=np.nan, rule_train_corr=np.nan):
    """A table row: ``vs_rule_pct`` / ``vs_rule_train_pct``, the saving against the rule tuned on this drive /
    on the training cycles (> 0: less corrected fuel)."""
    s = sim.summary()
    return {"cycle": cycle, "T_amb": T_amb, "strategy": strategy, "fuel_g": s["fuel_g"], "fuel_corrected_g": corr,
            "credit_g": s["fuel_g"] - corr, "residual_g": residual,
            "soc_final": s["soc_final"], "dsoc": s["soc_final"] - s["soc_initial"],
            "T_cl_final": s["T_cl_final_degC"], "T_cab_final": s["T_cab_final_degC"],
            "gap_to_dp_pct": 100.0 * (corr / dp_corr - 1.0) if dp_corr else np.nan,
            "vs_rule_pct": 100.0 * (1.0 - corr / rule_corr) if rule_corr else np.nan,
            "vs_rule_train_pct": 100.0 * (1.0 - corr / rule_train_corr) if rule_train_corr else np.nan, "time_s": t_s}


def own_chain(params, sources, settings: dict | None = None) -> tuple[DemandMarkov, dict]:
    """The demand chain of ``sources`` with ``settings``' ``alpha`` and the :class:`SDPConfig` fields the other
    :data:`SELECTED` settings set (None: the defaults, i.e. the committed SDP's)."""
    cfg = {k: float(settings[k]) for k in SELECTED} if settings else {}
    alpha = cfg.pop("alpha", None)
    return DemandMarkov.estimate(params, sources, **({} if alpha is None else {"alpha": alpha})), cfg


def compare_causal(params, *, train=TRAIN_CYCLES, train_logs=(), held_out=TEST_CYCLES, ambients=AMBIENTS,
                   sdp_config: SDPConfig | None = None, ecms: ECMSParams | None = None, grids=None,
                   scenario=None, threads: int | None = 2, progress: bool = True,
                   valuation: str = "corrected", soc_band: float | None = None,
                   learn_from=(), own_settings: dict | None = None) -> CausalComparison:
    """Build statistics and policies from ``train`` (+ ``train_logs``) and compare on ``held_out``.

    ``learn_from``: more drives (e.g. the same cars' earlier trips) for a second demand chain, whose
    policy drives every held-out drive as ``sdp_own`` beside the ``sdp`` of ``train`` alone. ``own_settings``:
    the settings ``sdp_own`` uses (a row of ``studies/causal_select/causal_select.py``'s report: ``alpha``,
    ``w_soc_g_per_s``, ``soc_bias``, ``regen_fraction``, ``regen_slope_per_mps``); None: the same as ``sdp``.

    ``valuation``: ``"corrected"`` (fuel minus the fuel equivalents of the stored-energy changes; Thermal-DP
    with the scenario's terminal condition) or ``"continuation"`` (continuation-corrected fuel; Thermal-DP
    with the ``continued`` terminal condition and ``|SOC_N - SOC_0| <= soc_band``, default :data:`SOC_TOL`,
    the charge-sustaining band the causal controllers are held to; ``math.inf``: SOC_N free). Rows carry
    ``credit_g`` (fuel minus the corrected figure)
    and, with the continuation, ``residual_g`` (the part valued by fuel equivalents after it)."""
    from dataclasses import replace

    from calib.model.simulate import simulate
    from optimize.formulations.scenario import DPScenario
    from optimize.formulations.solve import solve_thermal
    from optimize.tuning import tune_rule_based, tune_rule_on_drives

    say = print if progress else (lambda *a, **k: None)
    overlap = (set(train) | set(learn_from)) & set(held_out)
    if overlap:
        from calib.errors import IptmError

        raise IptmError(f"causal comparison: {sorted(overlap)} both trains and tests the controllers; "
                        "held-out drives must not be training drives")
    if valuation not in VALUATIONS:
        from calib.errors import IptmError

        raise IptmError(f"causal comparison: valuation {valuation!r}; choose one of {', '.join(VALUATIONS)}")
    base = scenario or DPScenario()
    base = valuation_scenario(base, valuation, soc_band)
    mp = params.model_params() if hasattr(params, "model_params") else params
    markov = DemandMarkov.estimate(params, list(train) + list(train_logs))
    own, own_cfg = (own_chain(params, list(train) + list(train_logs) + list(learn_from), own_settings)
                    if learn_from else (None, {}))
    validation, validation_own = [], []
    rows, policies, timings, rules_train = [], {}, {}, {}
    for T_amb in ambients:
        validation += [{**r, "T_amb": T_amb} for r in markov.validate(params, held_out, T_amb=T_amb)]
        if own is not None:
            validation_own += [{**r, "T_amb": T_amb} for r in own.validate(params, held_out, T_amb=T_amb)]
        cfg = replace(sdp_config or SDPConfig(), T_amb=T_amb, Q_heat=base.Q_heat, soc_target=base.soc0)
        pol = build_policy(params, markov, cfg, threads=threads)
        policies[T_amb] = pol
        timings[f"sdp_build_s@{T_amb:g}"] = pol.info["t_build_s"]
        say(f"SDP policy at {T_amb:g} degC: {pol.info['t_build_s']:.1f} s, {pol.info['iterations']} iterations",
            flush=True)
        pol_own = build_policy(params, own, replace(cfg, **own_cfg), threads=threads) if own is not None else None
        ep = replace(ecms or ECMSParams(), Q_heat_W=base.Q_heat, soc_target=base.soc0)
        t0 = time.perf_counter()
        rt = tune_rule_on_drives(params, [replace(base, cycle=c).load_cycle() for c in train], T_amb=T_amb,
                                 soc0=base.soc0, T_cl0=base.T_cl0, T_cab0=base.T_cab0, Q_heat=base.Q_heat)
        timings[f"rule_train_tune_s@{T_amb:g}"] = time.perf_counter() - t0
        rules_train[T_amb] = rt.rule.to_dict() | {"n_feasible": rt.n_feasible}
        say(f"rule-based tuned on {', '.join(train)} at {T_amb:g} degC: {rt.rule.to_dict()} "
            f"({rt.n_feasible}/{rt.n_tried} settings charge sustaining on all)", flush=True)
        for cyc in held_out:
            scen = replace(base, cycle=cyc, T_amb=T_amb)
            t0 = time.perf_counter()
            dp = solve_thermal(params, scen, grids)
            t_dp = time.perf_counter() - t0
            t0 = time.perf_counter()
            tr = tune_rule_based(params, scen.load_cycle(), T_amb=T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0,
                                 T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)
            t_rule = time.perf_counter() - t0
            dp_corr, dp_res = valued_fuel(dp.sim, scen, valuation)
            rule_corr, rule_res = valued_fuel(tr.result, scen, valuation)
            kw = dict(T_amb=T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0, T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)
            t0 = time.perf_counter()
            rts = simulate(params, scen.load_cycle(), rule_params=rt.rule, **kw)
            t_rt = time.perf_counter() - t0
            rt_corr, rt_res = valued_fuel(rts, scen, valuation)
            ref = (dp_corr, rule_corr)
            rows.append(_row(cyc, T_amb, "dp_thermal", dp.sim, *ref, t_dp, dp_corr, dp_res, rt_corr))
            rows.append(_row(cyc, T_amb, "rule_tuned", tr.result, *ref, t_rule, rule_corr, rule_res, rt_corr))
            rows.append(_row(cyc, T_amb, "rule_train", rts, *ref, t_rt, rt_corr, rt_res, rt_corr))
            ctrls = [("sdp", SDPController(mp, pol, T_amb)), ("ecms", ECMSController(mp, ep, T_amb))]
            if pol_own is not None:
                ctrls.append(("sdp_own", SDPController(mp, pol_own, T_amb)))
            for name, ctrl in ctrls:
                t0 = time.perf_counter()
                sim = simulate(params, scen.load_cycle(), ctrl, **kw)
                t_s = time.perf_counter() - t0
                rows.append(_row(cyc, T_amb, name, sim, *ref, t_s, *valued_fuel(sim, scen, valuation), rt_corr))
            say(f"  {cyc} at {T_amb:g} degC: DP {dp_corr:.2f} g, rule {rule_corr:.2f} g, rule (training) {rt_corr:.2f} g, "
                + ", ".join(f"{n} {r['fuel_corrected_g']:.2f} g" for (n, _), r in zip(ctrls, rows[-len(ctrls):]))
                + " (corrected)", flush=True)
    return CausalComparison(rows, markov, validation, policies, timings, valuation,
                            base.cont_soc_band if valuation == "continuation" else SOC_TOL, tuple(learn_from),
                            validation_own, rules_train)


def step_timing(params, controller, cycle="artemis_urban", T_amb=-10.0, reps: int = 3) -> dict:
    """Per-call time of a controller (s): median and 99th percentile over ``reps`` drives."""
    from calib.model.cycles import load_cycle
    from calib.model.equations import traction_power

    mp = params.model_params() if hasattr(params, "model_params") else params
    cyc = load_cycle(cycle)
    P = [traction_power(mp, cyc.v[k], cyc.v[k + 1], 0.0, cyc.Ts) for k in range(cyc.n_steps)]
    ts = []
    for _ in range(reps):
        if hasattr(controller, "reset"):
            controller.reset()
        soc, tcl, tcab = 0.6, 70.0, 20.0
        for k, Pt in enumerate(P):
            t0 = time.perf_counter()
            controller(k, soc, tcl, tcab, Pt, cyc.Ts)
            ts.append(time.perf_counter() - t0)
    ts = np.array(ts[len(P):] if reps > 1 else ts)  # the first drive warms caches
    return {"median_s": float(np.median(ts)), "p99_s": float(np.percentile(ts, 99)), "max_s": float(ts.max()),
            "calls": int(ts.size)}
