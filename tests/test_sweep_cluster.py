"""A study on a real cluster: `dask scheduler` and two `dask worker` processes started as a user starts them.

The test starts the scheduler and the workers as separate processes on 127.0.0.1 (a free port), runs
`iptm sweep --scheduler tcp://127.0.0.1:PORT` as a separate process, SIGKILLs one worker while both hold a
case, and checks that every case finished and the table equals a sequential run in this process. Every
process it started is killed at the end, whatever happens.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
STUDY = """
[study]
name = "cluster"
strategies = ["rule", "thermal"]
grids = "soc=0.02,tcl=2,pbat=1000"
hold_s = 3.0
[scenario]
duration_s = 60
[vary]
T_amb = [-10, 0]
cycle = ["artemis_urban", "nycc"]
"""
COLS = ["cycle", "T_amb", "strategy", "status", "fuel_g", "fuel_corrected_g", "soc_final", "T_cl_final_degC",
        "T_cab_final_degC", "saving_pct"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update({"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                "OPENBLAS_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    return env


def _start(args, log: Path):
    fh = open(log, "wb")
    # its own process group, so the nanny's worker child goes with it at clean-up
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, env=_env(), stdout=fh, stderr=subprocess.STDOUT,
                            start_new_session=True), fh


def _stop(proc):
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


@pytest.mark.timeout(240)
def test_study_survives_a_killed_worker_on_a_real_cluster(tmp_path):
    from distributed import Client

    from optimize.sweep import load_study, run_sequential

    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    study_file = tmp_path / "cluster.toml"
    study_file.write_text(STUDY)
    procs = []
    client = None
    try:
        procs.append(_start(["-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                             "--dashboard-address", ":0"], tmp_path / "scheduler.log"))
        for i in range(2):
            procs.append(_start(["-m", "distributed.cli.dask_worker", addr, "--nthreads", "1", "--nworkers", "1",
                                 "--dashboard-address", ":0", "--name", f"w{i}"], tmp_path / f"worker{i}.log"))
        client = Client(addr, timeout=60)
        client.wait_for_workers(2, timeout=90)
        sweep, sweep_log = _start(["-m", "iptm.cli", "sweep", str(study_file), "--scheduler", addr,
                                   "--store", str(tmp_path / "store"), "--out", str(tmp_path / "out"),
                                   "--metric", "saving_pct"], tmp_path / "sweep.log")
        procs.append((sweep, sweep_log))

        # Wait until both workers hold a case, then kill one of them in the middle of its case.
        victim = None
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end and sweep.poll() is None:
            busy = [w for w, ts in client.processing().items() if any(str(t).startswith("iptm-sweep-") for t in ts)]
            if len(busy) == 2:
                victim = busy[0]
                break
            time.sleep(0.1)
        assert victim is not None, "the two workers never held a case at the same time: " + \
            (tmp_path / "sweep.log").read_text()[-2000:]
        time.sleep(1.0)  # inside the case's 3-s hold
        pid = client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)

        rc = sweep.wait(timeout=180)
        log = (tmp_path / "sweep.log").read_text()
        assert rc == 0, log[-3000:]
        assert "4 cases" in log and "0 with a failure" in log, log[-3000:]
        df = pd.read_parquet(tmp_path / "out" / "results.parquet")
        assert (df["status"] == "ok").all() and df["case_id"].nunique() == 4

        # The killed worker's case ran again elsewhere: no stored record comes from the killed process.
        from calib.store import Store

        pids = {Store(tmp_path / "store").get_json("sweep", k)["pid"] for k in df["case_key"].unique()}
        assert pid not in pids

        # Same figures as the cases run one after the other in this process.
        ref = run_sequential(load_study(study_file))
        a = df[COLS].sort_values(["cycle", "T_amb", "strategy"]).reset_index(drop=True)
        b = ref[COLS].sort_values(["cycle", "T_amb", "strategy"]).reset_index(drop=True)
        pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=1e-9, atol=1e-9)
        assert np.isfinite(a["fuel_g"]).all()
    finally:
        if client is not None:
            client.close()
        for proc, fh in reversed(procs):
            _stop(proc)
            fh.close()
