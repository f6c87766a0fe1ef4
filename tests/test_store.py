from pathlib import Path

import numpy as np
import pytest

from calib.model.simulate import sim_from_arrays, sim_to_arrays, simulate
from calib.store import Store, content_key


def test_content_key_stable_and_sensitive():
    a = content_key({"x": 1.0, "y": [1, 2]}, "s")
    assert a == content_key({"y": [1, 2], "x": 1.0}, "s")
    assert a != content_key({"x": 1.0000001, "y": [1, 2]}, "s")
    assert content_key(np.arange(3.0)) == content_key([0.0, 1.0, 2.0])


def test_store_round_trip_sim(tmp_path, params):
    res = simulate(params, "nycc", T_amb=-5.0)
    st = Store(tmp_path)
    st.put_npz("sim", "k1", sim_to_arrays(res))
    back = sim_from_arrays(st.get_npz("sim", "k1"))
    assert back.summary()["fuel_g"] == pytest.approx(res.summary()["fuel_g"])
    assert back.info == res.info
    assert st.get_json("x", "missing") is None
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "bad.json").write_text("{not json")
    assert st.get_json("x", "bad") is None


def test_code_version_follows_the_source(tmp_path):
    """Editing any file of a package (here a copy of calib) changes code_version, so cached results
    computed by the old code are not served."""
    import shutil
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    shutil.copytree(root / "calib", tmp_path / "calib", ignore=shutil.ignore_patterns("__pycache__"))
    probe = [sys.executable, "-c", "import calib.store as s, calib; assert calib.__file__.startswith(%r); "
             "print(s.code_version('calib'))" % str(tmp_path)]
    env = {**__import__("os").environ, "PYTHONPATH": str(tmp_path)}
    first = subprocess.run(probe, env=env, cwd=tmp_path, capture_output=True, text=True, check=True).stdout.strip()
    again = subprocess.run(probe, env=env, cwd=tmp_path, capture_output=True, text=True, check=True).stdout.strip()
    with open(tmp_path / "calib" / "model" / "equations.py", "a") as f:
        f.write("\n# an edit\n")
    edited = subprocess.run(probe, env=env, cwd=tmp_path, capture_output=True, text=True, check=True).stdout.strip()
    assert first == again and edited != first
