"""Real-browser test of the dashboard: ``streamlit run app.py`` in a subprocess, driven by Playwright with the
system's headless Chromium (``scripts/install_browser.sh`` installs both).

Uploads a corrupt log (message shown, and still shown after the next upload) and a 300-s log, runs a
calibration, an optimisation on 60 s with coarse grids and the report (the downloaded HTML, opened in the
browser, has a labelled row per strategy in its comparison table), and saves a screenshot of each page to
``reports/figures/page_{logs,calibrate,optimize,report}.png`` (shown in the README).

Run: ``make test-browser`` (``pytest -q -m browser``).
"""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

ROOT = Path(__file__).resolve().parent.parent
FIGS = ROOT / "reports" / "figures"
CHROMIUM = os.environ.get("IPTM_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]
# ms: one calibration / optimisation / report step (the first compiles the numba kernels; README mode: paper grids)
LONG = 900_000 if os.environ.get("IPTM_README_SHOTS") == "1" else 240_000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# `make test-browser` / `make screenshots` set IPTM_REQUIRE_BROWSER=1: a missing browser is then a failure,
# never a silent skip that would look like a pass.
REQUIRE = os.environ.get("IPTM_REQUIRE_BROWSER") == "1"


def _missing(msg):
    (pytest.fail if REQUIRE else pytest.skip)(msg)


@pytest.fixture(scope="module")
def sync_playwright():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _missing("playwright is not installed: run scripts/install_browser.sh (make browser)")
    if not Path(CHROMIUM).is_file():
        _missing(f"no Chromium at {CHROMIUM}: run scripts/install_browser.sh (make browser)")
    return sync_playwright


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("browser")
    port = _free_port()
    env = dict(os.environ, IPTM_CACHE_DIR=str(tmp / "cache"), IPTM_SESSION_ROOT=str(tmp / "sessions"),
               MPLBACKEND="Agg", PYTHONUNBUFFERED="1")
    log = open(tmp / "streamlit.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "streamlit", "run", str(ROOT / "app.py"), "--server.headless", "true",
         "--server.port", str(port), "--server.address", "127.0.0.1", "--browser.gatherUsageStats", "false",
         "--server.fileWatcherType", "none", "--client.toolbarMode", "viewer", "--global.developmentMode", "false"],
        cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.time() + 90
        while True:
            try:
                with urllib.request.urlopen(url + "/_stcore/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.time() > deadline:
                log.flush()
                pytest.fail("streamlit did not start:\n" + (tmp / "streamlit.log").read_text()[-3000:])
            time.sleep(0.5)
        yield url, tmp
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def _small_csv(path: Path, seconds: float = 300.0) -> Path:
    lines = (ROOT / "logs" / "winter_warm_restart.csv").read_text().splitlines()
    head = [ln for ln in lines[:10] if ln.startswith("#") or ln.startswith("time")]
    body = [ln for ln in lines if ln[:1].isdigit() and float(ln.split(",", 1)[0]) < seconds]
    path.write_text("\n".join(head + body) + "\n")
    return path


def _idle(page, timeout=LONG):
    """Wait until the script run finished (the 'Running...' status widget is gone)."""
    page.wait_for_timeout(400)
    page.wait_for_function(
        "() => { const w = document.querySelector('[data-testid=\"stStatusWidget\"]');"
        " return !w || !/Running|Stop/.test(w.innerText); }", timeout=timeout)
    page.wait_for_timeout(500)


def _goto(page, title):
    page.locator('[data-testid="stSidebarNav"]').get_by_text(title, exact=True).click()
    page.get_by_role("heading", name=title).first.wait_for(timeout=60_000)
    _idle(page)


# IPTM_README_SHOTS=1: the README's screenshots (bundled logs, whole cycle, paper grids) into
# reports/figures/; otherwise the quick CI flow (a 300-s upload, 60 s on coarse grids) into a temp folder.
README_MODE = os.environ.get("IPTM_README_SHOTS") == "1"
SHOTS = FIGS if README_MODE else Path(os.environ.get("IPTM_SHOT_DIR", "/tmp/iptm-browser-shots"))


def _shot(page, name):
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / name), full_page=True)


def test_dashboard_in_chromium(sync_playwright, server):
    url, tmp = server
    good = _small_csv(tmp / "winter_short.csv")
    bad = tmp / "corrupt.blf"
    bad.write_bytes(b"LOGG" + b"\xff" * 200)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            # README mode: tall enough that each page's charts are in the picture
            page = browser.new_page(viewport={"width": 1400, "height": 2700 if README_MODE else 1800})
            page.goto(url, wait_until="domcontentloaded")
            page.get_by_role("heading", name="Logs").first.wait_for(timeout=60_000)
            _idle(page)

            # a corrupt upload: a message in the page, the app keeps working
            page.locator('[data-testid="stFileUploader"] input[type="file"]').first.set_input_files(str(bad))
            page.get_by_text("Could not load corrupt.blf").wait_for(timeout=60_000)

            if README_MODE:
                page.get_by_role("button", name="Load the bundled sample logs (SYNTHETIC)").click()
                page.get_by_text("winter_warm_restart.blf [SYNTHETIC]").first.wait_for(timeout=120_000)
            else:  # a good upload
                page.locator('[data-testid="stFileUploader"] input[type="file"]').first.set_input_files(str(good))
                page.get_by_text("winter_short.csv [SYNTHETIC]: 299 s").wait_for(timeout=120_000)
            _idle(page)
            # the earlier upload's error is still shown after the next upload
            assert page.get_by_text("Could not load corrupt.blf").count() >= 1
            assert page.get_by_text("Could not load corrupt.blf").first.is_visible()
            page.locator('[data-testid="stSidebar"]').get_by_text("SYNTHETIC data").wait_for(timeout=30_000)
            page.get_by_role("tab", name="Plot").click()
            page.wait_for_timeout(1500)
            _shot(page, "page_logs.png")

            # calibration
            _goto(page, "Calibrate")
            page.get_by_role("button", name="Run calibration").click()
            page.get_by_role("heading", name="Calibrated parameters").wait_for(timeout=LONG)
            _idle(page)
            page.get_by_role("button", name="Download the calibration file (TOML)").wait_for()
            page.locator('[data-testid="stVegaLiteChart"]').first.wait_for(timeout=LONG)  # measured vs simulated
            _idle(page)
            assert page.locator('[data-testid="stException"]').count() == 0
            _shot(page, "page_calibrate.png")

            # optimisation on 60 s, coarse grids (the page's defaults)
            _goto(page, "Optimize")
            fields = {"Use the first ... s of the cycle (0 = whole)": "0" if README_MODE else "60"}
            if README_MODE:
                fields.update({"SOC [-]": "0.01", "coolant [degC]": "1", "cabin [degC]": "1", "battery [W]": "500",
                               "heater [W]": "50"})
            for label, value in fields.items():
                box = page.get_by_label(label, exact=True)
                box.fill(value)
                box.press("Enter")
                _idle(page)
            page.get_by_role("button", name="Run optimisation").click()
            page.get_by_role("heading", name="Figures").wait_for(timeout=LONG)
            _idle(page)
            page.locator('[data-testid="stImage"] img').first.wait_for(timeout=60_000)
            page.locator('[data-testid="stVegaLiteChart"]').first.wait_for(timeout=60_000)  # trajectories
            assert page.locator('[data-testid="stMetric"]').count() == 3
            assert page.locator('[data-testid="stException"]').count() == 0
            _shot(page, "page_optimize.png")

            # the report (whole chain through iptm.pipeline.run, same scenario)
            _goto(page, "Report")
            page.get_by_role("button", name="Build the report").click()
            page.get_by_role("button", name="Download the HTML report").wait_for(timeout=LONG)
            _idle(page)
            assert page.locator('[data-testid="stException"]').count() == 0
            _shot(page, "page_report.png")  # before the downloads, which re-run the page
            with page.expect_download() as dl:
                page.get_by_role("button", name="Download the JSON").click()
            saved = tmp / "report.json"
            dl.value.save_as(saved)
            assert saved.read_text().lstrip().startswith("{")
            with page.expect_download() as dl:
                page.get_by_role("button", name="Download the HTML report").click()
            html = tmp / "report.html"
            dl.value.save_as(html)
            # the downloaded report, rendered: the comparison table has a labelled row per strategy
            rp = browser.new_page(viewport={"width": 1200, "height": 1600})
            rp.goto(html.as_uri(), wait_until="load")
            table = rp.locator("p:has-text('one row per strategy') + div.tablewrap table")
            assert table.count() == 1
            first = [c.strip() for c in table.locator("tbody tr td:first-child").all_inner_texts()]
            assert first[:4] == ["Rule-based (tuned)", "Baseline-DP on thermal model", "Thermal-DP",
                                 "Thermal-Cabin-DP"], first
            assert table.locator("thead th").first.inner_text().strip() == "strategy"
            # the table fits the page or scrolls inside its own box; the page itself does not widen
            assert rp.evaluate("document.documentElement.scrollWidth <= window.innerWidth + 1")
            rp.close()
        finally:
            browser.close()
    for name in ("page_logs.png", "page_calibrate.png", "page_optimize.png", "page_report.png"):
        assert (SHOTS / name).stat().st_size > 10_000


def test_two_browser_sessions_calibrating_at_once_see_only_their_own(sync_playwright, server):
    """Two browser contexts (two users) upload different logs and start a calibration at the same time on
    one server: each page lists only its own log and shows a calibration of its own log only."""
    url, tmp = server
    files = {"a": _small_csv(tmp / "drive_user_a.csv", 300.0), "b": _small_csv(tmp / "drive_user_b.csv", 240.0)}
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            pages = {}
            for who in files:
                ctx = browser.new_context(viewport={"width": 1400, "height": 1800})
                page = ctx.new_page()
                page.goto(url, wait_until="domcontentloaded")
                page.get_by_role("heading", name="Logs").first.wait_for(timeout=60_000)
                _idle(page)
                pages[who] = page
            for who, page in pages.items():
                page.locator('[data-testid="stFileUploader"] input[type="file"]').first.set_input_files(str(files[who]))
            for who, page in pages.items():
                page.get_by_text(f"{files[who].name} [SYNTHETIC]").first.wait_for(timeout=120_000)
                _idle(page)
            for page in pages.values():
                _goto(page, "Calibrate")
            for page in pages.values():  # both runs start before either finishes
                page.get_by_role("button", name="Run calibration").click()
            for page in pages.values():
                page.get_by_role("heading", name="Calibrated parameters").wait_for(timeout=LONG)
                _idle(page)
            for who, page in pages.items():
                other = files["b" if who == "a" else "a"].name
                assert page.locator('[data-testid="stException"]').count() == 0
                assert page.get_by_role("tab", name=f"{files[who].name} [SYNTHETIC] (fitted)").count() == 1
                assert page.get_by_text(other).count() == 0, f"user {who} sees {other}"
                _goto(page, "Logs")
                assert page.get_by_text(files[who].name).count() >= 1
                assert page.get_by_text(other).count() == 0, f"user {who} sees {other} on the Logs page"
        finally:
            browser.close()
