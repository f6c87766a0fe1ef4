"""The Report page: the run's stage progress at the top (not a fixed 10 %), a failed run clears its bar and
shows the error, and the summary names every subsystem left at its priors (streamlit.testing.v1.AppTest, with
the main job replaced by a stand-in that reports stages)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("streamlit")
from streamlit.testing.v1 import AppTest  # noqa: E402

from iptm import pipeline  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _env(tmp_path_factory, monkeypatch):
    base = tmp_path_factory.getbasetemp()
    monkeypatch.setenv("IPTM_CACHE_DIR", str(base / "iptm-cache"))
    monkeypatch.setenv("IPTM_SESSION_ROOT", str(base / "sessions"))


def _page_with_logs(tmp_path):
    at = AppTest.from_file(str(ROOT / "app.py"), default_timeout=300)
    at.run()
    csv = (ROOT / "logs" / "winter_warm_restart.csv").read_bytes()
    at.file_uploader(key="log_upload").upload("w.csv", csv, "text/csv")
    at.run()
    at.switch_page("pages/report.py").run()
    assert not at.exception, [e.value for e in at.exception]
    return at


def test_stage_progress_and_the_priors_banner(monkeypatch, tmp_path):
    seen = []

    def fake_run(cfg):
        for k, stage in enumerate(["ingest", "calibrate", "optimise", "report"], 1):
            cfg.on_progress(k, 4, stage, 0.5, f"{stage} half way")
            seen.append(cfg.on_progress)
        # the scenario's grids are the command line's when the Optimize page was not visited
        from iptm.present import converged_grids

        assert cfg.grids == converged_grids()
        d = Path(cfg.reports_dir) / "r1"
        d.mkdir(parents=True)
        (d / "index.html").write_text("<!DOCTYPE html><html><table></table></html>")
        summary = {"run_id": "r1", "n_estimated": 17, "n_weak": 1, "ordering_ok": True,
                   "calibration_text": "17 parameters estimated (4 of them tables with only some entries "
                                       "determined), 1 weakly informed (posterior mostly the prior)",
                   "at_prior": ["fuel parameters (fuel_scale) left at their priors: no log has fuel rate"]}
        (d / "report.json").write_text(json.dumps({"summary": summary, "case_study": {"table": [
            {"strategy": "Rule-based (tuned)", "fuel_corrected_g": 10.0, "fuel_g": 9.0}]}}))
        return pipeline.RunOutcome(d, summary, 1.0)

    monkeypatch.setattr(pipeline, "run", fake_run)
    at = _page_with_logs(tmp_path)
    at.button(key="rep_run").click()
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    assert len(seen) == 4
    bars = at.get("progress")
    assert len(bars) == 1 and "done in" in bars[0].proto.text and bars[0].proto.value == 100
    assert any("Not fitted: fuel parameters (fuel_scale) left at their priors" in w.value.replace("\\", "")
               for w in at.warning)
    assert any("17 parameters estimated (4 of them" in c.value for c in at.caption)


def test_a_failed_run_clears_its_progress_and_shows_the_error(monkeypatch, tmp_path):
    from calib.errors import ScenarioError

    def failing(cfg):
        cfg.on_progress(3, 5, "optimise", 0.4, "Thermal-DP: solving, step 40 of 100")
        raise ScenarioError("the drive cannot be followed")

    monkeypatch.setattr(pipeline, "run", failing)
    at = _page_with_logs(tmp_path)
    at.button(key="rep_run").click()
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    assert not at.get("progress")
    assert any("Report failed" in e.value and "cannot be followed" in e.value for e in at.error)
    assert "iptm_report" not in at.session_state
