"""Benchmark: forward simulation speed (993-s ARTEMIS Urban, rule-based) and the EPA comparison."""
from __future__ import annotations

import time


def run(quick: bool = False) -> dict:
    from calib.model import default_parameters, epa_comparison, simulate

    ps = default_parameters()
    simulate(ps, "artemis_urban")  # compile / load the numba cache outside the timing
    reps = 3 if quick else 20
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        res = simulate(ps, "artemis_urban", T_amb=-10.0, soc0=0.6, T_cl0=70.0, T_cab0=20.0, Q_heat=1500.0)
        times.append(time.perf_counter() - t0)
    best, med = min(times), sorted(times)[len(times) // 2]
    n = len(res.e_mode)
    print(f"simulate ARTEMIS Urban ({n} steps, rule-based): median {med * 1e3:.1f} ms, best {best * 1e3:.1f} ms "
          f"({n / med / 1e3:.0f} k steps/s) over {reps} runs")
    df = epa_comparison(ps)
    print("EPA warm comparison (rule-based, SOC-corrected):")
    print(df.to_string(index=False))
    return {"sim_artemis_median_s": med, "sim_artemis_best_s": best, "sim_artemis_times_s": times, "steps": n,
            "epa": df.to_dict(orient="records")}
