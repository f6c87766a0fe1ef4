"""A content-keyed result store: results are filed under a hash of everything that determines them.

Used by the main pipeline's cache (ingested logs, calibrations, DP results) and by parameter sweeps
(a case already computed is never recomputed; an interrupted study resumes). Files are written atomically
and are JSON, TOML, Parquet or ``.npz`` (loaded with ``allow_pickle=False``): nothing a user hands us is
unpickled.
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

from calib.fileio import atomic_path, write_json


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


class Store:
    """Files under ``root/<kind>/<key>.<ext>``."""

    def __init__(self, root):
        self.root = Path(root)

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
            return json.loads(p.read_text())
        except (OSError, ValueError):
            return None  # a damaged entry is recomputed, never trusted

    def put_json(self, kind: str, key: str, obj) -> Path:
        """Store ``obj`` as JSON (atomically); returns its path."""
        p = self.path(kind, key, "json")
        write_json(p, obj)
        return p

    def get_npz(self, kind: str, key: str):
        """The stored arrays as a dict, or None when the entry is missing or damaged."""
        p = self.path(kind, key, "npz")
        if not p.is_file():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError):
            return None

    def put_npz(self, kind: str, key: str, arrays: dict) -> Path:
        """Store a dict of arrays as ``.npz`` (atomically); returns its path."""
        p = self.path(kind, key, "npz")
        with atomic_path(p) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        return p
