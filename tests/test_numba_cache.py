"""numba's kernel cache is keyed by the source version: an edited equation in one file must not leave a
kernel in another file running its old compiled copy."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from calib import _numba_cache

ROOT = Path(__file__).resolve().parent.parent


def _tree(tmp_path, body):
    for pkg in ("calib", "optimize"):
        (tmp_path / pkg).mkdir(exist_ok=True)
    (tmp_path / "calib" / "equations.py").write_text(body)
    (tmp_path / "optimize" / "kernel.py").write_text("from calib.equations import f\n")
    return _numba_cache.source_key(tmp_path)


def test_key_changes_with_any_source_file_and_only_then(tmp_path):
    k1 = _tree(tmp_path, "def f(x):\n    return x\n")
    assert _tree(tmp_path, "def f(x):\n    return x\n") == k1
    assert _tree(tmp_path, "def f(x):\n    return x + 1\n") != k1  # the kernel's own file did not change
    (tmp_path / "calib" / "equations.py").write_text("def f(x):\n    return x\n")
    (tmp_path / "optimize" / "sub").mkdir()
    (tmp_path / "optimize" / "sub" / "new.py").write_text("")
    assert _numba_cache.source_key(tmp_path) != k1  # a new file counts too


@pytest.mark.skipif(bool(os.environ.get("NUMBA_CACHE_DIR")), reason="the user chose the cache folder")
def test_importing_calib_points_numba_at_this_versions_folder(tmp_path):
    import numba

    want = _numba_cache.cache_root() / _numba_cache.source_key(ROOT)
    assert _numba_cache.CACHE_DIR == str(want) and numba.config.CACHE_DIR == str(want)


def test_a_cache_folder_the_user_chose_is_kept(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "mine")}
    out = subprocess.run([sys.executable, "-c", "import calib, numba; print(calib._numba_cache.CACHE_DIR, "
                          "numba.config.CACHE_DIR)"], env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["None", str(tmp_path / "mine")]
