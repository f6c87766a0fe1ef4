"""Atomic outputs get the mode any new file gets under the user's umask (not mkstemp's private 0600)."""
import os
import stat

import pytest

from calib import fileio


def test_atomic_output_follows_umask(tmp_path):
    p = tmp_path / "out.json"
    fileio.write_json(p, {"a": 1})
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~fileio._UMASK
    ref = tmp_path / "plain.txt"
    ref.write_text("x")  # what open() gives under the same umask
    assert stat.S_IMODE(p.stat().st_mode) == stat.S_IMODE(ref.stat().st_mode)
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]


def test_canonical_csv_and_sidecar_belong_together(tmp_path):
    """A write killed between the sidecar and the table leaves a pair that is refused, not old provenance."""
    import pandas as pd

    from calib.drivelog import DriveLog, LogMeta
    from calib.errors import LogFormatError
    from calib.ingest import read_canonical, write_canonical

    out = tmp_path / "t.csv"
    a = DriveLog(pd.DataFrame({"speed_mps": [1.0, 2.0]}, index=[0.0, 1.0]), LogMeta(source="a.csv"))
    b = DriveLog(pd.DataFrame({"speed_mps": [3.0, 4.0]}, index=[0.0, 1.0]), LogMeta(source="b.csv"))
    write_canonical(a, out)
    assert read_canonical(out).meta.source == "a.csv"
    old_table = out.read_bytes()
    write_canonical(b, out)
    assert read_canonical(out).meta.source == "b.csv"
    out.write_bytes(old_table)  # as if the table's rename had not happened
    with pytest.raises(LogFormatError, match="belongs to another version"):
        read_canonical(out)


def test_stale_temporary_files_are_removed(tmp_path):
    import os
    import time

    from calib.fileio import STALE_TMP_S, write_text

    stale = tmp_path / ".out.txt.abc123.tmp"
    stale.write_text("")
    t = time.time() - STALE_TMP_S - 10
    os.utime(stale, (t, t))
    write_text(tmp_path / "out.txt", "x")
    assert not stale.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_run_ids_are_unique_within_a_second():
    from iptm.pipeline import new_run_id

    ids = {new_run_id("abcdef123") for _ in range(200)}
    assert len(ids) > 190  # 16 bits of randomness: a repeat among 200 is rare, and a folder clash is refused
