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
