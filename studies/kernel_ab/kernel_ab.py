"""Before/after timing of the fused DP kernels in one process: the kernels of an earlier commit against the
working tree's, alternated, so that both see the same machine (on a shared machine, timings of separate
processes minutes apart differ by up to 2 times).

    .venv/bin/python studies/kernel_ab/kernel_ab.py REV [--states 2|3] [--duration S] [--reps N]

REV's ``optimize/formulations/fused.py`` is loaded from git as a second module (compiled without numba's
cache, beside the working tree's); both run the backward pass of the default car on the paper's grids
(``--states 2``: Thermal-DP, 3: Thermal-Cabin-DP) over the first S seconds of the default drive. Prints the
median backward-pass time of each, every time, the load average, and whether the value functions and levels
are the same bit for bit. Set ``NUMBA_NUM_THREADS`` for the thread count.
"""
import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def load_rev(rev: str):
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:optimize/formulations/fused.py"], check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "fused_before.py"
    path.write_text(src.replace("cache=True", "cache=False"))
    spec = importlib.util.spec_from_file_location("fused_before", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rev")
    ap.add_argument("--states", type=int, choices=(2, 3), default=2)
    ap.add_argument("--duration", type=float, default=None, help="seconds of the drive (default: all of it)")
    ap.add_argument("--reps", type=int, default=7)
    a = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from calib.model import default_parameters
    from optimize.formulations import DPGrids, DPScenario, backward_pass_fused, build_problem

    before = load_rev(a.rev)
    prob = build_problem(default_parameters(), DPScenario(duration_s=a.duration), DPGrids(), a.states).prob
    print(f"{prob.grid_shape} states x {prob.n_controls} controls, {prob.N} steps; numba threads "
          f"{os.environ.get('NUMBA_NUM_THREADS', 'default')}; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '')}; "
          f"load before {os.getloadavg()[0]:.2f}", flush=True)
    ts, vf = {"before": [], "after": []}, {}
    for r in range(a.reps + 1):  # the first round compiles
        for name, kernel in (("before", before.backward_pass_fused), ("after", backward_pass_fused)):
            v = kernel(prob)
            if r:
                ts[name].append(v.t_backward)
            vf[name] = v
    for name, t in ts.items():
        print(f"{name} ({a.rev if name == 'before' else 'working tree'}, {vf[name].kernel}): median "
              f"{statistics.median(t):.3f} s ({', '.join(f'{x:.3f}' for x in t)})")
    b, n = vf["before"], vf["after"]
    fin = np.isfinite(b.V)
    dv = float(np.max(np.abs(np.where(fin, b.V - n.V, 0.0)))) if fin.any() else float("nan")
    print(f"max |dV| {dv:g}; finite at the same nodes {np.array_equal(fin, np.isfinite(n.V))}; levels equal "
          f"{np.array_equal(b.L, n.L)}; ratio {statistics.median(ts['before']) / statistics.median(ts['after']):.2f}; "
          f"load now {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    main()
