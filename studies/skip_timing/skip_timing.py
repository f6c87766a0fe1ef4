"""Thermal-DP's fused backward pass on the default drive, computing every SOC node against skipping those
outside [soc_min, soc_max] (`backward_pass_fused(prob, skip=...)`), alternated in one process.

    .venv/bin/python studies/skip_timing/skip_timing.py [REPEATS]
"""
import os
import sys
import time

import numpy as np

from calib.model import default_parameters
from optimize.formulations import DPGrids, DPScenario, backward_pass_fused, build_problem


def main(reps=5):
    b = build_problem(default_parameters(), DPScenario(), DPGrids(), 2)
    for skip in (True, False):
        backward_pass_fused(b.prob, skip=skip)  # compile
    t = {True: [], False: []}
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    for _ in range(reps):
        for skip in (False, True):
            t0 = time.perf_counter()
            vf = backward_pass_fused(b.prob, skip=skip)
            t[skip].append(time.perf_counter() - t0)
            t[(skip, "n")] = vf.n_evaluations
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    for skip in (False, True):
        x = t[skip]
        print(f"skip={skip}: median {np.median(x):.3f} s (range {min(x):.3f}-{max(x):.3f}), "
              f"{t[(skip, 'n')]:.3g} evaluations")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
