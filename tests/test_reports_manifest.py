"""reports/ keeps only the files reports/MANIFEST.toml lists (each with the command that regenerates it and
what reads it); everything else there is output of runs and studies, git-ignored so that a rerun is not
committed by accident."""
from __future__ import annotations

import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "reports" / "MANIFEST.toml"
ENTRIES = tomllib.loads(MANIFEST.read_text())["file"]
PATHS = [e["path"] for e in ENTRIES]


def _git(*args: str) -> subprocess.CompletedProcess:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)


def test_every_entry_exists_once_and_says_how_it_is_made_and_who_reads_it():
    assert len(PATHS) == len(set(PATHS)), "a file is listed twice"
    for e in ENTRIES:
        p = e["path"]
        assert p.startswith("reports/") and (ROOT / p).is_file(), f"{p}: listed but missing"
        assert e.get("command", "").strip(), f"{p}: no command"
        assert e.get("read_by"), f"{p}: nothing reads it, so it need not be kept"
        missing = [r for r in e["read_by"] if not (ROOT / r).is_file()]
        assert not missing, f"{p}: read_by names files that do not exist: {missing}"


def test_every_committed_file_under_reports_is_in_the_manifest():
    out = _git("ls-files", "reports")
    assert out.returncode == 0, out.stderr
    committed = set(out.stdout.split()) - {"reports/MANIFEST.toml"}
    assert committed, "git lists nothing under reports/"
    extra = sorted(committed - set(PATHS))
    assert not extra, f"committed under reports/ but not in reports/MANIFEST.toml: {extra}"


def test_gitignore_keeps_exactly_the_manifest():
    """The listed files are not ignored; any other file a rerun writes under reports/ is."""
    probes = ["reports/causal-select.json", "reports/bench-dp.json", "reports/mutation-seed99-first-pass.json",
              "reports/causal-cmap-trip9-corrected.json", "reports/figures/new.png", "reports/run-1/index.html"]
    listed = _git("check-ignore", "--no-index", *PATHS, "reports/MANIFEST.toml")
    assert listed.returncode == 1 and not listed.stdout.strip(), f"ignored but listed:\n{listed.stdout}"
    ignored = _git("check-ignore", "--no-index", *probes)
    assert ignored.stdout.split() == probes, f"not ignored: {sorted(set(probes) - set(ignored.stdout.split()))}"
