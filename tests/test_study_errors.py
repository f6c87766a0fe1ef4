"""A study file's bad [vary] value is refused on loading, by one message naming the study file."""
import pytest

from calib.errors import ScenarioError
from optimize.sweep import load_study


@pytest.mark.parametrize("bad", ["inf", "-inf", "nan", "1e400"])
def test_bad_vary_value_names_the_study_file(tmp_path, bad):
    path = tmp_path / "cold.toml"
    path.write_text('[study]\nstrategies = ["rule"]\n[scenario]\ncycle = "nycc"\n'
                    f"[vary]\nT_amb = [-7.0, {bad}]\n")
    with pytest.raises(ScenarioError) as err:
        load_study(path)
    msg = str(err.value)
    assert str(path) in msg and "T_amb" in msg and "finite" in msg
    assert "\n" not in msg


def test_good_vary_values_load(tmp_path):
    path = tmp_path / "ok.toml"
    path.write_text('[study]\nstrategies = ["rule"]\n[scenario]\ncycle = "nycc"\n[vary]\nT_amb = [-7.0, 0.0, 5.0]\n')
    assert len(load_study(path).expand()) == 3
