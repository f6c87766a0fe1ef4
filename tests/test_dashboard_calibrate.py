"""The Calibrate page on a log without fuel rate: the fuel and engine-thermal subsystems are named as left
at their priors (with why), the fuel-rate channel reads "not scored" (never RMSE 0), and the count of
estimated parameters is the report's (iptm.present.parameter_counts)."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("streamlit")
from streamlit.testing.v1 import AppTest  # noqa: E402

from iptm import dashboard as dash  # noqa: E402
from iptm import present  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _env(tmp_path_factory, monkeypatch):
    base = tmp_path_factory.getbasetemp()
    monkeypatch.setenv("IPTM_CACHE_DIR", str(base / "iptm-cache"))
    monkeypatch.setenv("IPTM_SESSION_ROOT", str(base / "sessions"))


def _no_fuel_csv() -> bytes:
    """The first 300 s of the bundled (SYNTHETIC) warm-restart CSV without its fuel-rate column."""
    lines = (ROOT / "logs" / "winter_warm_restart.csv").read_text().splitlines()
    head = [ln for ln in lines[:10] if ln.startswith("#")]
    cols = next(ln for ln in lines if ln.startswith("time")).split(",")
    j = cols.index("fuel_rate [g/s]")
    body = [ln for ln in lines if ln[:1].isdigit() and float(ln.split(",", 1)[0]) < 300.0]
    keep = [",".join(c for i, c in enumerate(ln.split(",")) if i != j) for ln in [",".join(cols)] + body]
    return ("\n".join(head + keep) + "\n").encode()


def test_calibrate_page_names_what_was_not_fitted_and_not_scored():
    at = AppTest.from_file(str(ROOT / "app.py"), default_timeout=300)
    at.run()
    at.file_uploader(key="log_upload").upload("nofuel.csv", _no_fuel_csv(), "text/csv")
    at.run()
    at.switch_page("pages/calibrate.py").run()
    at.button(key="cal_run").click()
    at.run()
    assert not at.exception, [e.value for e in at.exception]
    res = at.session_state[dash.CALIB]["result"]
    warnings = [w.value.replace("\\", "") for w in at.warning]
    for line in present.prior_banner(res):
        assert any(line in w for w in warnings), (line, warnings)
    assert any(w.startswith("Not fitted: fuel parameters") for w in warnings)
    counts = present.parameter_counts(res.params)
    assert next(m for m in at.metric if m.label == "parameters estimated").value == str(counts["estimated"])
    caps = [c.value.replace("\\", "") for c in at.caption]
    assert any("fuel_rate not scored (the log has no fuel_rate_g_per_s)" in c for c in caps), caps
    assert not any("fuel_rate RMSE" in c for c in caps)
