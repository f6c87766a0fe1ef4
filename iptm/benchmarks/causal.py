"""Benchmark: causal strategies (SDP, ECMS, the rule tuned on the training cycles) on held-out drives against
Thermal-DP and the rule-based controller tuned for each drive,
with the demand chain's validation, the policy build time and the controller step time."""
from __future__ import annotations

from pathlib import Path

#: A training log: its drive is UDDS (see logs/README.md), a training cycle, never a held-out one.
TRAIN_LOG = Path("logs") / "winter_cold_start.blf"


def run(quick: bool = False, valuation: str = "corrected", drives: str = "test-cycles", learn_from=(),
        own_settings: dict | None = None) -> dict:
    import numpy as np
    import pandas as pd

    from calib.model import default_parameters
    from optimize.causal import AMBIENTS, DRIVE_SETS, TRAIN_CYCLES, ECMSController, ECMSParams, SDPController, compare_causal, drives_of, step_timing

    ps = default_parameters()
    test_drives = DRIVE_SETS[drives]
    logs = []
    if TRAIN_LOG.is_file():
        from calib.ingest import read_log

        logs = [read_log(TRAIN_LOG)]
    more = drives_of(learn_from, "--learn-from")
    learn = learn_from if isinstance(learn_from, str) else ",".join(learn_from)  # drives_of takes either
    print(f"training drives: {', '.join(TRAIN_CYCLES)}" + (f" + log {TRAIN_LOG} (SYNTHETIC)" if logs else "")
          + f"; held out ({drives}): {', '.join(test_drives)}; ambients {', '.join(f'{a:g}' for a in AMBIENTS)} degC"
          + (f"; sdp_own: the SDP on a chain that also learnt the {learn} drives ({', '.join(more)}), "
             + (f"settings {own_settings}" if own_settings else "the SDP's settings") if more else ""))
    # compile (or load the numba cache) outside the timings: a tiny policy and one ECMS drive
    from optimize.causal import DemandMarkov, SDPConfig, build_policy

    build_policy(ps, DemandMarkov.estimate(ps, ["nycc"]), SDPConfig(soc_step=0.1, tcl_step=25.0, max_iter=3))
    held = test_drives[:1] if quick else test_drives
    amb = AMBIENTS[:1] if quick else AMBIENTS
    cmp = compare_causal(ps, train_logs=logs, held_out=held, ambients=amb, threads=2, valuation=valuation,
                         learn_from=more, own_settings=own_settings)
    cols = ["drive", "T_amb", "tv_distance_vs_training", "stay_prob_heldout", "stay_prob_model", "lag1_autocorr_heldout",
            "lag1_autocorr_model", "mean_demand_kW_heldout", "mean_demand_kW_model", "loglik_per_step_markov",
            "loglik_per_step_iid"]
    for what, v in (("", cmp.validation), (f" (sdp_own's chain, which also learnt {learn})", cmp.validation_own)):
        if v:
            print(f"\ndemand Markov chain{what} vs held-out drives:")
            with pd.option_context("display.width", 200, "display.max_columns", 20):
                print(pd.DataFrame(v)[cols].to_string(index=False, float_format="%.3f"))
    print(f"\n{valuation} fuel (g) on held-out drives; gap to DP and saving vs tuned rule-based in %:")
    print(cmp.format())
    from calib.model import credit_per_gram

    mp0 = ps.model_params()
    credit = {P: credit_per_gram(mp0, P) for P in (5e3, 15e3, 30e3)}
    print("corrected-fuel valuation: a gram of fuel burnt to charge the battery is credited "
          + ", ".join(f"{c:.2f} g at {P / 1e3:g} kW" for P, c in credit.items())
          + " (charge and coolant heat; before losses): charge and heat made just before a drive ends earn "
            "more than they cost")
    cont = {}
    if valuation == "continuation":
        from calib.model import continuation_credit_per_gram

        cont = {P: continuation_credit_per_gram(ps, P, T_amb=amb[0]) for P in (5e3, 15e3, 30e3)}
        print(f"continuation valuation (UDDS six times, {amb[0]:g} degC, from SOC 0.6, coolant 85 degC): the same gram "
              "is credited " + ", ".join(f"{c:.2f} g at {P / 1e3:g} kW" for P, c in cont.items()))
        res = [r["residual_g"] for r in cmp.rows]
        print(f"end-state difference left after the continuation, valued by fuel equivalents: "
              f"{min(res):.2f} to {max(res):.2f} g per run")
    mp = ps.model_params()
    pol = next(iter(cmp.policies.values()))
    steps = {"sdp": step_timing(ps, SDPController(mp, pol)), "ecms": step_timing(ps, ECMSController(mp))}
    for k, v in steps.items():
        print(f"controller step {k}: median {v['median_s'] * 1e6:.1f} us, p99 {v['p99_s'] * 1e6:.1f} us, "
              f"max {v['max_s'] * 1e3:.2f} ms over {v['calls']} calls (goal < 1 ms)")
    for T, p in cmp.policies.items():
        print(f"SDP policy build at {T:g} degC on 2 threads: {p.info['t_build_s']:.1f} s ({p.info['n_states']} states "
              f"x {p.info['n_controls']} controls, {p.info['iterations']} iterations, converged "
              f"{p.info['converged']}) (goal < 60 s)")
    return {"table": cmp.rows, "goals": cmp.goals(),
            "credit_per_gram": {str(k): v for k, v in credit.items()}, "valuation": valuation, "drives": drives,
            "learn_from": list(more), "own_settings": own_settings, "ecms_settings": ECMSParams().to_dict(),
            "continuation_credit_per_gram": {str(k): v for k, v in cont.items()}, "validation": cmp.validation,
            "validation_own": cmp.validation_own, "step": steps,
            "build": {str(T): p.info for T, p in cmp.policies.items()},
            "rules_train": {str(T): r for T, r in cmp.rules_train.items()},
            "mean_abs_gap_pct": float(np.mean([abs(r["gap_to_dp_pct"]) for r in cmp.rows]))}
