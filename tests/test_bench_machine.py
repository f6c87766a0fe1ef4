"""The machine-limit probe printed by ``iptm bench dp`` (iptm/benchmarks/machine.py)."""
import numpy as np

from iptm.benchmarks.machine import measure


def test_machine_limits_are_measured_and_ordered():
    """Bandwidth and both flop rates are positive and finite, and the BLAS matrix product (vectorised, all
    threads, cache-blocked) is faster than the compiled scalar multiply-add loop, which it is on any CPU
    with SIMD units; a probe that measured nothing (zero, NaN) or mixed up the two figures fails."""
    m = measure(quick=True)
    for key in ("bandwidth_GB_per_s", "blas_GFLOP_per_s", "scalar_GFLOP_per_s"):
        assert np.isfinite(m[key]) and m[key] > 0.0, (key, m[key])
    assert m["blas_GFLOP_per_s"] > m["scalar_GFLOP_per_s"]
    assert m["threads"] >= 1
