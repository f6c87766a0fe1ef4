"""The file format of saved results (simulations, calibrations, DP outcomes): one folder per result.

::

    RESULT/
        result.json    {"format": "iptm-result", "version": 1, "kind": ..., every number and text}
        arrays.npz     the arrays, by name (numpy's .npz, read with allow_pickle=False)
        *.toml, ...    other text files of the kind (a calibration's parameter set)
        SUB/           a result held by this one, in the same format (a DP outcome's re-simulated drive)

Text where it can be (a saved result diffs like source), binary only for the time series; nothing is
unpickled. A folder is written under a temporary name beside ``RESULT`` and renamed onto it when complete,
so a reader never sees a half-written result. docs/results.md describes the format and each kind.
"""
from __future__ import annotations

import json
import os
import secrets
import shutil
import zipfile
from pathlib import Path

import numpy as np

from calib.errors import ResultFileError

FORMAT = "iptm-result"
#: Bumped when a kind's contents change so that an older reader cannot read them right.
VERSION = 1
META = "result.json"
ARRAYS = "arrays.npz"


def save_result(path, fill) -> Path:
    """Write a result folder at ``path``: ``fill(folder)`` writes the contents (with :func:`write_parts`) into
    a temporary folder, which then replaces ``path``. An existing ``path`` that is not a saved result is
    refused, never overwritten."""
    path = Path(path)
    if path.exists() and not (path.is_dir() and (path / META).is_file()):
        raise ResultFileError(f"{path}: exists and is not a saved result; choose a new path")
    path.parent.mkdir(parents=True, exist_ok=True)
    tag = f"{os.getpid()}-{secrets.token_hex(3)}"
    tmp = path.parent / f".{path.name}.partial-{tag}"
    tmp.mkdir()
    try:
        fill(tmp)
        if path.exists():
            old = path.parent / f".{path.name}.old-{tag}"
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def write_parts(folder: Path, kind: str, meta: dict, arrays: dict | None = None, texts: dict | None = None) -> None:
    """Fill ``folder`` (inside :func:`save_result`'s ``fill``): ``result.json``, ``arrays.npz``, text files."""
    from calib.fileio import write_json

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    clash = {"format", "version", "kind"} & set(meta)
    if clash:
        raise ValueError(f"write_parts: {sorted(clash)} name the file format itself; call them otherwise")
    doc = {"format": FORMAT, "version": VERSION, "kind": kind, **meta}
    write_json(folder / META, doc)
    if arrays:
        with open(folder / ARRAYS, "wb") as fh:
            np.savez_compressed(fh, **{k: np.asarray(v) for k, v in arrays.items()})
    for name, text in (texts or {}).items():
        (folder / name).write_text(text)


def read_parts(path, kind: str) -> tuple[dict, dict, Path]:
    """``(meta, arrays, folder)`` of a saved result of ``kind``; one ResultFileError saying what is wrong."""
    path = Path(path)
    if not (path / META).is_file():
        raise ResultFileError(f"{path}: not a saved result (no {META})")
    try:
        doc = json.loads((path / META).read_text())
    except (OSError, ValueError) as exc:
        raise ResultFileError(f"{path / META}: unreadable ({str(exc)[:120]})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ResultFileError(f"{path / META}: not an {FORMAT} file")
    if doc.get("kind") != kind:
        raise ResultFileError(f"{path}: holds a {doc.get('kind')!r} result, not a {kind!r} one")
    if not isinstance(doc.get("version"), int) or doc["version"] > VERSION:
        raise ResultFileError(f"{path}: format version {doc.get('version')!r}; this software reads up to {VERSION}")
    arrays = {}
    if (path / ARRAYS).is_file():
        try:
            with np.load(path / ARRAYS, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise ResultFileError(f"{path / ARRAYS}: unreadable ({str(exc)[:120]})") from None
    return doc, arrays, path


def need(d: dict, key: str, where):
    """``d[key]``, or a ResultFileError naming what is missing."""
    try:
        return d[key]
    except KeyError:
        raise ResultFileError(f"{where}: {key!r} is missing") from None
