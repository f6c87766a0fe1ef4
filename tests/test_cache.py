"""The one content-keyed cache (calib.store): keys, folder entries, size cap, configuration, and the pipeline's
use of it (a hit loads the saved results; a changed parameter misses)."""
import os
import time

import pytest

from calib.errors import IptmError
from calib.model.params import default_parameters
from calib.store import Store, default_root, result_key
from optimize.formulations.scenario import DPGrids, DPScenario

SCEN = DPScenario(cycle="nycc", duration_s=120.0, terminal="free")
GRIDS = DPGrids(soc=0.02, pbat=2000.0)


def test_result_key_misses_on_any_change(monkeypatch):
    ps = default_parameters()
    base = dict(params=ps, scenario=SCEN.to_dict(), grids=GRIDS.to_dict())
    k = result_key("baseline", **base)
    assert k == result_key("baseline", **{**base, "params": ps.copy()})
    assert k != result_key("baseline", **{**base, "params": ps.with_values(UA_cab_W_per_K=51.0)})
    assert k != result_key("baseline", **{**base, "scenario": {**SCEN.to_dict(), "T_amb": -9.0}})
    assert k != result_key("baseline", **{**base, "grids": {**GRIDS.to_dict(), "soc": 0.01}})
    assert k != result_key("thermal", **base)
    assert k != result_key("baseline", **base, options={"hold": False})
    x = ps.param("f_cl").x
    moved = ps.copy()
    moved.param("f_cl").x = [x[0] - 1.0] + x[1:]  # a table's breakpoints are part of it
    assert k != result_key("baseline", **{**base, "params": moved})
    import calib.store

    real = calib.store.code_version
    monkeypatch.setattr(calib.store, "code_version", lambda *pk: real(*pk) + "-edited")
    assert k != result_key("baseline", **base)


def test_folder_entries_are_complete_or_absent(tmp_path):
    st = Store(tmp_path)

    def broken(d):
        (d / "half.txt").write_text("half")
        raise RuntimeError("killed mid-way")

    with pytest.raises(RuntimeError):
        st.put_dir("dp", "k1", broken)
    assert st.get_dir("dp", "k1") is None and not list((tmp_path / "dp").iterdir())
    (tmp_path / "dp" / "k2").mkdir()  # a folder without its completion mark (an interrupted writer)
    assert st.get_dir("dp", "k2") is None
    d = st.put_dir("dp", "k2", lambda d: (d / "x.txt").write_text("whole"))
    assert st.get_dir("dp", "k2") == d and (d / "x.txt").read_text() == "whole"


def test_size_cap_removes_the_least_recently_used(tmp_path):
    st = Store(tmp_path, max_mb=2.5 / 1024)  # 2.5 kB
    blob = "x" * 900
    for i, key in enumerate(("old", "used", "new")):
        p = st.put_json("sweep", key, {"blob": blob})
        os.utime(p, (time.time() - 100 + 10 * i,) * 2)
    assert st.get_json("sweep", "used") is not None  # read: now the most recently used
    st.put_json("sweep", "newest", {"blob": blob})
    left = {p.stem for p in (tmp_path / "sweep").iterdir()}
    assert left == {"used", "newest"}
    assert sum(p.stat().st_size for p in (tmp_path / "sweep").iterdir()) <= st.max_bytes


def test_folder_and_cap_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("IPTM_CACHE_DIR", str(tmp_path / "c"))
    monkeypatch.setenv("IPTM_CACHE_MAX_MB", "12.5")
    assert default_root() == tmp_path / "c" and Store().root == tmp_path / "c"
    assert Store().max_bytes == int(12.5 * 1024 * 1024)
    from iptm import dashboard

    assert dashboard.cache_dir() == tmp_path / "c"  # the dashboard's folder is the same
    for bad in ("lots", "-1", "nan"):
        monkeypatch.setenv("IPTM_CACHE_MAX_MB", bad)
        with pytest.raises(IptmError, match="IPTM_CACHE_MAX_MB"):
            Store()


def test_pipeline_hit_loads_the_saved_outcome_and_a_changed_parameter_misses(tmp_path, monkeypatch, params):
    import optimize
    from iptm.pipeline import optimize_cached

    solves = []
    real = optimize.run_case_study  # the front door the pipeline calls through
    monkeypatch.setattr(optimize, "run_case_study", lambda *a, **k: solves.append(a[2]) or real(*a, **k))
    st = Store(tmp_path)
    first = optimize_cached(params, SCEN, GRIDS, ("baseline",), st, progress=False)
    assert solves == [("baseline",)]
    again = optimize_cached(params, SCEN, GRIDS, ("baseline",), st, progress=False)
    assert solves == [("baseline",)]  # a hit
    o, back = first.outcomes["baseline"], again.outcomes["baseline"]
    assert back.cached and not getattr(o, "cached", False)
    assert _json(back.describe()) == _json(o.describe())
    assert back.sim.to_pandas().equals(o.sim.to_pandas())
    assert again.to_dict()["table"] == first.to_dict()["table"]
    optimize_cached(params.with_values(UA_cab_W_per_K=51.0), SCEN, GRIDS, ("baseline",), st, progress=False)
    assert solves == [("baseline",), ("baseline",)]  # a changed parameter misses


def _json(d):
    import json

    return json.dumps(d, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o), sort_keys=True)
