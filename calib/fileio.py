"""Atomic file output: write to a temporary file in the same folder, then rename.

An interrupted run therefore never leaves a half-written output behind.
"""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def _read_umask() -> int:
    # os.umask can only be read by setting it; do that once, at import, before any threads exist
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


#: A temporary file of an atomic write older than this was left by a process that was killed mid-write.
STALE_TMP_S = 3600.0


def _remove_stale_tmp(path: Path) -> None:
    import time

    now = time.time()
    for f in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            if now - f.stat().st_mtime > STALE_TMP_S:
                f.unlink()
        except OSError:
            pass


@contextmanager
def atomic_path(path):
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    Temporary files of earlier writes of the same path that were killed mid-write (older than
    :data:`STALE_TMP_S`) are removed first."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_tmp(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp makes the file private (0600); the output gets the mode any new file would (umask)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _default(o):
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_text(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a reader never sees a half-written file)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path, obj) -> None:
    """Write ``obj`` as indented JSON, atomically (numpy scalars and arrays allowed)."""
    write_text(path, json.dumps(obj, indent=2, default=_default, allow_nan=True) + "\n")


def save_figure(fig, path, dpi: int = 110) -> None:
    """Save a matplotlib figure atomically (format from the suffix) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)


#: Largest configuration file (parameters, scenario, study, map) read, in bytes: such files are a few kB; a
#: larger one (or a device such as /dev/zero) is refused before it is read.
MAX_CONFIG_BYTES = 16 * 2**20


def read_config(path, error, what: str = "file") -> dict:
    """A TOML (or, by its suffix, JSON) configuration file as a dict, read within limits.

    Refuses, with one ``error(message)`` naming the file: a path that is not a regular file, a file over
    :data:`MAX_CONFIG_BYTES`, bytes that are not UTF-8, a syntax error, an integer of more digits than Python
    converts (``ValueError``), nesting deeper than the parser's recursion allows, and a top level that is not
    a table.
    """
    import tomllib

    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror})") from None
    import stat as _stat

    if not _stat.S_ISREG(st.st_mode):
        raise error(f"{p}: not a regular file: give a {what} (TOML or JSON)")
    if st.st_size > MAX_CONFIG_BYTES:
        raise error(f"{p}: {st.st_size / 2**20:.1f} MiB is too large for a {what} (at most "
                    f"{MAX_CONFIG_BYTES / 2**20:.0f} MiB)")
    try:
        text = p.read_bytes().decode("utf-8")
        d = json.loads(text) if p.suffix.lower() == ".json" else tomllib.loads(text)
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror})") from None
    except RecursionError:
        raise error(f"{p}: not a valid {what}: nested too deeply") from None
    except (ValueError, UnicodeDecodeError) as exc:  # syntax, non-UTF-8, over-long integers
        kind = "JSON" if p.suffix.lower() == ".json" else "TOML"
        raise error(f"{p}: not a valid {kind} {what}: {str(exc).splitlines()[0][:200]}") from None
    if not isinstance(d, dict):
        raise error(f"{p}: a {what} must be a table of fields, not {type(d).__name__}")
    return d
