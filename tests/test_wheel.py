"""The wheel a user installs: built from the sources (``pip wheel --no-build-isolation``, offline), installed in a
fresh virtual environment that cannot see this checkout, and run from a folder outside it.

The fresh environment gets the dependencies through a ``.pth`` line naming this interpreter's site-packages:
a plain path line, so the ``.pth`` files there (among them the editable install's finder of this checkout)
are not run. Each command runs with ``PYTHONPATH`` unset and an empty numba cache of its own, so nothing
compiled from the checkout is reused.

The fast checks (the wheel's file list, one ECMS simulation) run in the normal suite; every subcommand's
smoke case is ``slow`` (it compiles every kernel afresh).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calib", "optimize", "iptm", "testcars")


def _package_dirs() -> list[str]:
    """Every folder of the sources with an ``__init__.py``, as a path in the wheel."""
    return sorted(p.parent.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("__init__.py")
                  if "__pycache__" not in p.parts)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """(the wheel, pip's output): built from a copy of the sources, so the build leaves nothing in the checkout."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    skip = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in PACKAGES + ("logs",):
        shutil.copytree(ROOT / name, src / name, symlinks=True, ignore=skip)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    out = tmp / "dist"
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-w", str(out), str(src)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (whl,) = out.glob("iptm-*.whl")
    return whl, proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory):
    """(python, iptm, environment, work folder) of a fresh virtual environment holding only the wheel."""
    tmp = tmp_path_factory.mktemp("venv")
    env_dir = tmp / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True, timeout=120)
    py = env_dir / "bin" / "python"
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                           str(wheel[0])], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    Path(site, "iptm_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(NUMBA_CACHE_DIR=str(tmp / "numba"), MPLBACKEND="Agg", PYTHONNOUSERSITE="1")
    work = tmp / "work"
    work.mkdir()
    assert ROOT not in work.parents
    return py, env_dir / "bin" / "iptm", env, work


def _run(venv, *args, timeout=900) -> str:
    """Run a command of the fresh environment in its work folder; return its output (it must succeed)."""
    py, iptm, env, work = venv
    exe = [str(py)] if args[0] == "python" else [str(iptm)]
    proc = subprocess.run(exe + [str(a) for a in args[1:]], cwd=work, env=env, capture_output=True, text=True,
                          timeout=timeout)
    out = proc.stdout + proc.stderr
    assert "ModuleNotFoundError" not in out and "Traceback" not in out, out[-4000:]
    assert proc.returncode == 0, f"{' '.join(map(str, args))}: exit {proc.returncode}\n{out[-4000:]}"
    return out


def test_the_wheel_ships_every_package_and_the_data(wheel):
    whl, log = wheel
    assert "warn" not in log.lower(), log  # setuptools says nothing about the package layout
    names = set(zipfile.ZipFile(whl).namelist())
    missing = [d for d in _package_dirs() if f"{d}/__init__.py" not in names]
    assert not missing, f"packages missing from the wheel: {missing}"
    for f in ("iptm/samples/winter_cold_start.blf", "iptm/samples/winter_warm_restart.csv",
              "calib/data/cycles/udds.csv", "calib/data/can/prius_iptm.dbc"):
        assert f in names, f
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]


def test_the_installed_package_is_the_wheel_not_the_checkout(venv):
    out = _run(venv, "python", "-c", "import calib, optimize, iptm, testcars, iptm.bundled as b; "
                                     "print(calib.__file__, optimize.__file__, iptm.__file__, testcars.__file__, "
                                     "b.bundled_logs_dir())")
    env_dir = venv[0].parent.parent
    paths = out.split()
    assert len(paths) == 5 and all(Path(p).is_relative_to(env_dir) for p in paths), out


def test_simulate_with_ecms_from_outside_the_checkout(venv):
    out = _run(venv, "iptm", "simulate", "--cycle", "udds", "--ambient", "-7", "--controller", "ecms")
    assert "fuel" in out


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_every_subcommand_from_the_wheel(venv):
    py, iptm, env, work = venv
    samples = Path(_run(venv, "python", "-c", "import iptm.bundled as b; print(b.bundled_logs_dir())").strip())
    assert "usage: iptm" in _run(venv, "iptm", "--help")
    _run(venv, "iptm", "params", "--out", "params.toml")
    _run(venv, "iptm", "synth", "--out", "synth", "--scenario", "winter_cold_start", "--formats", "csv")
    _run(venv, "iptm", "ingest", samples / "winter_warm_restart.csv", "--out", "warm.parquet")
    _run(venv, "iptm", "calibrate", samples / "winter_warm_restart.csv", "--out", "cal.toml", "--quiet")
    for controller in ("ecms", "sdp"):
        _run(venv, "iptm", "simulate", "--params", "cal.toml", "--cycle", "udds", "--ambient", "-7",
             "--controller", controller)
    grid = "soc=0.04,tcl=4,tcab=3,pbat=2000,qheat=250"
    _run(venv, "iptm", "optimize", "--duration", "60", "--grid", grid, "--cache", "cache")
    (work / "scenario.toml").write_text(f'[scenario]\nduration_s = 60\n[grids]\n{chr(10).join(grid.split(","))}\n')
    out = _run(venv, "iptm", "run", samples / "winter_warm_restart.csv", "--scenario", "scenario.toml",
               "--no-convergence", "--quiet", "--reports", "reports", "--cache", "cache")
    assert list((work / "reports").glob("*/index.html")), out
    (work / "study.toml").write_text('[study]\nname = "smoke"\nstrategies = ["rule"]\n[scenario]\nduration_s = 30\n'
                                     '[vary]\nT_amb = [-10, 0]\n')
    _run(venv, "iptm", "sweep", "study.toml", "--workers", "1", "--out", "study", "--store", "store", "--quiet")
    _run(venv, "iptm", "bench", "sim", "--quick")
