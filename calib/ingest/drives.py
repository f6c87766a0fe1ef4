"""Which logs record the same drive.

The same drive exported in several formats (BLF, candump, CSV, MCAP) reads into canonical tables that
agree to the formats' quantisation, not bit for bit, so a hash of the table alone would miss the copies.
Two logs are the same drive when their canonical tables have the same time base and channels and every
channel agrees within a small fraction of its range (or the tables hash equal). Fitting on copies weights
one drive several times, and "validating" on a copy of a fitted drive is no validation at all.
"""
from __future__ import annotations

import hashlib

import numpy as np

#: Two channels agree when their largest difference is below this fraction of the channel's range.
REL_TOL = 0.01


def table_hash(log) -> str:
    """SHA-256 of the canonical table (time base, channel names and values)."""
    d = log.data
    h = hashlib.sha256()
    h.update(",".join(map(str, d.columns)).encode())
    h.update(np.ascontiguousarray(d.index.to_numpy(float)).tobytes())
    h.update(np.ascontiguousarray(d.to_numpy(float)).tobytes())
    return h.hexdigest()


def same_drive(a, b, rel_tol: float = REL_TOL) -> bool:
    """Whether two DriveLogs record the same drive (see the module text)."""
    da, db = a.data, b.data
    if da.shape != db.shape or sorted(da.columns) != sorted(db.columns):
        return False
    if not np.allclose(da.index.to_numpy(float), db.index.to_numpy(float)):
        return False
    if table_hash(a) == table_hash(b):
        return True
    for c in da.columns:
        x, y = da[c].to_numpy(float), db[c].to_numpy(float)
        if not np.array_equal(np.isfinite(x), np.isfinite(y)):
            return False
        ok = np.isfinite(x)
        if not ok.any():
            continue
        span = float(np.nanmax(x) - np.nanmin(x)) or max(abs(float(np.nanmax(x))), 1.0)
        if float(np.max(np.abs(x[ok] - y[ok]))) > rel_tol * span:
            return False
    return True


def group_drives(logs) -> list[list[int]]:
    """Indices of ``logs`` grouped by drive (first occurrence order); a group of one is a distinct drive."""
    groups: list[list[int]] = []
    for i, lg in enumerate(logs):
        for g in groups:
            if same_drive(logs[g[0]], lg):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


def split_fit_validation(fit_logs, val_logs) -> tuple[list, list, list[str]]:
    """Keep one copy of each drive for fitting and drop held-out logs that repeat a fitted drive.

    Returns ``(fit_logs, val_logs, warnings)``; the warnings name the copies (by :meth:`DriveLog.label`).
    """
    warnings = []
    groups = group_drives(fit_logs)
    kept = [fit_logs[g[0]] for g in groups]
    for g in groups:
        if len(g) > 1:
            warnings.append(f"{', '.join(fit_logs[i].label() for i in g)} are the same drive: fitted once, on "
                            f"{fit_logs[g[0]].label()}")
    val = []
    for v in val_logs:
        twin = next((f for f in kept if same_drive(f, v)), None)
        if twin is not None:
            warnings.append(f"{v.label()} is the same drive as the fitted {twin.label()}: not used for validation "
                            "(a drive that was fitted cannot validate the fit)")
            continue
        if any(same_drive(w, v) for w in val):
            warnings.append(f"{v.label()} repeats another held-out log: validated once")
            continue
        val.append(v)
    return kept, val, warnings
