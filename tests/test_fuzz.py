"""A short run of the fuzzing harness (`iptm bench fuzz` runs 10,000 inputs per reader)."""
from pathlib import Path

import pytest

from iptm.benchmarks import fuzz as fuzz_mod
from iptm.benchmarks.fuzz import LOG_READERS, READERS, fuzz, truncation_check


@pytest.fixture(scope="module")
def counts(tmp_path_factory):
    return fuzz(n=25, seed=7, folder=tmp_path_factory.mktemp("fuzz"), log=lambda *_: None)


@pytest.mark.parametrize("reader", READERS)
def test_mutated_input_reads_or_fails_cleanly(counts, reader):
    if reader not in counts:
        pytest.skip(f"{reader}: optional library missing")
    c = counts[reader]
    assert c["escape"] == 0 and c["unclear"] == 0 and c["printed"] == 0, c["examples"]
    assert c["read"] + c["recovered"] + c["error"] == c["n"] == 25


def test_mutations_are_reproducible():
    from iptm.benchmarks.fuzz import mutate

    data = bytes(range(256)) * 8
    assert mutate(data, 3, 1, 5) == mutate(data, 3, 1, 5)
    assert mutate(data, 3, 1, 5) != mutate(data, 3, 1, 6)


def test_truncated_logs_lose_nothing_before_the_cut(tmp_path):
    fmts = [f for f in LOG_READERS if f != "mf4"]  # MDF4 keeps its channel definitions after the data
    res = truncation_check(n=4, seed=3, readers=fmts, folder=tmp_path, log=lambda *_: None)
    for fmt in fmts:
        r = res[fmt]
        assert r["read_or_recovered_whole"] == r["n"], (fmt, r)
    # LZ4 chunks are read up to the cut itself: every message lying before it (zstd loses a cut block's)
    lz4 = res["mcap-lz4"]
    assert lz4["read_or_recovered_whole"] == lz4["nothing_lost_before_cut"] == lz4["n"], lz4


def _crash_on_odd_length(path):
    """A reader that crashes the process (as a compiled library reading past a buffer would) on some inputs."""
    import os
    import signal

    if len(Path(path).read_bytes()) % 2:
        os.kill(os.getpid(), signal.SIGSEGV)
    return {}


def test_a_crashing_reader_is_an_escape_and_the_run_goes_on(tmp_path):
    w = fuzz_mod._Worker(_crash_on_odd_length, b"0123456789" * 20, 0, 0, tmp_path / "case.bin")
    outcomes = []
    try:
        for i in range(30):
            outcomes.append(w.run(i))
    finally:
        w.close()
    kinds = {o for o, _, _ in outcomes}
    assert kinds == {"read", "escape"}  # both happen in 30 seeded cases, and every case has an outcome
    crashed = [d for o, d, _ in outcomes if o == "escape"]
    assert all("died (exit code -11)" in d for d in crashed)
    lengths = [len(fuzz_mod.mutate(b"0123456789" * 20, 0, 0, i)) for i in range(30)]
    assert [o == "escape" for o, _, _ in outcomes] == [n % 2 == 1 for n in lengths]
