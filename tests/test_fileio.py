"""Atomic outputs get the mode any new file gets under the user's umask (not mkstemp's private 0600)."""
import os
import stat

from calib import fileio


def test_atomic_output_follows_umask(tmp_path):
    p = tmp_path / "out.json"
    fileio.write_json(p, {"a": 1})
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~fileio._UMASK
    ref = tmp_path / "plain.txt"
    ref.write_text("x")  # what open() gives under the same umask
    assert stat.S_IMODE(p.stat().st_mode) == stat.S_IMODE(ref.stat().st_mode)
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]
