"""Benchmark: a 16-case Thermal-DP study on 2 local dask workers vs the same cases in sequence.

Study: Thermal-DP only, 8 ambients (-25 to +10 degC, step 5) x 2 whole cycles (ARTEMIS Urban 993 s, NYCC
598 s) on the paper's grids (Table II: SOC 0.01, T_cl 1 degC, P_bat 500 W; 1-3 s per case on one core);
``quick``: the first 200 s of each cycle on coarse grids (SOC 0.02, T_cl 2 degC, P_bat 1000 W).
Both sides are warmed up first (numba compile / disk-cache load: one short case
in this process and on every worker), and each timed run uses a fresh, empty result store, so nothing is
read from a cache.

Sequential: :func:`optimize.sweep.run_case` on every case in this process, once with numba's default
thread count (the DP kernels are parallel: on a 2-core machine they already use both cores) and once with
one numba thread. Parallel: :func:`optimize.sweep.run_study` on a ``LocalCluster`` of 2 worker processes x 1
thread (numba 1 thread each); the cluster start-up is timed separately. The speed-up is bounded by the core
count (2 here).
"""
from __future__ import annotations

import os
import tempfile
import time


def _study(quick: bool):
    from optimize import Study

    scen = {"duration_s": 200.0} if quick else {}
    grids = {"soc": 0.02, "tcl": 2.0, "pbat": 1000.0} if quick else {}  # full: the paper's Table II
    return Study(name="bench_sweep", strategies=["thermal"], grids=grids, scenario=scen,
                 vary={"T_amb": [-25.0, -20.0, -15.0, -10.0, -5.0, 0.0, 5.0, 10.0],
                       "cycle": ["artemis_urban", "nycc"]})


def _failures(label: str, recs) -> list[str]:
    return [f"{label}: case {str(r.get('key') or '?')[:12]}: {r['error']}" for r in recs if r.get("error")]


def _report_failures(out: dict, failures: list[str]) -> dict:
    print(f"FAILED: {len(failures)} case(s) failed; no time or speed-up is reported")
    for f in failures[:10]:
        print(f"  {f}")
    if len(failures) > 10:
        print(f"  ... and {len(failures) - 10} more")
    out["failures"] = failures
    return out


def run(quick: bool = False) -> dict:
    import numba

    from optimize import Study, local_client, run_case, run_study

    st = _study(quick)
    cases = st.expand()
    warm = Study(name="warm", strategies=["thermal"], grids=st.grids, scenario={"duration_s": 30.0}).expand()[0]
    print(f"{len(cases)} Thermal-DP cases (8 ambients x 2 cycles{', first 200 s' if quick else ', whole cycles'}), "
          f"grids {st.grids}; {os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.1f} (other processes "
          "distort the figures)", flush=True)

    out = {"n_cases": len(cases), "quick": quick, "grids": st.grids, "cpu_count": os.cpu_count()}
    bad = _failures("warm-up in this process", [run_case(warm)])
    if bad:
        return _report_failures(out, bad)
    n_default = numba.get_num_threads()
    seq, lines = {}, []  # figures are printed once every run has succeeded
    for label, nt in (("numba_default", n_default), ("numba_1", 1)):
        numba.set_num_threads(nt)
        t0, c0 = time.perf_counter(), time.process_time()
        recs = [run_case(c) for c in cases]
        seq[label] = time.perf_counter() - t0
        seq[label + "_cpu"] = time.process_time() - c0
        bad = _failures(f"sequential, numba {nt} thread(s)", recs)
        if bad:
            numba.set_num_threads(n_default)
            return _report_failures(out, bad)
        lines.append(f"sequential, numba {nt} thread(s): {seq[label]:.1f} s (process CPU {seq[label + '_cpu']:.1f} s)")
    numba.set_num_threads(n_default)

    t0 = time.perf_counter()
    client = local_client(2)
    t_start = time.perf_counter() - t0
    try:
        # compile / load numba's cache on every worker (as a user warms a cluster: the study must still run)
        bad = _failures("warm-up on a worker", client.run(run_case, warm).values())
        with tempfile.TemporaryDirectory() as store:
            t0 = time.perf_counter()
            df = run_study(st, client=client, store_dir=store)
            t_par = time.perf_counter() - t0
            from calib import Store

            recs_par = [Store(store).get_json("sweep", c["key"]) or {"key": c["key"], "error": "no result stored"}
                        for c in cases]
            bad += _failures("2 local workers", recs_par)
            cpu_par = sum(r.get("cpu_s", 0.0) for r in recs_par)
            wall_cases_par = sum(r.get("elapsed_s", 0.0) for r in recs_par)
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    n_failed = int((df["status"] != "ok").sum())
    if n_failed and not bad:
        bad = [f"2 local workers: {n_failed} row(s) of the study table failed"]
    if bad:
        return _report_failures(out, bad)
    out.update({"numba_default_threads": n_default, "t_sequential_s": seq["numba_default"],
                "t_sequential_numba1_s": seq["numba_1"], "t_parallel_s": t_par, "t_cluster_start_s": t_start,
                "speedup": seq["numba_default"] / t_par, "speedup_vs_numba1": seq["numba_1"] / t_par,
                "speedup_incl_cluster_start": seq["numba_default"] / (t_par + t_start), "n_failed": n_failed,
                "load_average_1min_end": os.getloadavg()[0], "cpu_parallel_s": cpu_par,
                "cores_obtained_parallel": cpu_par / t_par, "case_wall_sum_parallel_s": wall_cases_par})
    print("\n".join(lines))
    print(f"2 local workers x 1 thread: {t_par:.1f} s (+ {t_start:.1f} s cluster start-up), no failure; "
          f"worker CPU {cpu_par:.1f} s, i.e. {cpu_par / t_par:.2f} cores obtained on average (2 = no contention)")
    print(f"speed-up {out['speedup']:.2f}x over sequential with numba {n_default} threads "
          f"({out['speedup_incl_cluster_start']:.2f}x counting the cluster start-up), "
          f"{out['speedup_vs_numba1']:.2f}x over sequential with 1 numba thread", flush=True)
    return out
