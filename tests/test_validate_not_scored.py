"""A channel the log does not carry is not scored: a log without fuel rate has no fuel_rate metric (never an
RMSE of 0 from zeros put where the engine was stopped)."""
from pathlib import Path

import calib
from calib.fit.validate import replay
from calib.model.params import default_parameters

ROOT = Path(__file__).resolve().parent.parent


def test_log_without_fuel_rate_is_not_scored_on_fuel(tmp_path):
    lines = (ROOT / "logs" / "winter_warm_restart.csv").read_text().splitlines()
    cols = next(ln for ln in lines if ln.startswith("time")).split(",")
    j = cols.index("fuel_rate [g/s]")
    keep = [ln for ln in lines if ln.startswith("#")]
    keep += [",".join(c for i, c in enumerate(ln.split(",")) if i != j)
             for ln in lines if ln.startswith("time") or (ln[:1].isdigit() and float(ln.split(",", 1)[0]) < 300)]
    path = tmp_path / "nofuel.csv"
    path.write_text("\n".join(keep) + "\n")
    rep = replay(calib.read_log(path), default_parameters())
    assert "fuel_rate" not in rep.measured
    with_fuel = replay(calib.read_log(ROOT / "logs" / "winter_warm_restart.csv"), default_parameters())
    assert "fuel_rate" in with_fuel.measured
