"""Real-browser test of the dashboard: ``streamlit run app.py`` in a subprocess, driven by Playwright with the
system's headless Chromium (``scripts/install_browser.sh`` installs both).

Uploads a corrupt log (message shown, and still shown after the next upload) and a 300-s log, runs a
calibration, an optimisation on 60 s on the default grids and the report (the downloaded HTML, opened in the
browser, has a labelled row per strategy in its comparison table), and saves a screenshot of each page to
``reports/figures/page_{logs,calibrate,optimize,report}.png`` (shown in the README). Two users calibrate at
once, each seeing only their own logs. One user uploads a unit bomb, a decompression bomb and a log whose header
note is Markdown while another calibrates: the other's answer comes in its usual time, the server's health
check answers throughout, and the note is shown as text.

Run: ``make test-browser`` (``pytest -q -m browser``).
"""
from __future__ import annotations

import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import threading
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


SESSION_TTL_S = 5  # how long Streamlit keeps a closed tab's session for a reconnect


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
         "--server.fileWatcherType", "none", "--client.toolbarMode", "viewer", "--global.developmentMode", "false",
         "--server.disconnectedSessionTTL", str(SESSION_TTL_S)],
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
        yield url, tmp, proc.pid
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def _small_csv(path: Path, seconds: float = 300.0, notes: tuple[str, ...] = ()) -> Path:
    """The first ``seconds`` of the bundled warm-restart CSV, with ``# note: ...`` header lines added."""
    lines = (ROOT / "logs" / "winter_warm_restart.csv").read_text().splitlines()
    comments = [ln for ln in lines[:10] if ln.startswith("#")] + [f"# note: {n}" for n in notes]
    header = [ln for ln in lines[:10] if ln.startswith("time")]
    body = [ln for ln in lines if ln[:1].isdigit() and float(ln.split(",", 1)[0]) < seconds]
    path.write_text("\n".join(comments + header + body) + "\n")
    return path


def _idle(page, timeout=LONG):
    """Wait until the script run finished (the 'Running...' status widget is gone, and with it the elements of
    the previous run that this one has not drawn again)."""
    page.wait_for_timeout(400)
    page.wait_for_function(
        "() => { const w = document.querySelector('[data-testid=\"stStatusWidget\"]');"
        " return (!w || !/Running|Stop/.test(w.innerText)) && !document.querySelector('[data-stale=\"true\"]'); }",
        timeout=timeout)
    page.wait_for_timeout(500)


def _goto(page, title):
    page.locator('[data-testid="stSidebarNav"]').get_by_text(title, exact=True).click()
    page.get_by_role("heading", name=title).first.wait_for(timeout=60_000)
    _idle(page)


# IPTM_README_SHOTS=1: the README's screenshots (bundled logs, whole cycle, paper grids) into
# reports/figures/; otherwise the quick CI flow (a 300-s upload, 60 s on the default grids) into a temp folder.
README_MODE = os.environ.get("IPTM_README_SHOTS") == "1"
SHOTS = FIGS if README_MODE else Path(os.environ.get("IPTM_SHOT_DIR", "/tmp/iptm-browser-shots"))


def _shot(page, name):
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / name), full_page=True)


def test_dashboard_in_chromium(sync_playwright, server):
    url, tmp, _ = server
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

            # optimisation on 60 s on the page's default grids (each formulation's converged grid); README mode:
            # the paper's grids, set as custom steps
            _goto(page, "Optimize")
            fields = {"Use the first ... s of the cycle (0 = whole)": "0" if README_MODE else "60"}
            if README_MODE:
                page.get_by_text("custom steps, the same for every formulation").click()
                _idle(page)
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
    url, tmp, _ = server
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


def _mcap_bomb(path: Path) -> tuple[Path, Path, int]:
    """A known 300-s drive as MCAP (written with the mcap package) with one more zstd chunk after its header
    record: 33 kB that inflate to 1 GiB of zeros while the chunk declares 4096 bytes. Returns the bomb, the
    intact drive and the byte where the bomb chunk starts."""
    from testcars.fabricate import fabricate_streams
    from calib.ingest.writers import write_streams
    from test_ingest_bombs import chunk_record, zstd_rle_frame

    streams, meta = fabricate_streams(300, seed=7)
    intact = write_streams(streams, meta, path.with_name(path.stem + "_intact.mcap"), "mcap")
    data = intact.read_bytes()
    assert data[8] == 1  # the header record follows the magic
    at = 8 + 9 + struct.unpack_from("<Q", data, 9)[0]
    bomb = chunk_record(zstd_rle_frame(1 << 30), declared=4096, t_ns=(10**9, 2 * 10**9))
    assert len(bomb) < 40_000
    path.write_bytes(data[:at] + bomb + data[at:])
    return path, intact, at


# Times one script run of the page, in the page itself (so that the test can drive another page meanwhile):
# from now until the status widget, once it showed the run, is gone again. Epoch milliseconds.
_RUN_TIMER = """() => {
  const r = window.__iptmRun = {start: Date.now(), busy: null, end: null};
  const busy = () => { const w = document.querySelector('[data-testid="stStatusWidget"]');
                       return !!w && /Running|Stop/.test(w.innerText); };
  const tick = () => {
    if (busy()) { if (r.busy === null) r.busy = Date.now(); }
    else if (r.busy !== null) { r.end = Date.now(); return; }
    setTimeout(tick, 20);
  };
  tick();
}"""


def _start_calibration(page, truncate_s: float) -> None:
    box = page.get_by_label("Use only the first ... seconds of each log (0 = whole log)", exact=True)
    box.fill(f"{truncate_s:g}")
    box.press("Enter")
    _idle(page)
    page.evaluate(_RUN_TIMER)
    page.get_by_role("button", name="Run calibration").click()


def _calibration_seconds(page) -> tuple[float, float]:
    """(seconds from the click to the end of the run, epoch seconds of that end) of the run timed by
    :data:`_RUN_TIMER`, once it has ended."""
    page.wait_for_function("() => window.__iptmRun.end !== null", timeout=LONG)
    r = page.evaluate("window.__iptmRun")
    page.get_by_role("heading", name="Calibrated parameters").wait_for(timeout=60_000)
    return (r["end"] - r["start"]) / 1000, r["end"] / 1000


def _rss_kib(pid: int, field: str) -> int:
    line = next(ln for ln in Path(f"/proc/{pid}/status").read_text().splitlines() if ln.startswith(field + ":"))
    return int(line.split()[1])


def _reset_peak_rss(pid: int) -> int:
    """Resets the process's peak resident memory (VmHWM) to its current one, returned in KiB."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    return _rss_kib(pid, "VmRSS")


class _HealthProbe(threading.Thread):
    """Asks the server's health endpoint every 0.1 s until stopped: (seconds to answer, HTTP status or error)."""

    def __init__(self, url: str):
        super().__init__(daemon=True)
        self.url, self.answers, self.halt = url + "/_stcore/health", [], threading.Event()

    def run(self):
        while not self.halt.is_set():
            t = time.perf_counter()
            try:
                with urllib.request.urlopen(self.url, timeout=5) as r:
                    got = r.status
            except OSError as exc:
                got = f"{type(exc).__name__}: {exc}"
            self.answers.append((time.perf_counter() - t, got))
            self.halt.wait(0.1)


NOTE_MD = "![pixel](http://127.0.0.1:9/p.png) **bold**"  # a remote image and bold text, if rendered
WARN_MD = "![pixel](http://127.0.0.1:9/w.png) **bold**"  # the same, in a note the page shows as a warning


def test_hostile_uploads_in_one_session_leave_another_sessions_calibration_on_time(sync_playwright, server):
    """Session A uploads a unit bomb, an MCAP decompression bomb and a log with a Markdown header note while
    session B calibrates the bundled logs: B's answer comes within about twice its time alone, B sees no
    error, the health check answers throughout, the server's memory does not jump, A gets a clear message
    for each bomb and its note as text (no image fetched, nothing rendered)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    url, tmp, pid = server
    unit_bomb = tmp / "unit_bomb.csv"
    unit_bomb.write_text("time [s],speed [km/h**9**9**9]\n0,1\n1,2\n")
    zip_bomb, intact, at = _mcap_bomb(tmp / "zip_bomb.mcap")
    from calib.ingest import read_log

    kept = read_log(intact)  # what the bomb's file still holds
    md = _small_csv(tmp / "markdown_note.csv", 120.0, notes=(NOTE_MD, "warning: " + WARN_MD))
    md_s = read_log(md).duration_s
    requests: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            a_ctx, b_ctx = (browser.new_context(viewport={"width": 1400, "height": 1800}) for _ in "ab")
            a_ctx.on("request", lambda r: requests.append(r.url))
            a, b = a_ctx.new_page(), b_ctx.new_page()
            for page in (a, b):
                page.goto(url, wait_until="domcontentloaded")
                page.get_by_role("heading", name="Logs").first.wait_for(timeout=60_000)
                _idle(page)
            b.get_by_role("button", name="Load the bundled sample logs (SYNTHETIC)").click()
            b.get_by_text("winter_warm_restart.blf [SYNTHETIC]").first.wait_for(timeout=120_000)
            _idle(b)
            _goto(b, "Calibrate")
            # the server's first calibration also compiles the numba kernels: not part of B's usual time
            b.get_by_role("button", name="Run calibration").click()
            b.get_by_role("heading", name="Calibrated parameters").wait_for(timeout=LONG)
            _idle(b)
            # Each timed run fits the whole of every log (none is longer than 2600 s); its own truncation
            # gives it its own key in the page's calibration cache, so each is computed.
            base_alone = _reset_peak_rss(pid)
            _start_calibration(b, 3000)
            alone, _ = _calibration_seconds(b)
            _idle(b)
            peak_alone = _rss_kib(pid, "VmHWM") - base_alone

            health = _HealthProbe(url)
            base_loaded = _reset_peak_rss(pid)
            _start_calibration(b, 4000)
            health.start()
            try:
                a_began = time.time()
                uploader = a.locator('[data-testid="stFileUploader"] input[type="file"]').first
                said = {}  # what the page says about each upload when it has read it
                for f in (unit_bomb, zip_bomb, md):
                    uploader.set_input_files(str(f))  # each outcome is awaited before the next file is added
                    outcome = a.locator('[data-testid^="stAlertContent"]').filter(
                        has_text=re.compile(rf"^(Could not load )?{re.escape(f.name)}"))
                    try:
                        outcome.first.wait_for(timeout=60_000)
                    except PlaywrightTimeout:
                        pytest.fail(f"{f.name}: no outcome in the page within 60 s of its upload")
                    _idle(a)
                    said[f.name] = {k: a.locator(f'[data-testid="stAlertContent{k}"]').filter(has_text=f.name)
                                    .all_inner_texts() for k in ("Error", "Warning", "Success")}
            finally:
                health.halt.set()
                health.join(timeout=10)
            loaded, b_ended = _calibration_seconds(b)
            _idle(b)
            peak_loaded = _rss_kib(pid, "VmHWM") - base_loaded
            print(f"\nB's calibration alone: {alone:.1f} s; with A's uploads: {loaded:.1f} s; health check: "
                  f"{len(health.answers)} answers, slowest {max(s for s, _ in health.answers):.2f} s; server peak "
                  f"memory above its start: {peak_alone / 1024:.0f} MiB alone, {peak_loaded / 1024:.0f} MiB with A")

            # B: its answer in its usual time, while A's uploads went on, and no error
            assert b_ended > a_began, "B's calibration ended before A's uploads began: nothing was measured"
            assert loaded <= 2 * alone + 5, f"B took {loaded:.1f} s with A's uploads, {alone:.1f} s alone"
            for tid in ("stException", "stAlertContentError"):
                assert b.locator(f'[data-testid="{tid}"]').count() == 0, b.locator(f'[data-testid="{tid}"]').all_inner_texts()
            assert b.get_by_text("unit_bomb.csv").count() == b.get_by_text("zip_bomb.mcap").count() == 0
            # the server answered its health check all the while, and no bomb cost it memory
            assert len(health.answers) >= 5, health.answers
            assert all(got == 200 for _, got in health.answers), [g for _, g in health.answers if g != 200]
            assert peak_loaded < peak_alone + 500 * 1024, (peak_alone, peak_loaded)

            # A: the unit bomb is refused with one message naming the column
            assert said["unit_bomb.csv"]["Success"] == said["unit_bomb.csv"]["Warning"] == []
            err = [m for m in said["unit_bomb.csv"]["Error"] if m.startswith("Could not load unit_bomb.csv: ")]
            assert len(err) == 1 and "speed [km/h**9**9**9]" in err[0], said["unit_bomb.csv"]
            # the decompression bomb: its chunk refused by name, the rest of the drive read, never in green
            bomb = said["zip_bomb.mcap"]
            assert bomb["Success"] == [] and not [m for m in bomb["Error"] if "Could not load" in m], bomb
            warn = [m for m in bomb["Warning"] if m.startswith("zip_bomb.mcap [SYNTHETIC] [RECOVERED]: ")]
            assert len(warn) == 1, bomb
            assert warn[0].startswith(f"zip_bomb.mcap [SYNTHETIC] [RECOVERED]: {kept.duration_s:.0f} s, "
                                      f"{len(kept.channels())} channels: "), warn
            assert f"chunk at byte {at}" in warn[0] and "4096 bytes" in warn[0], warn
            # and it stays in red while that log is selected
            assert a.locator('[data-testid="stAlertContentError"]').filter(has_text=f"chunk at byte {at}").count() == 1
            assert said["markdown_note.csv"]["Error"] == []
            assert [m for m in said["markdown_note.csv"]["Success"]
                    if m.startswith(f"markdown_note.csv [SYNTHETIC]: {md_s:.0f} s, ")], said["markdown_note.csv"]
            assert a.locator('[data-testid="stException"]').count() == 0

            # the Markdown note: nothing of it rendered or fetched, and it is shown as written, as a warning
            # and in the provenance
            a.locator('[data-testid="stSelectbox"]').filter(has=a.get_by_text("Log", exact=True)).click()
            a.get_by_role("option", name="markdown_note.csv [SYNTHETIC]").click()
            a.get_by_text("markdown_note.csv is SYNTHETIC").wait_for(timeout=30_000)  # the run for it has begun
            _idle(a)
            a.get_by_role("tab", name="Channel report").click()
            rendered = a.evaluate("""() => ({
                img: [...document.images].map(i => i.src).filter(s => s.includes('127.0.0.1:9')),
                bold: [...document.querySelectorAll('strong, b, em')].filter(e => e.innerText === 'bold').length})""")
            assert rendered == {"img": [], "bold": 0}, rendered
            assert not [u for u in requests if "127.0.0.1:9/" in u], "the browser fetched the note's image"
            # as written, but for the invisible word joiner that keeps the address from becoming a link
            warnings = [w.strip().replace("\u2060", "")
                        for w in a.locator('[data-testid="stAlertContentWarning"]').all_inner_texts()]
            assert WARN_MD in warnings, warnings
            assert a.locator('a[href*="127.0.0.1:9"]').count() == 0
            a.get_by_role("tab", name="Provenance").click()
            prov = a.locator('[data-testid="stJson"]')
            prov.locator(".node-ellipsis").first.click()  # the whole record, then its notes
            prov.locator(".object-key-val").filter(has_text='"notes"').last.locator(".node-ellipsis").first.click()
            assert prov.get_by_text(f'"{NOTE_MD}"').count() == 1
            assert prov.get_by_text(f'"warning: {WARN_MD}"').count() == 1
        finally:
            browser.close()


def test_closing_the_tab_removes_the_sessions_folder(sync_playwright, server):
    url, tmp, _ = server
    sessions = tmp / "sessions"
    before = set(sessions.glob("iptm-session-*"))
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1800})
            page.goto(url, wait_until="domcontentloaded")
            page.get_by_role("heading", name="Logs").first.wait_for(timeout=60_000)
            _idle(page)
            page.locator('[data-testid="stFileUploader"] input[type="file"]').first.set_input_files(
                str(_small_csv(tmp / "to_forget.csv", seconds=60.0)))
            _idle(page)
            mine = set(sessions.glob("iptm-session-*")) - before
            assert len(mine) == 1 and any(mine.pop().rglob("*.csv"))
        finally:
            browser.close()
    deadline = time.time() + SESSION_TTL_S + 60
    while time.time() < deadline and set(sessions.glob("iptm-session-*")) - before:
        time.sleep(1)
    assert not set(sessions.glob("iptm-session-*")) - before, "the closed session's folder is still there"
