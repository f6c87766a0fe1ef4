"""The one content-keyed cache: results are filed under a hash of everything that determines them.

Used by the main pipeline (ingested logs, calibrations, DP outcomes), the dashboard (the same entries: a
result computed by ``iptm run`` is served to the dashboard and back) and parameter sweeps (a case already
computed is never recomputed; an interrupted study resumes). :func:`result_key` is the one recipe for a
result's key: the parameter values, the scenario, the grids, what is computed and the code version.

The folder is ``--cache`` on the command line, else ``IPTM_CACHE_DIR``, else ``.iptm-cache`` in the working
folder; its size is capped (``IPTM_CACHE_MAX_MB``, default :data:`DEFAULT_MAX_MB`): past the cap the least
recently used entries are removed. Entries are written atomically (a temporary name, then a rename) and are
JSON, TOML, Parquet, ``.npz`` (loaded with ``allow_pickle=False``) or result folders (docs/results.md):
nothing a user hands us is unpickled.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import secrets
import shutil
import time
import zipfile
from pathlib import Path

import numpy as np

from calib.errors import IptmError
from calib.fileio import atomic_path, write_json

#: The cache folder when neither ``--cache`` nor ``IPTM_CACHE_DIR`` names one.
DEFAULT_ROOT = ".iptm-cache"
#: The size cap (MB) when ``IPTM_CACHE_MAX_MB`` sets none.
DEFAULT_MAX_MB = 4096.0


def default_root() -> Path:
    """The cache folder: ``IPTM_CACHE_DIR``, else ``.iptm-cache`` in the working folder."""
    return Path(os.environ.get("IPTM_CACHE_DIR") or DEFAULT_ROOT)


def default_max_mb() -> float:
    """The size cap: ``IPTM_CACHE_MAX_MB`` (a positive number of MB), else :data:`DEFAULT_MAX_MB`."""
    raw = os.environ.get("IPTM_CACHE_MAX_MB", "").strip()
    if not raw:
        return DEFAULT_MAX_MB
    try:
        mb = float(raw)
    except ValueError:
        mb = float("nan")
    if not (math.isfinite(mb) and mb > 0):
        raise IptmError(f"IPTM_CACHE_MAX_MB={raw!r}: give the cache's size cap as a positive number of MB")
    return mb


def _canon(o):
    if isinstance(o, dict):
        return {str(k): _canon(v) for k, v in sorted(o.items(), key=lambda kv: str(kv[0]))}
    if isinstance(o, (list, tuple)):
        return [_canon(v) for v in o]
    if isinstance(o, np.ndarray):
        return [_canon(v) for v in o.tolist()]
    if isinstance(o, (np.floating, float)):
        f = float(o)
        return repr(f) if math.isfinite(f) else str(f)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "_asdict"):
        return _canon(o._asdict())
    return o


_DIGESTS: dict = {}


def code_version(*packages: str) -> str:
    """The installed version plus a digest of the sources of ``packages`` (default: ``calib``).

    Every ``.py`` file under each package, recursively, enters the digest with its path, so an edit of
    any model, fitting or optimisation file changes the keys of the results that depend on it and a
    store never serves a result computed by other code.
    """
    import importlib

    from calib._version import __version__

    packages = packages or ("calib",)
    key = tuple(sorted(packages))
    if key not in _DIGESTS:
        h = hashlib.sha256()
        for name in key:
            root = Path(importlib.import_module(name).__file__).parent
            for f in sorted(root.rglob("*.py")):
                h.update(f.relative_to(root.parent).as_posix().encode())
                h.update(f.read_bytes())
        _DIGESTS[key] = f"{__version__}+{h.hexdigest()[:12]}"
    return _DIGESTS[key]


def content_key(*parts, length: int = 20) -> str:
    """A stable hash of JSON-like parts (dicts, lists, numbers, strings, numpy arrays, namedtuples)."""
    blob = json.dumps(_canon(list(parts)), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:length]


def result_key(what, *, params=None, scenario=None, grids=None, inputs=None, options=None,
               code=("calib", "optimize")) -> str:
    """The key of a result: a hash of what is computed (``what``: a strategy, ``"calibration"``...), the
    parameter values (a ParameterSet or a dict of values), the scenario, the grids, other inputs (e.g. the
    logs' digests), solver options and :func:`code_version` of ``code``. Any change of any of them misses."""
    if params is not None and hasattr(params, "to_dict"):
        params = {n: ([p.value, p.x] if p.is_table else p.value) for n, p in ((n, params.param(n)) for n in params)}
    parts = {"what": what, "params": params, "scenario": scenario, "grids": grids, "code": code_version(*code)}
    if inputs is not None:
        parts["inputs"] = inputs
    if options:
        parts["options"] = options
    return content_key(parts)


class Store:
    """The cache: entries under ``root/<kind>/<key>.<ext>`` (files) or ``root/<kind>/<key>/`` (folders).

    ``root`` None: :func:`default_root`; ``max_mb`` None: :func:`default_max_mb`. A read that finds an entry
    marks it used (its modification time), so the size cap removes what has not been used longest."""

    def __init__(self, root=None, max_mb: float | None = None):
        self.root = Path(root) if root is not None else default_root()
        self.max_bytes = int((max_mb if max_mb is not None else default_max_mb()) * 1024 * 1024)
        self._size = None  # the folder's size as last measured plus what this process wrote since

    def path(self, kind: str, key: str, ext: str) -> Path:
        """Where the entry ``kind``/``key`` with extension ``ext`` is (or would be) stored."""
        return self.root / kind / f"{key}.{ext}"

    def has(self, kind: str, key: str, ext: str = "json") -> bool:
        """Whether the entry is stored."""
        return self.path(kind, key, ext).is_file()

    def get_json(self, kind: str, key: str):
        """The stored JSON entry, or None when it is missing or damaged."""
        p = self.path(kind, key, "json")
        if not p.is_file():
            return None
        try:
            out = json.loads(p.read_text())
        except (OSError, ValueError):
            return None  # a damaged entry is recomputed, never trusted
        self.touch(p)
        return out

    def put_json(self, kind: str, key: str, obj) -> Path:
        """Store ``obj`` as JSON (atomically); returns its path."""
        p = self.path(kind, key, "json")
        write_json(p, obj)
        self.written(p)
        return p

    def get_npz(self, kind: str, key: str):
        """The stored arrays as a dict, or None when the entry is missing or damaged."""
        p = self.path(kind, key, "npz")
        if not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                out = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            return None  # a damaged entry is recomputed, never trusted
        self.touch(p)
        return out

    def put_npz(self, kind: str, key: str, arrays: dict) -> Path:
        """Store a dict of arrays as ``.npz`` (atomically); returns its path."""
        p = self.path(kind, key, "npz")
        with atomic_path(p) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        self.written(p)
        return p

    # --- folder entries (result folders, a calibration with its figures) -------------------------
    def folder(self, kind: str, key: str) -> Path:
        """Where the entry ``key`` of ``kind`` lives (whether or not it exists)."""
        return self.root / kind / key

    def get_dir(self, kind: str, key: str) -> Path | None:
        """The entry's folder, when complete (written by :meth:`put_dir`), else None."""
        d = self.folder(kind, key)
        if not (d / "done").is_file():
            return None
        self.touch(d)
        return d

    def put_dir(self, kind: str, key: str, fill) -> Path:
        """Write a folder entry: ``fill(folder)`` fills a temporary folder, which is then renamed onto the
        entry (an entry another process filed first is kept: the key is the content, so it is the same)."""
        d = self.folder(kind, key)
        d.parent.mkdir(parents=True, exist_ok=True)
        tmp = d.parent / f".{key}.partial-{os.getpid()}-{secrets.token_hex(3)}"
        tmp.mkdir()
        try:
            fill(tmp)
            (tmp / "done").write_text("")
            try:
                tmp.rename(d)
            except OSError:
                if (d / "done").is_file():
                    shutil.rmtree(tmp, ignore_errors=True)
                else:  # a damaged entry left by an interrupted run
                    shutil.rmtree(d, ignore_errors=True)
                    tmp.rename(d)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self.written(d)
        return d

    # --- the size cap ----------------------------------------------------------------------------
    @staticmethod
    def touch(p: Path) -> None:
        try:
            os.utime(p)
        except OSError:
            pass  # a read-only cache is still read

    def written(self, p: Path) -> None:
        """Count a new entry against the cap and remove the least recently used entries past it."""
        if self._size is not None:
            self._size += _size_of(p)
        if self._size is None or self._size > self.max_bytes:
            self.prune()

    def entries(self) -> list[tuple[float, int, Path]]:
        """``(last used, bytes, path)`` of every entry (files and folders under each kind)."""
        out = []
        if not self.root.is_dir():
            return out
        for kind in self.root.iterdir():
            if not kind.is_dir():
                continue
            for e in kind.iterdir():
                if e.name.startswith("."):
                    continue  # a temporary of a write in progress
                try:
                    out.append((e.stat().st_mtime, _size_of(e), e))
                except OSError:
                    continue
        return out

    def prune(self) -> int:
        """Remove the least recently used entries until the cache is within its cap; returns how many."""
        _remove_stale_partials(self.root)
        ents = sorted(self.entries(), key=lambda t: t[0])
        total = sum(b for _, b, _ in ents)
        removed = 0
        for _, b, e in ents:
            if total <= self.max_bytes:
                break
            if e.is_dir():
                shutil.rmtree(e, ignore_errors=True)
            else:
                e.unlink(missing_ok=True)
            total -= b
            removed += 1
        self._size = total
        return removed


def _size_of(p: Path) -> int:
    if p.is_dir():
        return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
    return p.stat().st_size if p.exists() else 0


def _remove_stale_partials(root: Path, older_s: float = 86400.0) -> None:
    """Remove the temporaries of writes killed mid-way (older than ``older_s``: a write in progress is younger)."""
    now = time.time()
    for kind in (root.iterdir() if root.is_dir() else ()):
        for e in (kind.glob(".*.partial-*") if kind.is_dir() else ()):
            try:
                if now - e.stat().st_mtime > older_s:
                    shutil.rmtree(e, ignore_errors=True)
            except OSError:
                continue
