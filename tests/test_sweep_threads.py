"""A study on workers that already ran numba: the thread count numba started with and the environment's
``NUMBA_NUM_THREADS`` differ there (a dask nanny sets the environment after the worker imported numba), and
numba refuses every later compilation unless the sweep reconciles them."""
from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor

import pytest


def _warm_worker():
    """What a warmed cluster worker has done: run a parallel numba function (its thread pool starts), then
    receive an environment with another thread count."""
    import numba
    import numpy as np

    @numba.njit(parallel=True)
    def total(x):
        s = 0.0
        for i in numba.prange(x.size):
            s += x[i]
        return s

    total(np.ones(64))
    os.environ["NUMBA_NUM_THREADS"] = "1" if numba.config.NUMBA_NUM_THREADS != 1 else "2"


def _case_then_compile(case):
    """One case of the study, then a compilation in the same worker (numba re-reads the environment)."""
    import numba

    from optimize.sweep import run_case

    rec = run_case(case)

    @numba.njit
    def plus_one(x):
        return x + 1

    return rec, plus_one(1), os.environ["NUMBA_NUM_THREADS"], numba.config.NUMBA_NUM_THREADS


def _tiny_cases():
    from optimize.sweep import Study

    st = Study(name="warm_workers", strategies=["rule"], grids={},
               scenario={"duration_s": 30.0}, vary={"T_amb": [-10.0, 0.0]})
    return st.expand()


@pytest.mark.timeout(600)
def test_sweep_runs_on_workers_that_already_ran_numba():
    cases = _tiny_cases()
    ctx = multiprocessing.get_context("spawn")  # a fresh interpreter, as a cluster worker is
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_warm_worker) as pool:
        out = list(pool.map(_case_then_compile, cases))
    for rec, one_more, env, threads in out:
        assert rec["error"] is None, rec["error"]
        assert rec["results"]["rule"]["fuel_g"] > 0
        assert one_more == 2
        assert env == str(threads)  # the environment now names the pool's count


def test_limit_threads_reloads_before_the_pool_starts(monkeypatch):
    """Before numba's pool starts, the environment's count is taken (the worker then starts that many)."""
    from numba.core import config
    from numba.np.ufunc import parallel

    from optimize import sweep

    calls = []
    monkeypatch.setattr(parallel, "_is_initialized", False)
    monkeypatch.setattr(config, "reload_config", lambda: calls.append("reload"))
    monkeypatch.setenv("NUMBA_NUM_THREADS", str(config.NUMBA_NUM_THREADS + 1))
    sweep._agree_numba_threads()
    assert calls == ["reload"]
    assert os.environ["NUMBA_NUM_THREADS"] == str(config.NUMBA_NUM_THREADS + 1)
