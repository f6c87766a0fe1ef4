"""`iptm optimize --scenario` reads the same file as `iptm run`: [scenario], [grids] and [run]."""
from types import SimpleNamespace

import pytest

from calib.errors import ScenarioError
from iptm.commands.optimize import _scenario


def _args(path, **kw):
    base = dict(scenario=str(path), cycle=None, duration=None, ambient=None, soc0=None, tcl0=None, tcab0=None,
                heater=None, terminal=None)
    base.update(kw)
    return SimpleNamespace(**base)


def test_sections_are_read_not_ignored(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('[scenario]\ncycle = "udds"\nduration_s = 60\n[grids]\nsoc = 0.02\n'
                 '[run]\nstrategies = ["rule", "baseline"]\n')
    scen, grids, strategies = _scenario(_args(f, ambient=-5.0))
    assert (scen.cycle, scen.duration_s, scen.T_amb) == ("udds", 60, -5.0)  # the option overrides the file
    assert grids.of("baseline").soc == 0.02 and grids.of("thermal").soc == 0.02
    assert strategies == ("rule", "baseline")


def test_flat_file_still_reads(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('cycle = "udds"\nT_amb = -7.0\n')
    scen, grids, strategies = _scenario(_args(f))
    assert scen.T_amb == -7.0 and grids is None and strategies is None


@pytest.mark.parametrize("text, msg", [
    ('[scenario]\nT_amb = nan\n', "finite"), ('[scenario]\nduration_s = nan\n', "finite"),
    ('[scenario]\ncycle = "from log"\n', "iptm run"), ('[scenario]\n[grids]\nsoc = -1\n', "positive"),
    ('[scenario]\n[bogus]\nx = 1\n', "unknown section"),
])
def test_bad_scenarios_are_one_message(tmp_path, text, msg):
    f = tmp_path / "s.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError, match=msg):
        _scenario(_args(f))
