"""The Streamlit dashboard (app.py, pages/*.py, iptm/dashboard.py) driven by ``streamlit.testing.v1.AppTest``.

Small data: the first 300 s of the bundled (SYNTHETIC) warm-restart CSV as the upload, calibration on it,
optimisation on 60 s of a cycle with coarse grids. The real-browser test is tests/test_browser.py.
"""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("streamlit")
from streamlit.testing.v1 import AppTest  # noqa: E402

from iptm import dashboard as dash  # noqa: E402


def _txt(element) -> str:
    """An alert's text as the user reads it (user-supplied text is Markdown-escaped on the page)."""
    return element.value.replace("\\", "")

ROOT = Path(__file__).resolve().parent.parent
APP = str(ROOT / "app.py")
TIMEOUT = 240


@pytest.fixture(autouse=True)
def _env(tmp_path_factory, monkeypatch):
    base = tmp_path_factory.getbasetemp()
    monkeypatch.setenv("IPTM_CACHE_DIR", str(base / "iptm-cache"))  # shared by the tests: content-keyed
    monkeypatch.setenv("IPTM_SESSION_ROOT", str(base / "sessions"))
    monkeypatch.delenv("IPTM_MAX_UPLOAD_MB", raising=False)


@pytest.fixture(scope="session")
def small_csv() -> bytes:
    """The first 300 s of logs/winter_warm_restart.csv (SYNTHETIC; header comments kept)."""
    lines = (ROOT / "logs" / "winter_warm_restart.csv").read_text().splitlines()
    head = [ln for ln in lines[:10] if ln.startswith("#") or ln.startswith("time")]
    body = [ln for ln in lines if ln[:1].isdigit() and float(ln.split(",", 1)[0]) < 300.0]
    return ("\n".join(head + body) + "\n").encode()


def new_app() -> AppTest:
    at = AppTest.from_file(APP, default_timeout=TIMEOUT)
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    return at


def errors(at):
    return [_txt(e) for e in at.error]


def ok(at):
    assert not at.exception, [e.value for e in at.exception]
    return at


def upload(at, name, data, mime="application/octet-stream"):
    at.file_uploader(key="log_upload").upload(name, data, mime)
    return ok(at.run())


# ------------------------------------------------------------------------------------------------
# iptm.dashboard: pure helpers
# ------------------------------------------------------------------------------------------------
def test_safe_name_and_limits(monkeypatch):
    assert dash.safe_name("../../etc/passwd") == "passwd"
    assert dash.safe_name(r"C:\logs\drive 1.blf") == "drive_1.blf"
    assert dash.safe_name("...") == "upload"
    monkeypatch.setenv("IPTM_MAX_UPLOAD_MB", "1")
    assert dash.max_upload_bytes() == 2**20
    from calib.errors import IptmError

    with pytest.raises(IptmError, match="too large"):
        dash.check_size("big.blf", 2**20 + 1)
    with pytest.raises(dash.IptmError, match="empty"):
        dash.check_size("e.csv", 0)
    with pytest.raises(dash.IptmError, match="unsupported file type '.exe'"):
        dash.check_log_extension("tool.exe")
    monkeypatch.setenv("IPTM_MAX_UPLOAD_MB", "nonsense")
    assert dash.max_upload_bytes() == int(dash.DEFAULT_MAX_UPLOAD_MB * 2**20)


def test_error_messages_never_quote_raw_bytes():
    exc = dash.IptmError("x.mcap: not a valid MCAP file, invalid magic: (104, 101, 108, 108, 111, 32, 116, 104)")
    msg = dash.error_message(exc)
    assert "104, 101" not in msg and "x.mcap: not a valid MCAP file" in msg and "header" in msg
    assert "b'" not in dash.error_message(ValueError("bad start b'\\x89MCAP0\\r\\n'"))
    st = {}
    dash.record_upload(st, "a.csv", True, "ok")
    dash.record_upload(st, "b.mcap", False, "broken")
    assert dash.upload_history(st).to_dict("records") == [
        {"file": "b.mcap", "status": "FAILED", "message": "broken"}, {"file": "a.csv", "status": "loaded", "message": "ok"}]


def test_session_state_helpers(small_csv):
    a, b = {}, {}
    entry = dash.add_upload(a, "short.csv", small_csv)
    assert dash.session_dir(a) != dash.session_dir(b)
    assert entry.path.parent.parent == dash.session_dir(a) and entry.path.name == "short.csv"
    assert list(dash.logs(a)) == ["short.csv"] and dash.logs(b) == {}
    assert entry.synthetic and dash.any_synthetic(a) and not dash.any_synthetic(b)
    assert 295 <= entry.log.duration_s <= 300
    assert dash.truncate(entry.log, 60).duration_s <= 60
    cyc = dash.cycle_csv_from_log(a, entry)
    assert cyc.read_text().startswith("time_s,speed_kph")
    from calib.model.params import default_parameters

    tbl = dash.parameter_table(default_parameters())
    assert list(tbl["parameter"]) == dash.calibratable_parameters()
    assert set(tbl["identifiable"]) == {"-"}
    dash.remove_log(a, "short.csv")
    assert dash.logs(a) == {} and not entry.path.exists()
    with pytest.raises(dash.IptmError) as ei:
        dash.add_upload(a, "broken.mcap", b"\x89MCAP0\r\n" + b"\x00" * 50)
    assert str(dash.session_dir(a)) not in str(ei.value)  # named as uploaded, not by the temporary path


# ------------------------------------------------------------------------------------------------
# pages
# ------------------------------------------------------------------------------------------------
def test_every_page_renders_without_logs():
    at = new_app()
    assert at.title[0].value == "Logs"
    assert any("No logs yet" in _txt(i) for i in at.info)
    assert not at.sidebar.warning
    for page, title in (("pages/calibrate.py", "Calibrate"), ("pages/optimize.py", "Optimize"),
                        ("pages/report.py", "Report")):
        ok(at.switch_page(page).run())
        assert at.title[0].value == title
        if title == "Optimize":
            assert at.button(key="opt_run").disabled is False  # works without logs (library cycle)


def test_upload_channel_report_and_plot(small_csv):
    at = new_app()
    upload(at, "short.csv", small_csv, "text/csv")
    assert not errors(at)
    assert any("short.csv [SYNTHETIC]" in _txt(s) for s in at.success)
    assert any("SYNTHETIC" in w.value for w in at.sidebar.warning)
    frames = [d.value for d in at.dataframe]
    rep = next(f for f in frames if "channel" in f.columns).set_index("channel")  # the channel report
    assert rep.loc["speed_mps", "unit"] == "m/s (km/h)" and rep.loc["soc", "unit"] == "%"
    hist = next(f for f in frames if "status" in f.columns and "file" in f.columns)
    assert hist.to_dict("records")[0]["file"] == "short.csv" and hist["status"].tolist() == ["loaded"]
    at.multiselect(key="chans_short.csv").set_value(["speed_mps", "soc", "coolant_temp_degC"])
    ok(at.run())
    assert list(at.session_state[dash.LOGS]) == ["short.csv"]


def test_bad_uploads_show_messages_and_app_keeps_working(small_csv, monkeypatch):
    at = new_app()
    msgs = []
    for name, data in (("corrupt.blf", b"LOGG" + b"\xff" * 200), ("notes.docx", b"PK\x03\x04 not a log"),
                       ("empty.csv", b""), ("text.csv", b"this is not,a drive log\n1,2\n")):
        upload(at, name, data)
        got = errors(at)
        # each bad file: one message, newest first; earlier failures stay visible
        assert name in got[0] and len(got) == len(msgs) + 1, got
        assert all(m in got for m in msgs)
        msgs = got
        assert at.title[0].value == "Logs"
    assert any("corrupt.blf" in m for m in msgs)
    assert any("unsupported file type '.docx'" in m for m in msgs)
    assert any("empty" in m for m in msgs)
    assert any("text.csv" in m for m in msgs)
    assert all("iptm-session-" not in m for m in msgs)
    # oversized: the limit is configurable
    monkeypatch.setenv("IPTM_MAX_UPLOAD_MB", "0.05")
    upload(at, "big.csv", small_csv, "text/csv")
    assert any("too large" in m and "big.csv" in m for m in errors(at))
    hist = dash.upload_history(at.session_state)
    assert hist["status"].tolist() == ["FAILED"] * 5 and hist["file"].iloc[0] == "big.csv"
    monkeypatch.delenv("IPTM_MAX_UPLOAD_MB")
    # a bad DBC is refused too
    at.file_uploader(key="dbc_upload").upload("bad.dbc", b"\x00\x01 garbage", "application/octet-stream")
    ok(at.run())
    assert any("bad.dbc" in m for m in errors(at))
    # ... and the app still works: a good upload, other pages render
    upload(at, "short.csv", small_csv, "text/csv")
    assert any("short.csv" in _txt(s) for s in at.success)
    assert list(at.session_state[dash.LOGS]) == ["short.csv"]
    for page in ("pages/calibrate.py", "pages/optimize.py", "pages/report.py"):
        ok(at.switch_page(page).run())


def test_sessions_do_not_share_uploads(small_csv):
    a, b = new_app(), new_app()
    upload(a, "short.csv", small_csv, "text/csv")
    ok(b.run())
    assert any("No logs yet" in i.value for i in b.info)
    assert b.session_state[dash.LOGS] == {}
    assert dash.TMP not in b.session_state  # b never made a folder; a's is its own
    upload(b, "other.csv", small_csv, "text/csv")
    assert a.session_state[dash.TMP] != b.session_state[dash.TMP]
    assert list(a.session_state[dash.LOGS]) == ["short.csv"] and list(b.session_state[dash.LOGS]) == ["other.csv"]


def _csv_slice(t_end: float) -> bytes:
    """The bundled (SYNTHETIC) warm-restart CSV up to ``t_end`` s (header comments kept)."""
    lines = (ROOT / "logs" / "winter_warm_restart.csv").read_text().splitlines()
    head = [ln for ln in lines[:10] if ln.startswith("#") or ln.startswith("time")]
    body = [ln for ln in lines if ln[:1].isdigit() and float(ln.split(",", 1)[0]) < t_end]
    return ("\n".join(head + body) + "\n").encode()


def _files_under(folder) -> set[str]:
    return {p.name for p in Path(folder).rglob("*") if p.is_file()}


@pytest.mark.timeout(900)
def test_two_sessions_interleaved_keep_their_own_logs_and_calibrations():
    """Two sessions upload a different log each and calibrate on it, their steps interleaved (A uploads, B
    uploads, A calibrates, B calibrates). Streamlit's AppTest is not thread-safe (two instances run in
    threads fail inside its widget registry), so truly simultaneous sessions are tested in a real browser
    (``tests/test_browser.py::test_two_browser_sessions_calibrating_at_once_see_only_their_own``)."""
    drives = {"drive_a.csv": _csv_slice(300.0), "drive_b.csv": _csv_slice(240.0)}
    out = {name: {"at": new_app()} for name in drives}
    for name, data in drives.items():
        upload(out[name]["at"], name, data, "text/csv")
    for name in drives:
        at = out[name]["at"]
        ok(at.switch_page("pages/calibrate.py").run())
        at.multiselect(key="cal_fix_params").set_value(["kappa"])
    for name in drives:
        at = out[name]["at"]
        at.button(key="cal_run").click()
        ok(at.run())
        assert not errors(at), errors(at)
    a, b = (out[n]["at"].session_state for n in drives)
    assert a[dash.TMP] != b[dash.TMP]
    for name, state in zip(drives, (a, b)):
        other = next(n for n in drives if n != name)
        assert list(state[dash.LOGS]) == [name]
        assert state[dash.LOGS][name].path.read_bytes() == drives[name]
        files = _files_under(state[dash.TMP])
        assert name in files and other not in files, files
        cal = state[dash.CALIB]
        assert cal["fit"] == [name] and cal["val"] == []
        assert (Path(state[dash.TMP]) / "calibration" / "calibration.toml").read_bytes() == cal["artifact"]
    assert a[dash.CALIB]["key"] != b[dash.CALIB]["key"]
    assert a[dash.CALIB]["artifact"] != b[dash.CALIB]["artifact"]
    assert a[dash.CALIB]["result"] is not b[dash.CALIB]["result"]


def test_oversized_upload_is_refused_before_it_is_written(small_csv, monkeypatch):
    monkeypatch.setenv("IPTM_MAX_UPLOAD_MB", "0.05")
    assert len(small_csv) > 0.05 * 2**20
    at = new_app()
    upload(at, "big.csv", small_csv, "text/csv")
    assert any("too large" in m and "big.csv" in m for m in errors(at))
    folder = at.session_state[dash.TMP] if dash.TMP in at.session_state else None
    assert folder is None or "big.csv" not in _files_under(folder)
    # the helper that writes uploads refuses before creating anything
    state = {}
    from calib.errors import IptmError

    with pytest.raises(IptmError, match="too large"):
        dash.save_upload(state, "big.csv", small_csv)
    assert "big.csv" not in _files_under(dash.session_dir(state))


def test_bundled_sample_logs_button():
    at = new_app()
    at.button(key="load_bundled").click()
    ok(at.run())
    assert not errors(at)
    names = list(at.session_state[dash.LOGS])
    assert names == [p.name for p in dash.bundled_logs()] and len(names) == 3
    assert any("SYNTHETIC" in w.value for w in at.sidebar.warning)


def test_calibrate_optimize_report_flow(small_csv):
    at = new_app()
    upload(at, "short.csv", small_csv, "text/csv")

    # --- calibration on the 300-s log
    ok(at.switch_page("pages/calibrate.py").run())
    assert at.multiselect(key="cal_fit_logs").value == ["short.csv"]
    at.multiselect(key="cal_fix_params").set_value(["kappa"])
    at.button(key="cal_run").click()
    ok(at.run())
    assert not errors(at), errors(at)
    tbl = at.dataframe[0].value
    assert {"parameter", "value", "stderr", "status", "identifiable"} <= set(tbl.columns)
    # measured vs simulated: interactive, on the fitted log too
    charts = at.get("vega_lite_chart")
    assert len(charts) == 1 and '"vconcat"' in charts[0].proto.spec and "simulated" in charts[0].proto.spec
    assert tbl.set_index("parameter").loc["kappa", "status"] == "fixed"
    assert (tbl["identifiable"] == "yes").any()
    assert at.get("download_button"), "calibration download missing"
    art = at.session_state[dash.CALIB]["artifact"]
    assert b"[parameters." in art

    # --- optimisation: 60 s of the library cycle, coarse grids, calibrated parameters
    ok(at.switch_page("pages/optimize.py").run())
    assert at.radio(key="opt_params_src").value == "calibrated in this session"
    at.number_input(key="opt_duration").set_value(60.0)
    at.button(key="opt_run").click()
    ok(at.run())
    assert not errors(at), errors(at)
    cs = at.session_state[dash.OPT]["cs"]
    assert {"rule", "baseline", "thermal", "thermal_cabin"} <= set(cs.sims)
    assert len(at.session_state[dash.OPT]["figures"]) >= 9
    assert len(at.metric) == 3
    # the paper's savings are a reference caption, not a delta arrow that reads as an improvement
    assert all(m.proto.delta == "" for m in at.metric)
    assert sum("paper (Gong et al.)" in c.value for c in at.caption) == 3
    comp = at.dataframe[0].value
    assert comp["strategy"].tolist()[:4] == ["Rule-based (tuned)", "Baseline-DP on thermal model", "Thermal-DP",
                                            "Thermal-Cabin-DP"]
    assert {"corrected fuel [g]", "corrected L/100 km", "corrected mpg", "raw fuel [g]", "raw L/100 km", "raw mpg"} <= set(comp.columns)
    assert list(comp.columns).index("corrected fuel [g]") < list(comp.columns).index("raw fuel [g]")
    # interactive trajectories (one Vega-Lite chart, panels with a shared time axis)
    charts = at.get("vega_lite_chart")
    assert len(charts) == 1 and '"vconcat"' in charts[0].proto.spec

    # --- cycle from the uploaded log, one strategy
    at.radio(key="opt_cycle_src").set_value("from a loaded log")
    ok(at.run())
    at.multiselect(key="opt_strategies").set_value(["thermal"])
    at.button(key="opt_run").click()
    ok(at.run())
    assert not errors(at), errors(at)
    assert "from log" in at.session_state[dash.OPT]["cycle"]["name"] or \
        "short_cycle" in at.session_state[dash.OPT]["cycle"]["name"]
    assert list(at.session_state[dash.OPT]["cs"].sims) == ["thermal"]

    # --- an invalid scenario (initial coolant below the coolant grid's 0 degC) is a message, not a crash
    tcl0 = at.number_input(key="opt_Tcl0").value
    at.number_input(key="opt_Tcl0").set_value(-20.0)
    ok(at.run())
    # refused before the button, which is then disabled
    assert any("outside the coolant grid" in m for m in errors(at)), errors(at)
    assert at.button(key="opt_run").disabled
    at.number_input(key="opt_Tcl0").set_value(tcl0)

    # --- report: the whole chain through iptm.pipeline.run on the session's log and scenario
    at.number_input(key="opt_duration").set_value(60.0)
    at.multiselect(key="opt_strategies").set_value(["rule", "thermal"])
    at.radio(key="opt_cycle_src").set_value("from the library")
    ok(at.run())
    ok(at.switch_page("pages/report.py").run())
    at.button(key="rep_run").click()
    ok(at.run())
    assert not errors(at), errors(at)
    rep = at.session_state["iptm_report"]
    assert rep["html"].lstrip().lower().startswith(b"<!doctype html") or b"<html" in rep["html"][:500].lower()
    assert rep["json"].lstrip().startswith(b"{")
    assert len(at.get("download_button")) == 2
    assert Path(rep["dir"]).is_relative_to(Path(at.session_state[dash.TMP]))
    # a formatted summary (a row per strategy, economy units) and a preview of the HTML report, not raw JSON
    summ = at.dataframe[0].value
    assert summ["strategy"].tolist() == ["Rule-based (tuned)", "Thermal-DP"]
    assert {"corrected fuel [g]", "corrected L/100 km", "corrected mpg", "raw fuel [g]", "raw L/100 km", "raw mpg"} <= set(summ.columns)
    assert all(len(v.split(".")[1]) <= 2 for v in summ["corrected fuel [g]"])  # no 16-digit numbers
    assert at.get("iframe") and "<table" in at.get("iframe")[0].proto.srcdoc


def test_optimize_sweep_over_ambient():
    pytest.importorskip("optimize.sweep")
    at = new_app()
    ok(at.switch_page("pages/optimize.py").run())
    at.radio(key="opt_params_src").set_value("default 2017 Prius")
    at.number_input(key="opt_duration").set_value(60.0)
    at.multiselect(key="opt_strategies").set_value(["rule", "thermal"])
    ok(at.run())
    at.text_input(key="sweep_Tamb").set_value("-10, 0")
    at.button(key="sweep_run").click()
    ok(at.run())
    assert not errors(at), errors(at)
    df = at.session_state["iptm_sweep"]["df"]
    assert sorted(set(df["T_amb"])) == [-10.0, 0.0] and set(df["strategy"]) == {"rule", "thermal"}
    # a bad list of temperatures is a message
    at.text_input(key="sweep_Tamb").set_value("cold")
    at.button(key="sweep_run").click()
    ok(at.run())
    assert any("Sweep failed" in m for m in errors(at))


def test_copies_of_a_drive_are_not_validated_on():
    """The bundled set offers the warm restart also as CSV, MCAP and candump: one drive, four files."""
    at = new_app()
    at.checkbox(key="bundled_other_formats").check()
    at.button(key="load_bundled").click()
    ok(at.run())
    assert any("Same drive in several files" in _txt(i) for i in at.info)
    ok(at.switch_page("pages/calibrate.py").run())
    fit = at.multiselect(key="cal_fit_logs").value
    val = at.multiselect(key="cal_val_logs")
    # defaults: one file per drive; the held-out drive is not one that was fitted
    assert fit == ["winter_cold_start.blf", "winter_long_mixed.blf"]
    assert val.value == ["winter_warm_restart.blf"]
    at.multiselect(key="cal_fit_logs").set_value(fit + ["winter_warm_restart.csv"])
    ok(at.run())
    opts = at.multiselect(key="cal_val_logs").options
    assert not any("winter_warm_restart" in o for o in opts), opts  # no copy of a fitted drive is offered
    at.multiselect(key="cal_fit_logs").set_value(["winter_warm_restart.csv", "winter_warm_restart.mcap"])
    ok(at.run())
    assert any("same drive" in _txt(w) for w in at.warning)


def test_uploads_with_one_cleaned_name_are_kept_apart(tmp_path, monkeypatch):
    from iptm import dashboard as dash

    monkeypatch.setenv("IPTM_SESSION_ROOT", str(tmp_path / "sessions"))
    state = {}
    data = (Path(__file__).resolve().parents[1] / "logs" / "winter_warm_restart.csv").read_bytes()
    names = [dash.add_upload(state, n, data, store_root=tmp_path / "cache").name
             for n in ("log.csv", "log.csv", "../../x.csv", "x.csv")]
    assert names == ["log.csv", "log-2.csv", "x.csv", "x-2.csv"]
    assert set(dash.logs(state)) == set(names)
    dash.end_session(state)
    assert not list((tmp_path / "sessions").glob("iptm-session-*"))


def test_long_names_and_errors_never_show_server_paths(tmp_path, monkeypatch):
    from calib.errors import IptmError
    from iptm import dashboard as dash

    monkeypatch.setenv("IPTM_SESSION_ROOT", str(tmp_path / "sessions"))
    state = {}
    long = "a" * 300 + ".csv"
    with pytest.raises(IptmError) as err:
        dash.add_upload(state, long, b"time [s],speed [km/h]\n0,x\n", store_root=tmp_path / "cache")
    msg = dash.error_message(err.value)
    assert str(tmp_path) not in msg and "iptm-session" not in msg
    assert len(dash.safe_name(long)) <= dash.MAX_NAME_CHARS


def test_user_text_is_shown_as_text():
    from iptm.dashboard import plain

    out = plain("![pixel](http://203.0.113.9/p.png) [link](http://x) <img src=x> **bold**")
    for raw in ("![", "**"):
        assert raw not in out
    assert out.count("[") == out.count("\\[") == 2 and out.count("]") == out.count("\\]") == 2
    assert out.count("<") == out.count("\\<") == 1


def test_stale_session_folders_are_removed(tmp_path):
    import os
    import time

    from iptm.dashboard import remove_stale_sessions

    old, new = tmp_path / "iptm-session-old", tmp_path / "iptm-session-new"
    for d in (old, new):
        (d / "uploads").mkdir(parents=True)
        (d / "uploads" / "a.csv").write_text("x")
    t = time.time() - 7 * 3600
    for f in (old, old / "uploads", old / "uploads" / "a.csv"):
        os.utime(f, (t, t))
    assert remove_stale_sessions(root=tmp_path) == 1
    assert not old.exists() and new.exists()


def test_session_folder_removed_when_the_session_state_is_dropped(tmp_path, monkeypatch):
    """Streamlit frees an ended session's state; the folder goes with it, without waiting for staleness."""
    import gc

    from iptm import dashboard as dash

    monkeypatch.setenv("IPTM_SESSION_ROOT", str(tmp_path / "sessions"))
    state = {}
    d = dash.session_dir(state)
    (d / "upload.csv").write_text("time [s],speed [km/h]\n0,1\n")
    assert d.is_dir()
    del state
    gc.collect()
    assert not d.exists()


def test_folders_of_closed_sessions_removed_by_the_janitors_sweep(tmp_path):
    from iptm import dashboard as dash

    open_id, closed_id = "0f8fad5b-d9cb-469f-a165-70867728950e", "7c9e6679-7425-40de-944b-e07fc1f90ae7"
    kept = [tmp_path / f"iptm-session-{open_id}-abc", tmp_path / "iptm-session-nosession"]
    gone = tmp_path / f"iptm-session-{closed_id}-def"
    for d in [*kept, gone]:
        (d / "uploads").mkdir(parents=True)
    assert dash.remove_closed_sessions(tmp_path, lambda sid: sid == open_id) == 1
    assert not gone.exists() and all(d.exists() for d in kept)
