"""The main job end to end on small SYNTHETIC logs and coarse grids."""
import json
from pathlib import Path

import pytest

from calib.errors import IptmError
from calib.model.params import ParameterSet
from calib.synth import Scenario, draw_truth, synthesise
from calib.ingest.writers import write_streams
from iptm import pipeline
from optimize.casestudy import run_case_study
from optimize.formulations.scenario import DPGrids, DPScenario

GRIDS = DPGrids(soc=0.02, tcl=2.0, tcab=1.0, pbat=1000.0, qheat=100.0)
SCEN = DPScenario(duration_s=150.0)


@pytest.fixture(scope="module")
def small_logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("logs")
    truth = draw_truth(7)
    out = []
    for i, (name, cyc, T_cl0) in enumerate([("a_cold", "udds", -10.0), ("b_hw", "hwfet+us06", 20.0),
                                            ("c_city", "nycc", 40.0)]):
        sc = Scenario(name, cyc, -10.0, 0.6, T_cl0, -10.0 if T_cl0 < 0 else 10.0, T_bat=0.0,
                      with_bay_temp=(i == 1))
        _, streams, meta = synthesise(sc, truth, seed=i)
        out.append(write_streams(streams, meta, d / f"{name}.csv", "csv"))
    return out


@pytest.fixture(scope="module")
def first_run(small_logs, tmp_path_factory):
    root = tmp_path_factory.mktemp("run")
    cfg = pipeline.RunConfig(logs=small_logs, scenario=SCEN, grids=GRIDS, reports_dir=root / "reports",
                             cache_dir=root / "cache", progress=False)
    return cfg, pipeline.run(cfg)


def test_report_complete_and_matches_library(first_run):
    cfg, out = first_run
    d = out.report_dir
    for f in ("index.html", "report.json", "calibration.toml"):
        assert (d / f).is_file(), f
    rep = json.loads((d / "report.json").read_text())
    html = (d / "index.html").read_text()
    for sec in ("Summary", "Data used", "Calibration", "Optimisation", "Provenance", "SYNTHETIC"):
        assert sec in html
    assert rep["summary"]["synthetic_data"] is True
    assert len(rep["provenance"]["logs"]) == 3
    assert rep["provenance"]["logs"][2]["role"].startswith("validation")
    # the library, called directly with the calibrated parameters, gives the report's numbers
    ps = ParameterSet.load(d / "calibration.toml")
    cs = run_case_study(ps, SCEN, progress=False, grids=GRIDS)
    direct = {r["key"]: r for r in cs.to_dict()["table"]}
    for key, r in rep["summary"]["strategies"].items():
        assert r["fuel_g"] == pytest.approx(direct[key]["fuel_g"], rel=1e-9), key
        assert r["soc_final"] == pytest.approx(direct[key]["soc_final"], rel=1e-9), key
    assert len(rep["figures"]) >= 9
    assert set(rep["time_series"]) >= {"rule", "baseline", "thermal", "thermal_cabin"}


def test_report_prints_the_grid_convergence_check(first_run):
    """The run solves Baseline- and Thermal-DP again with every grid step halved: the report's change is the
    one between the direct library runs on the two grids, and Thermal-Cabin-DP is named as not checked."""
    from optimize.convergence import FUEL_TOL_PCT

    cfg, out = first_run
    d = out.report_dir
    conv = {r["formulation"]: r for r in json.loads((d / "report.json").read_text())["summary"]["convergence"]}
    assert set(conv) == {"baseline_warm", "baseline", "thermal"}
    ps = ParameterSet.load(d / "calibration.toml")
    half = run_case_study(ps, SCEN, ("baseline", "thermal"), progress=False, grids=GRIDS.halved())
    full = run_case_study(ps, SCEN, ("baseline", "thermal"), progress=False, grids=GRIDS)
    for f in ("baseline_warm", "baseline", "thermal"):
        c0 = full.sims[f].summary()["fuel_corrected_g"]
        c1 = half.sims[f].summary()["fuel_corrected_g"]
        assert conv[f]["rel_change_corrected_pct"] == pytest.approx(100.0 * (c1 - c0) / c0, rel=1e-9, abs=1e-12)
        assert conv[f]["converged"] == (abs(100.0 * (c1 - c0) / c0) < FUEL_TOL_PCT)
    html = (d / "index.html").read_text()
    assert "Grid convergence" in html and "thermal_cabin: not checked with this run" in html


def test_rerun_reuses_cache_and_never_overwrites(first_run):
    cfg, out = first_run
    again = pipeline.run(cfg)
    assert again.report_dir != out.report_dir and out.report_dir.is_dir()
    assert again.wall_s < out.wall_s
    a = json.loads((out.report_dir / "report.json").read_text())["summary"]["strategies"]
    b = json.loads((again.report_dir / "report.json").read_text())["summary"]["strategies"]
    assert a == b


def test_bad_log_stops_before_heavy_work(small_logs, tmp_path, monkeypatch):
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 50)

    def boom(*a, **k):
        raise AssertionError("calibration must not start")

    monkeypatch.setattr("calib.fit.calibrate", boom)  # the pipeline calibrates through calib.fit
    cfg = pipeline.RunConfig(logs=[small_logs[0], bad, small_logs[1]], scenario=SCEN, grids=GRIDS,
                             reports_dir=tmp_path / "reports", cache_dir=None, progress=False)
    with pytest.raises(IptmError, match="broken.mcap"):
        pipeline.run(cfg)
    assert not (tmp_path / "reports").exists() or not any((tmp_path / "reports").iterdir())


def test_interrupted_run_leaves_no_report(first_run, monkeypatch):
    cfg, _ = first_run
    before = set(Path(cfg.reports_dir).iterdir())

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("iptm.report.render", interrupt)
    with pytest.raises(KeyboardInterrupt):
        pipeline.run(cfg)
    assert set(Path(cfg.reports_dir).iterdir()) == before


def test_scenario_file(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('[scenario]\ncycle = "nycc"\nT_amb = -5.0\n[grids]\nsoc = 0.02\n[run]\nstrategies = ["rule", "thermal"]\n')
    scen, grids, strategies, cyc_log = pipeline.load_scenario(f)
    assert scen.cycle == "nycc" and scen.T_amb == -5.0 and strategies == ("rule", "thermal")
    # the file's steps replace every formulation's own; the others stay each formulation's default
    assert [grids.of(fm).soc for fm in ("baseline", "thermal", "thermal_cabin")] == [0.02] * 3
    assert (grids.of("baseline").pbat, grids.of("thermal").pbat, grids.of("thermal_cabin").tcab) == (250.0, 500.0, 1.5)
    f.write_text('[scenario]\ncycle = "from log"\ncycle_log = "x.csv"\n')
    assert pipeline.load_scenario(f)[3] == "x.csv"
    for text, message in (('[grids]\nsoc = -0.01\n', "positive"), ('[grids]\nsco = 0.01\n', "known: soc"),
                          ('[scenario]\nambient = 3\n', "unknown scenario field"),
                          ('[scenario]\ncycle = "nycc"\n[run]\nstrategies =-7.0\n', "strategies must be a list of names")):
        f.write_text(text)
        with pytest.raises(IptmError, match=message):
            pipeline.load_scenario(f)


def test_source_edit_recomputes_what_depends_on_it(first_run, monkeypatch):
    """The cache keys carry the source digest: a different calib source recomputes calibration and DP."""
    cfg, out = first_run
    cache = Path(cfg.cache_dir)
    before = {p.name for p in (cache / "calib").iterdir()}
    import calib.store

    real = calib.store.code_version  # every key of the cache is made there (calib.store.result_key)
    monkeypatch.setattr(calib.store, "code_version", lambda *pk: real(*pk) + "-edited" if "calib" in pk else real(*pk))
    calls = []
    import calib.fit as fit  # the pipeline calibrates through this front door

    orig = fit.calibrate
    monkeypatch.setattr(fit, "calibrate", lambda *a, **k: calls.append(1) or orig(*a, **k))
    pipeline.run(cfg)
    assert calls, "calibration was served from the cache after a source change"
    assert {p.name for p in (cache / "calib").iterdir()} - before
