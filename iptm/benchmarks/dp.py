"""Benchmark: the three DP formulations on the paper's grids, 993-s ARTEMIS Urban, -10 degC, Baseline-DP on
its default grid (:data:`optimize.formulations.BASELINE_CONVERGED_GRIDS`) and Thermal-Cabin-DP on its
converged grid (:data:`optimize.formulations.CABIN_CONVERGED_GRIDS`; with
``--halve`` also on that grid with every step halved, the convergence check, printed beside its time).

Each formulation is solved once to compile (or load numba's disk cache), then timed on a second solve.
Memory is the process's peak resident set size (``resource.getrusage().ru_maxrss``), i.e. a process-wide
high-water mark including Python, numba and everything solved before, not a per-solve figure.
"""
from __future__ import annotations

import time


def run(quick: bool = False, halve: bool = False) -> dict:
    """Time the formulations (see the module docstring); ``halve``: also solve the converged
    Thermal-Cabin-DP grid with every step halved (32 times its work) and print the change."""
    import numba

    from calib.model import default_parameters
    from optimize.formulations import BASELINE_CONVERGED_GRIDS, CABIN_CONVERGED_GRIDS, DPGrids, DPScenario, peak_rss_mb, solve_formulation

    ps = default_parameters()
    scen = DPScenario(duration_s=120.0) if quick else DPScenario()
    grids = DPGrids()
    cyc = scen.load_cycle()
    print(f"cycle {cyc.name}: {cyc.n_steps} steps; paper grids {grids.to_dict()}; numba threads "
          f"{numba.get_num_threads()}; timings after a warm-up (compile) solve")
    import os

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average (1 min) before the runs: {load:.2f} on {os.cpu_count()} CPUs (other processes slow "
          "the figures down); OMP_WAIT_POLICY=" + os.environ.get("OMP_WAIT_POLICY", ""))
    out = {"load_average_1min": load}
    from iptm.benchmarks.machine import measure

    lim = measure(quick)
    out["machine"] = lim
    print(f"machine limits, measured now: memory bandwidth {lim['bandwidth_GB_per_s']:.1f} GB/s (array copy), "
          f"{lim['blas_GFLOP_per_s']:.1f} GFLOP/s (matrix product), {lim['scalar_GFLOP_per_s']:.1f} GFLOP/s "
          f"(compiled multiply-adds on {lim['threads']} threads)")
    for f in ("baseline", "thermal", "thermal_cabin"):
        t0 = time.perf_counter()
        solve_formulation(f, ps, scen, grids)
        t_warm = time.perf_counter() - t0
        o = solve_formulation(f, ps, scen, grids)
        rss = peak_rss_mb()
        r = {"n_states": o.n_states, "n_controls": o.n_controls, "n_steps": cyc.n_steps,
             "t_total_s": o.t_total, "t_backward_s": o.t_backward, "t_forward_s": o.t_forward,
             "t_first_solve_incl_compile_s": t_warm, "n_evaluations": o.n_evaluations,
             "evals_per_second": o.evals_per_second, "peak_rss_mb_process": rss, "fuel_g": o.sim.fuel_g,
             "engine": o.extra.get("kernel", o.extra.get("engine", "generic")),
             "threads": 1 if f == "baseline" else numba.get_num_threads()}
        if f == "thermal_cabin":
            paper = o.sim.summary()  # compared with the converged grid below
        # what the machine allows: in the exact fused kernels a state-control evaluation does ~30 flops
        # (interpolations of level and cost, the reach rule, the stage cost) in scalar code and reads 8 values
        # (level and cost at 4 corners, 64 bytes) if none comes from cache; in the separable kernels ~10 (two
        # weighted reads of the cost-to-go interpolated along coolant and cabin, the stage cost and the minimum: 6;
        # that interpolation, shared by the SOC rows, about 4 per pair) and 5 reads (40 bytes), in loops the
        # compiler vectorises, so their flop bound is the vector peak (the matrix product's rate), not the
        # scalar one; their reads come from cache, so the memory figure is not their bound either. Thermal-Cabin's
        # separable kernel evaluates only some heats of a cell (the ends of affine stretches), so its
        # evaluations/s count the pairs it settles, not the pairs it computes
        sep = r["engine"] == "fused-separable"
        fl, by = (10.0, 40.0) if sep else (30.0, 64.0)
        r["flops_per_evaluation"] = fl
        r["flop_rate_used"] = "blas_GFLOP_per_s" if sep else "scalar_GFLOP_per_s"
        r["evals_per_s_if_flop_bound"] = lim[r["flop_rate_used"]] * 1e9 / fl
        r["evals_per_s_if_memory_bound"] = lim["bandwidth_GB_per_s"] * 1e9 / by
        out[f] = r
        print(f"{f:>14s}: {o.n_states} states x {o.n_controls} controls: total {o.t_total:.3f} s (backward "
              f"{o.t_backward:.3f} s, forward {o.t_forward:.3f} s, {o.evals_per_second / 1e6:.0f} M state-control "
              f"evals/s, {r['engine']} kernel, {r['threads']} thread(s)); process peak RSS {rss:.0f} MB; fuel {o.sim.fuel_g:.2f} g "
              f"[first solve incl. compile {t_warm:.1f} s]; the machine's bounds: "
              f"{r['evals_per_s_if_flop_bound'] / 1e6:.0f} M evals/s at ~{fl:.0f} flops each "
              f"({'vector' if sep else 'scalar'} rate), "
              f"{r['evals_per_s_if_memory_bound'] / 1e6:.0f} M evals/s if each read its {by:.0f} bytes from memory",
              flush=True)
    # the separable kernels (the default) against the exact fused kernels, alternated in this process:
    # Thermal-DP three times each; Thermal-Cabin-DP on the paper grid, the separable kernel three times and
    # the exact one once, after the first (it takes minutes), so that the separable time is a median too
    import statistics

    n = 1 if quick else 3
    for f, reps, reps_exact in (("thermal", n, n), ("thermal_cabin", n, 1)):
        ts = {"fused": [], "fused-exact": []}
        fuel = {}
        for r in range(reps):
            for eng in ts:
                if eng == "fused-exact" and r >= reps_exact:
                    continue
                o = solve_formulation(f, ps, scen, grids, engine=eng)
                ts[eng].append(o.t_backward)
                fuel[eng] = (o.sim.fuel_g, o.extra.get("kernel"))
        out[f + "_kernels"] = {e: {"kernel": fuel[e][1], "t_backward_s": v, "median_s": statistics.median(v),
                                   "fuel_g": fuel[e][0]} for e, v in ts.items()}
        print(f"{f} backward pass, alternated, {reps} and {reps_exact} run(s): {fuel['fused'][1]} kernel median "
              f"{statistics.median(ts['fused']):.3f} s ({', '.join(f'{t:.3f}' for t in ts['fused'])}), exact fused "
              f"kernel {statistics.median(ts['fused-exact']):.3f} s "
              f"({', '.join(f'{t:.3f}' for t in ts['fused-exact'])}), "
              f"{statistics.median(ts['fused-exact']) / statistics.median(ts['fused']):.1f} times; fuel "
              f"{fuel['fused'][0]:.4f} / {fuel['fused-exact'][0]:.4f} g; load now {os.getloadavg()[0]:.2f}", flush=True)
    # Baseline-DP's default grid (BASELINE_CONVERGED_GRIDS: the paper's steps are not converged for it)
    bg = BASELINE_CONVERGED_GRIDS
    o = solve_formulation("baseline", ps, scen, bg)
    out["baseline_default"] = {"grid": bg.to_dict(), "n_states": o.n_states, "n_controls": o.n_controls,
                               "t_total_s": o.t_total, "t_backward_s": o.t_backward,
                               "n_evaluations": o.n_evaluations, "evals_per_second": o.evals_per_second,
                               "fuel_corrected_g": o.sim.summary()["fuel_corrected_g"], "threads": 1}
    print(f"baseline on its default grid {bg.to_dict()}: {o.n_states} states x {o.n_controls} controls: total "
          f"{o.t_total:.3f} s (backward {o.t_backward:.3f} s, {o.evals_per_second / 1e6:.0f} M evals/s, "
          f"{o.extra.get('kernel', 'generic')} kernel, 1 thread); corrected fuel {out['baseline_default']['fuel_corrected_g']:.4f} g", flush=True)
    # the converged Thermal-Cabin-DP grid (its kernels are compiled by the solve above)
    cg = CABIN_CONVERGED_GRIDS
    o = solve_formulation("thermal_cabin", ps, scen, cg)
    summ = o.sim.summary()
    r = {"grid": cg.to_dict(), "n_states": o.n_states, "n_controls": o.n_controls, "t_total_s": o.t_total,
         "t_backward_s": o.t_backward, "n_evaluations": o.n_evaluations, "evals_per_second": o.evals_per_second,
         "fuel_corrected_g": summ["fuel_corrected_g"], "T_cab_mean_degC": summ["T_cab_mean_degC"],
         "fuel_corrected_paper_grid_g": paper["fuel_corrected_g"]}
    print(f"thermal_cabin on the converged grid {cg.to_dict()}: {o.n_states} states x {o.n_controls} controls: "
          f"total {o.t_total:.3f} s (backward {o.t_backward:.3f} s, {o.evals_per_second / 1e6:.0f} M evals/s; "
          f"target 20 s); corrected fuel {r['fuel_corrected_g']:.4f} g (paper grid {paper['fuel_corrected_g']:.4f} g)",
          flush=True)
    if halve:
        from optimize import halving_row

        h = solve_formulation("thermal_cabin", ps, scen, cg.halved())
        hr = halving_row("thermal_cabin", cg, o.sim, h.sim, o, h)
        r.update(halved_grid=hr["grid_half"], halved_n_states=h.n_states, halved_n_controls=h.n_controls,
                 halved_t_total_s=h.t_total, fuel_corrected_halved_g=hr["fuel_corrected_g_half"],
                 halving_change_pct=hr["rel_change_corrected_pct"], T_cab_mean_change_degC=hr["T_cab_mean_change_K"],
                 converged=hr["converged"])
        print(f"  every step halved ({h.n_states} states x {h.n_controls} controls, {h.t_total:.0f} s): corrected fuel "
              f"{hr['fuel_corrected_g_half']:.4f} g ({hr['rel_change_corrected_pct']:+.3f} %), mean cabin "
              f"{hr['T_cab_mean_change_K']:+.4f} degC: {'converged' if hr['converged'] else 'NOT converged'}", flush=True)
    out["thermal_cabin_converged"] = r
    return out
