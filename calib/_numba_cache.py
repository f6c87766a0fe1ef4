"""Where numba keeps the compiled kernels: a folder keyed by the source of every module that holds them.

numba's on-disk cache (``cache=True``) is invalidated only when the file of the cached function itself
changes. A kernel that inlines an equation from another file (every DP kernel inlines ``calib``'s battery,
fuel and coolant equations, and reads the parameter-vector layout of another module) would otherwise keep
running the old equation, or read the wrong slot, after that file changed: a silently wrong optimum. The
folder is therefore named by a hash of all ``calib`` and ``optimize`` sources, so any source change compiles
afresh. A ``NUMBA_CACHE_DIR`` set by the user is left alone.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path

#: Cache folders of other source versions unused for this long are removed (they are never read again).
STALE_DAYS = 30.0


def source_key(root: Path) -> str:
    """Hash of every ``.py`` file under ``root/calib`` and ``root/optimize`` (paths and contents)."""
    h = hashlib.sha256()
    for pkg in ("calib", "optimize"):
        for f in sorted((root / pkg).rglob("*.py")):
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "iptm" / "numba"


def configure() -> str | None:
    """Point numba's cache at this source version's folder (before any kernel is decorated); returns it, or
    None where the user set ``NUMBA_CACHE_DIR``."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    import numba

    root = cache_root()
    path = root / source_key(Path(__file__).resolve().parent.parent)
    numba.config.CACHE_DIR = str(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        os.utime(path)
        now = time.time()
        for old in root.iterdir():
            if old != path and old.is_dir() and now - old.stat().st_mtime > STALE_DAYS * 86400:
                shutil.rmtree(old, ignore_errors=True)
    except OSError:  # not writable: numba then falls back to its own locations
        pass
    return str(path)


#: This source version's folder (set on import of :mod:`calib`), or None where the user chose one.
CACHE_DIR = configure()
