"""Parameter sweeps on dask.distributed (optimize/sweep.py, iptm sweep).

One LocalCluster (2 worker processes, 1 thread each) is shared by the module. The small study: 2 ambients x
2 cycles, the first 60 s of each cycle, coarse grids, rule-based + Thermal-DP.
"""
from __future__ import annotations

import json
import os
import signal
import threading
import time

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("distributed")

from calib.errors import ParameterError, ScenarioError  # noqa: E402
from calib.model.params import default_parameters  # noqa: E402
from optimize.sweep import (Study, load_study, montecarlo_draws, plot_study, run_case, run_sequential,  # noqa: E402
                            run_study, write_table)

GRIDS = {"soc": 0.02, "tcl": 2.0, "pbat": 1000.0}
SMALL = dict(name="small", strategies=["rule", "thermal"], grids=GRIDS, scenario={"duration_s": 60.0},
             vary={"T_amb": [-10.0, 0.0], "cycle": ["artemis_urban", "nycc"]})
SMALL_TOML = """
[study]
name = "small"
strategies = ["rule", "thermal"]
grids = "soc=0.02,tcl=2,pbat=1000"
[scenario]
duration_s = 60
[vary]
T_amb = [-10, 0]
cycle = ["artemis_urban", "nycc"]
"""
COLS = ["case_id", "cycle", "T_amb", "strategy", "status", "fuel_g", "fuel_corrected_g", "soc_final",
        "T_cl_final_degC", "T_cab_final_degC", "saving_pct"]


@pytest.fixture(scope="module")
def client():
    from optimize.sweep import local_client

    c = local_client(2)
    yield c
    cluster = c.cluster
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return tmp_path_factory.mktemp("sweep_store")


@pytest.fixture(scope="module")
def reference():
    """The small study run case by case in this process (no cluster, no store)."""
    return run_sequential(Study(**SMALL))


# --------------------------------------------------------------------------------------------------- no cluster
def test_expand_keys_and_validation(tmp_path):
    st = Study(**SMALL)
    cases = st.expand()
    assert len(cases) == 4
    assert len({c["key"] for c in cases}) == 4
    assert {(c["scenario"]["cycle"], c["scenario"]["T_amb"]) for c in cases} == {
        (cy, t) for cy in ("artemis_urban", "nycc") for t in (-10.0, 0.0)}
    assert [c["key"] for c in Study(**SMALL).expand()] == [c["key"] for c in cases]  # stable
    json.dumps(cases)  # JSON-able
    # the key follows content, not labels or the test hold
    assert Study(**{**SMALL, "hold_s": 3.0}).expand()[0]["key"] == cases[0]["key"]
    assert Study(**{**SMALL, "grids": {**GRIDS, "soc": 0.01}}).expand()[0]["key"] != cases[0]["key"]
    # [[case]] list crossed with [vary]
    st2 = Study(name="l", strategies=["thermal"], cases=[{"Q_heat": 1000.0}, {"Q_heat": 2000.0}],
                vary={"T_amb": [-5.0]})
    assert [c["scenario"]["Q_heat"] for c in st2.expand()] == [1000.0, 2000.0]
    # [link]: a cold start, coolant at the ambient
    st3 = Study(name="c", strategies=["thermal"], scenario={"T_cl_min": -25.0}, vary={"T_amb": [-20.0, 5.0]},
                link={"T_cl0": "T_amb"})
    assert [c["scenario"]["T_cl0"] for c in st3.expand()] == [-20.0, 5.0]
    with pytest.raises(ScenarioError, match="link"):
        Study(name="bad", link={"T_cl0": "ambient"})
    with pytest.raises(ScenarioError, match="unknown scenario field"):
        Study(name="bad", vary={"T_ambient": [1.0]})
    with pytest.raises(ScenarioError, match="unknown strategy"):
        Study(name="bad", strategies=["dp"])
    with pytest.raises(ScenarioError, match="reference"):
        Study(name="bad", strategies=["thermal"], reference="rule")
    # wrong types in a study file are clean errors (found by the fuzz harness: grids = 0.6)
    with pytest.raises(ScenarioError, match="grids must be a table"):
        Study(name="bad", grids=0.6)
    with pytest.raises(ScenarioError, match="strategies must be a list"):
        Study(name="bad", strategies=3.0)
    with pytest.raises(ScenarioError, match="bad grid"):
        Study(name="bad", grids={"soc": "fine"})
    p = tmp_path / "s.toml"
    p.write_text(SMALL_TOML)
    assert [c["key"] for c in load_study(p).expand()] == [c["key"] for c in cases]


def _artifact(tmp_path):
    ps = default_parameters()
    for n, se in (("C_eng_J_per_K", 8000.0), ("UA_cab_W_per_K", 5.0), ("fuel_scale", 0.02)):
        ps.param(n).status, ps.param(n).stderr = "estimated", se
    ps.param("hA_eng_W_per_K").stderr = 3.0  # a stderr but not estimated: must not be drawn
    path = tmp_path / "calib.toml"
    ps.save(path)
    return ps, path


def test_montecarlo_draws(tmp_path):
    ps, path = _artifact(tmp_path)
    draws = montecarlo_draws(path, 6, seed=3)
    again = montecarlo_draws(path, 6, seed=3)
    assert [d.draw for d in draws] == list(range(6))
    changed = set()
    for d, d2 in zip(draws, again):
        for n in ps:
            if d.pset[n] != ps[n]:
                changed.add(n)
            assert d.pset[n] == d2.pset[n]
            lo, hi = d.pset.param(n).bounds
            vals = d.pset[n] if d.pset.param(n).is_table else [d.pset[n]]
            assert all(lo <= v <= hi for v in vals)
    assert changed == {"C_eng_J_per_K", "UA_cab_W_per_K", "fuel_scale"}
    assert len({d.pset["C_eng_J_per_K"] for d in draws}) == 6
    with pytest.raises(ParameterError, match="estimated"):
        montecarlo_draws(default_parameters(), 2)
    # through a study file: 3 draws x 2 ambients
    (tmp_path / "mc.toml").write_text('[study]\nstrategies = ["thermal"]\n[vary]\nT_amb = [-10, 0]\n'
                                      '[params]\nmontecarlo = {artifact = "calib.toml", n = 3, seed = 3}\n')
    cases = load_study(tmp_path / "mc.toml").expand()
    assert len(cases) == 6 and len({c["key"] for c in cases}) == 6
    assert sorted({c["labels"]["draw"] for c in cases}) == [0, 1, 2]


def test_run_case_records_errors():
    case = Study(**SMALL).expand()[0]
    bad = json.loads(json.dumps(case))
    bad["scenario"]["cycle"] = "no_such_cycle"
    rec = run_case(bad)
    assert rec["error"] and rec["results"] == {}


# --------------------------------------------------------------------------------------------------- on the cluster
def _compare(df, ref):
    a = df[COLS].sort_values(["case_id", "strategy"]).reset_index(drop=True)
    b = ref[COLS].sort_values(["case_id", "strategy"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=1e-9, atol=1e-9)


def test_study_on_local_cluster_matches_sequential(client, store, reference, tmp_path):
    seen = []
    df = run_study(Study(**SMALL), client=client, store_dir=store,
                   progress_callback=lambda d, t, r: seen.append((d, t)))
    assert seen[-1] == (4, 4) and len(seen) == 4
    assert (df["status"] == "ok").all() and not df["cached"].any()
    assert len(df) == 8
    _compare(df, reference)
    # the cases ran on the workers, not here: each stored record carries the pid of the process that ran it
    from calib.store import Store

    worker_pids = set(client.run(os.getpid).values())
    pids = {Store(store).get_json("sweep", k)["pid"] for k in df["case_key"].unique()}
    assert pids and pids <= worker_pids and os.getpid() not in pids
    # Parquet round trip and plots
    p = write_table(df, tmp_path / "r.parquet")
    back = pd.read_parquet(p)
    _compare(back, df)
    paths = plot_study(df, tmp_path / "plots")
    assert [os.path.basename(x) for x in paths] == ["saving_vs_ambient.png"]
    assert os.path.getsize(paths[0]) > 1000
    # resume: nothing recomputed (a client that cannot run anything would fail if used)
    t0 = time.perf_counter()
    again = run_study(Study(**SMALL), client=object(), store_dir=store)
    assert time.perf_counter() - t0 < 5
    assert again["cached"].all()
    _compare(again, df)


def test_interrupted_study_resumes(client, store, reference):
    """A store holding only some cases (an interrupted run) -> only the missing ones are submitted."""
    from calib.store import Store

    st = Study(**{**SMALL, "name": "resume"})
    cases = st.expand()
    import shutil

    part = store.parent / "partial_store"
    shutil.rmtree(part, ignore_errors=True)
    for c in cases[:2]:
        Store(part).put_json("sweep", c["key"], run_case(c))
    progress = []
    df = run_study(st, client=client, store_dir=part, progress_callback=lambda d, t, r: progress.append((d, r)))
    assert progress[0] == (2, None)
    assert df.groupby("case_id")["cached"].first().tolist() == [True, True, False, False]
    _compare(df, reference)


def test_interrupt_then_resume(client, tmp_path, reference):
    """The study stops after its first finished case (as on Ctrl-C); the next run computes only the rest."""
    st = Study(**{**SMALL, "name": "interrupt"})

    def stop(done, total, rec):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(st, client=client, store_dir=tmp_path, progress_callback=stop)
    n_stored = len(list((tmp_path / "sweep").glob("*.json")))
    assert 1 <= n_stored < 4
    df = run_study(st, client=client, store_dir=tmp_path)
    assert int(df.groupby("case_id")["cached"].first().sum()) == n_stored
    assert (df["status"] == "ok").all()
    _compare(df, reference)


def test_failed_case_recorded_others_complete(client, tmp_path):
    st = Study(name="fail", strategies=["rule", "thermal"], grids=GRIDS, scenario={"duration_s": 60.0},
               cases=[{"cycle": "nycc"}, {"cycle": "nycc", "soc0": 0.3}, {"cycle": "no_such_cycle"}])
    df = run_study(st, client=client, store_dir=tmp_path)
    by = {(r.case_id, r.strategy): r for r in df.itertuples()}
    assert by[0, "rule"].status == "ok" and by[0, "thermal"].status == "ok"
    assert by[1, "rule"].status == "ok"  # the rule-based controller runs from SOC 0.3...
    assert by[1, "thermal"].status == "failed" and "soc0" in by[1, "thermal"].error  # ...the DP grid does not
    assert np.isnan(by[1, "thermal"].fuel_g)
    assert by[2, "rule"].status == "failed" and by[2, "thermal"].status == "failed"
    assert "no_such_cycle" in by[2, "rule"].error
    # failures are stored: not recomputed unless asked
    again = run_study(st, client=object(), store_dir=tmp_path)
    assert again["cached"].all() and (again["status"] == df["status"]).all()
    redo = run_study(st, client=client, store_dir=tmp_path, retry_failed=True)
    assert redo.groupby("case_id")["cached"].first().tolist() == [True, False, False]


def test_worker_killed_mid_study(client, tmp_path, reference):
    """SIGKILL one worker process while both are busy: its case is rescheduled, nothing is lost."""
    st = Study(**{**SMALL, "name": "kill", "hold_s": 4.0})
    out, err = {}, []

    def target():
        try:
            out["df"] = run_study(st, client=client, store_dir=tmp_path)
        except BaseException as exc:  # noqa: BLE001
            err.append(exc)

    th = threading.Thread(target=target)
    th.start()
    victim = None
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        proc = client.processing()
        busy = [w for w, ts in proc.items() if any(str(t).startswith("iptm-sweep-") for t in ts)]
        if len(busy) == 2:
            victim = busy[0]
            break
        time.sleep(0.1)
    assert victim is not None, "the two workers never held a case at the same time"
    time.sleep(1.0)  # inside the case's hold
    nanny = next(n for n in client.cluster.workers.values() if n.worker_address == victim)
    pid = nanny.process.pid
    os.kill(pid, signal.SIGKILL)
    th.join(timeout=120)
    assert not th.is_alive() and not err, err
    df = out["df"]
    assert (df["status"] == "ok").all()
    assert df["case_id"].nunique() == 4
    _compare(df, reference)
    # the killed worker's case was re-run by another process (it had finished nothing: its case was on hold)
    from calib.store import Store

    pids = {Store(tmp_path).get_json("sweep", k)["pid"] for k in df["case_key"].unique()}
    assert pid not in pids and len(pids) >= 2
    # the nanny restarts the dead worker
    client.wait_for_workers(2, timeout=60)
    assert victim not in client.scheduler_info()["workers"] or len(client.scheduler_info()["workers"]) == 2


def test_cli_sweep_from_store(store, tmp_path, reference, client, capsys):
    """`iptm sweep` on the small study whose cases are all in the store: no cluster, table + plot + JSON."""
    from iptm.cli import main

    run_study(Study(**SMALL), client=client, store_dir=store)  # make sure every case is stored
    p = tmp_path / "small.toml"
    p.write_text(SMALL_TOML)
    rc = main(["sweep", str(p), "--store", str(store), "--out", str(tmp_path / "out"), "--json",
               str(tmp_path / "s.json")])
    assert rc == 0
    txt = capsys.readouterr().out
    assert "4 cases" in txt and "4 from the store" in txt
    df = pd.read_parquet(tmp_path / "out" / "results.parquet")
    _compare(df, reference)
    assert (tmp_path / "out" / "saving_vs_ambient.png").is_file()
    j = json.loads((tmp_path / "s.json").read_text())
    assert j["n_cases"] == 4 and j["n_failed"] == 0 and len(j["table"]) == 8
    assert main(["sweep", str(tmp_path / "missing.toml")]) == 2


def test_scheduler_address_and_montecarlo_spread(client, tmp_path):
    """The same call with a scheduler address instead of a Client (what --scheduler does); Monte-Carlo
    draws give different results and the spread plot."""
    ps, path = _artifact(tmp_path)
    (tmp_path / "mc.toml").write_text(
        '[study]\nname = "mc"\nstrategies = ["rule", "thermal"]\ngrids = "soc=0.02,tcl=2,pbat=1000"\n'
        '[scenario]\ncycle = "nycc"\nduration_s = 60\n[vary]\nT_amb = [-10, 0]\n'
        '[params]\nmontecarlo = {artifact = "calib.toml", n = 3, seed = 5}\n')
    st = load_study(tmp_path / "mc.toml")
    df = run_study(st, client=client.scheduler.address, store_dir=tmp_path / "store")
    assert len(df) == 12 and (df["status"] == "ok").all()
    assert sorted(df["draw"].unique().tolist()) == [0, 1, 2]
    rule = df[(df["strategy"] == "rule") & (df["T_amb"] == -10.0)]
    assert rule["fuel_g"].nunique() == 3  # the draws change the car
    paths = plot_study(df, tmp_path / "plots")
    assert sorted(os.path.basename(p) for p in paths) == ["saving_spread.png", "saving_vs_ambient.png"]
    assert len(client.scheduler_info()["workers"]) == 2  # the shared cluster is untouched


def test_montecarlo_draws_keep_f_cl_non_increasing_above_its_reference():
    """A calibrated f_cl whose hot entries sit at the reference (1) with a posterior sd: every draw is
    valid, and a hot entry drawn above the reference is held at it (the fit's constraint)."""
    ps = default_parameters()
    f = ps.param("f_cl")
    f.value = [1.6, 1.25, 1.05, 1.0, 1.0, 0.99, 0.95]
    f.stderr = [0.05, 0.03, 0.01, 0.0, 0.015, 0.02, 0.04]
    f.status = "estimated"
    draws = montecarlo_draws(ps, 12, seed=2)
    r = f.x.index(80.0)
    hot_below = 0
    for d in draws:
        v = d.pset.param("f_cl").value
        assert all(b <= a for a, b in zip(v, v[1:])), v
        assert v[r] == 1.0 and v[r + 1] <= 1.0
        hot_below += v[-1] < 0.95
    assert 0 < hot_below < len(draws)  # drawn on both sides of the estimate, not pinned
