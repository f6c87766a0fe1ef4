"""The dashboard's Optimize and Report pages against the command line: the same converged grids by default,
a preview labelled with its measured difference, the CLI's terminal conditions, and a failed run that leaves
no progress bar behind (streamlit.testing.v1.AppTest)."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("streamlit")
from streamlit.testing.v1 import AppTest  # noqa: E402

from iptm import dashboard as dash  # noqa: E402
from iptm import present  # noqa: E402
from optimize.formulations.scenario import DEFAULT_GRIDS, TERMINALS, DPScenario  # noqa: E402

APP = str(Path(__file__).resolve().parent.parent / "app.py")


@pytest.fixture(autouse=True)
def _env(tmp_path_factory, monkeypatch):
    base = tmp_path_factory.getbasetemp()
    monkeypatch.setenv("IPTM_CACHE_DIR", str(base / "iptm-cache"))
    monkeypatch.setenv("IPTM_SESSION_ROOT", str(base / "sessions"))


def _optimize_page():
    at = AppTest.from_file(APP, default_timeout=300)
    at.run()
    at.switch_page("pages/optimize.py").run()
    assert not at.exception, [e.value for e in at.exception]
    at.radio(key="opt_params_src").set_value("default 2017 Prius")
    at.number_input(key="opt_duration").set_value(30.0)
    at.multiselect(key="opt_strategies").set_value(["thermal"])
    at.run()
    return at


def test_defaults_are_the_command_lines():
    at = _optimize_page()
    assert at.radio(key="opt_grid_choice").value == "converged"
    sc = at.session_state[dash.SCENARIO]
    assert sc["grids"] == DEFAULT_GRIDS  # what `iptm optimize` / `iptm run` solve on without --grid
    term = at.selectbox(key="opt_terminal")
    assert list(term.options) == list(TERMINALS) and term.value == DPScenario().terminal
    term.set_value("free")
    at.run()
    assert at.session_state[dash.SCENARIO]["scenario"].terminal == "free"
    at.radio(key="opt_grid_choice").set_value("preview")
    at.run()
    assert at.session_state[dash.SCENARIO]["grids"] == present.preview_grids()
    assert "not measured yet" in at.radio(key="opt_grid_choice").options[1]


def test_a_failed_run_clears_its_progress(monkeypatch):
    import optimize  # the page solves through optimize's front door

    from calib.errors import ScenarioError

    def boom(*a, **k):
        raise ScenarioError("the drive cannot be followed")

    monkeypatch.setattr(optimize, "run_case_study", boom)
    at = _optimize_page()
    at.number_input(key="opt_duration").set_value(29.0)  # a scenario no other test solved (solves are cached)
    at.run()
    at.button(key="opt_run").click()
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    assert any("Optimisation failed" in e.value and "cannot be followed" in e.value for e in at.error)
    assert not at.get("progress")  # no bar left reading "solving..."
    assert dash.OPT not in at.session_state


def test_preview_is_measured_against_the_converged_grids():
    at = _optimize_page()
    at.radio(key="opt_grid_choice").set_value("preview")
    at.run()
    at.button(key="opt_run").click()
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    prev_cs = at.session_state[dash.OPT]["cs"]
    assert any("not measured yet" in i.value for i in at.info)
    at.button(key="opt_measure_preview").click()
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    got = at.session_state["iptm_preview_diff"]["diff"]
    # the difference shown is the one computed from both solves of this scenario
    from calib.model.params import default_parameters
    from optimize.casestudy import run_case_study

    conv = run_case_study(default_parameters(), prev_cs.scenario, ("thermal",), progress=False,
                          grids=present.converged_grids())
    want = present.preview_difference(prev_cs, conv)
    assert got["thermal"]["diff_pct"] == pytest.approx(want["thermal"]["diff_pct"], rel=1e-9, abs=1e-12)
    assert any(present.difference_text(got) in i.value for i in at.info)
    assert present.difference_text(got) in at.radio(key="opt_grid_choice").options[1]
