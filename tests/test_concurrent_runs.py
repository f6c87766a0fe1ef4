"""Two identical `iptm run` started together both succeed, each with its own report (distinct run ids), and
share the content-keyed cache without either stepping on the other's partial results."""
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCENARIO = """[scenario]
cycle = "udds"
duration_s = 60
[grids]
soc = 0.02
tcl = 2
tcab = 2
pbat = 1000
qheat = 100
[run]
strategies = ["rule", "baseline"]
"""


def test_two_identical_runs_at_once(tmp_path):
    shutil.copy(ROOT / "logs" / "winter_warm_restart.csv", tmp_path / "log.csv")
    (tmp_path / "sc.toml").write_text(SCENARIO)
    cmd = [sys.executable, "-m", "iptm.cli", "run", "log.csv", "--scenario", "sc.toml", "--reports", "rep",
           "--cache", "cache", "--no-convergence", "--quiet"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    reports = sorted((tmp_path / "rep").iterdir())
    assert len(reports) == 2 and all((r / "index.html").is_file() for r in reports)
    assert not [p for p in (tmp_path / "rep").iterdir() if p.name.startswith(".partial")]
    calib = list((tmp_path / "cache" / "calib").iterdir())
    assert [c.name for c in calib if ".partial" in c.name] == []
    assert len(calib) == 1 and (calib[0] / "done").is_file()
