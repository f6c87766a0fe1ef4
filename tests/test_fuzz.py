"""A short run of the fuzzing harness (`iptm bench fuzz` runs 10,000 inputs per reader)."""
import pytest

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
