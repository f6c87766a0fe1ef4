"""The machine's measured limits, for reading a kernel's throughput: memory bandwidth and flop rates.

* bandwidth: ``np.copyto`` of a 256 MB float64 array (reads and writes 512 MB), median of 5;
* peak flop rate: a float64 matrix product (BLAS, all its threads), 2 n^3 flops, median of 3;
* compiled scalar flop rate: a numba loop of independent multiply-adds on 8 accumulators per thread, on
  the threads numba uses: the kind of arithmetic the DP kernels do, without their memory traffic.
"""
from __future__ import annotations

import time

import numpy as np


def _median_time(fn, reps):
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _fma_kernel():
    from numba import njit, prange

    @njit(parallel=True, cache=True)
    def fma(n_per_thread, n_threads):
        out = np.zeros(n_threads)
        for t in prange(n_threads):
            a = np.empty(8)
            for i in range(8):
                a[i] = 1.0 + t * 1e-9 + i * 1e-3
            m, c = 0.999999, 1e-7
            for _ in range(n_per_thread):
                for i in range(8):  # unrolled by the compiler: 8 independent chains hide the latency
                    a[i] = a[i] * m + c
            out[t] = a.sum()
        return out

    return fma


def measure(quick: bool = False) -> dict:
    """Bandwidth (GB/s), BLAS and compiled scalar flop rates (GFLOP/s) of this machine, measured now."""
    import numba

    n = (8 if quick else 32) * 1024 * 1024  # float64 values: 64 or 256 MB
    src = np.ones(n)
    dst = np.empty_like(src)
    t = _median_time(lambda: np.copyto(dst, src), 5)
    bw = 2 * src.nbytes / t / 1e9
    m = 1024 if quick else 2048
    A = np.random.default_rng(0).random((m, m))
    tm = _median_time(lambda: A @ A, 3)
    blas = 2.0 * m ** 3 / tm / 1e9
    th = numba.get_num_threads()
    fma = _fma_kernel()
    fma(1000, th)
    it = 2_000_000 if quick else 20_000_000
    tf = _median_time(lambda: fma(it, th), 3)
    scalar = 16.0 * it * th / tf / 1e9  # 8 multiply-adds = 16 flops per iteration
    return {"bandwidth_GB_per_s": bw, "blas_GFLOP_per_s": blas, "scalar_GFLOP_per_s": scalar, "threads": th}
