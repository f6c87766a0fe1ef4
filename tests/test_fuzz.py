"""A short run of the fuzzing harness (`iptm bench fuzz` runs 10,000 inputs per reader and per generated file
kind): mutated and structure-aware hostile inputs are answered (a result or one clean IptmError), never an
escape or a hang; the harness itself counts crashes, hangs and memory."""
import time
from pathlib import Path

import numpy as np
import pytest

from iptm.benchmarks import fuzz as fuzz_mod
from iptm.benchmarks.fuzz import GENERATORS, LOG_READERS, READERS, fuzz, generate, truncation_check

#: Inputs per generated file kind here (seeded: the same inputs on every run).
N_GENERATED = 20
SEED = 7

#: File kinds whose first N_GENERATED inputs (seed 7) still escape, with where: a label here marks its case
#: xfail(strict) with the reason, so a fix shows as XPASS.
KNOWN_ESCAPES: dict[str, str] = {}


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    t0 = time.perf_counter()
    res = generate(n=N_GENERATED, seed=SEED, folder=tmp_path_factory.mktemp("gen"), log=lambda *_: None)
    return res, time.perf_counter() - t0


def _kinds():
    out = []
    for g, targets in GENERATORS.items():
        for t in targets:
            label = f"{g}/{t}"
            marks = [pytest.mark.xfail(strict=True, reason=KNOWN_ESCAPES[label])] if label in KNOWN_ESCAPES else []
            out.append(pytest.param(g, t, marks=marks, id=label))
    return out


@pytest.mark.parametrize(("gen", "kind"), _kinds())
def test_generated_input_is_answered(generated, gen, kind):
    res, _ = generated
    if kind not in res[gen]:
        pytest.skip(f"{gen}/{kind}: optional library missing")
    r = res[gen][kind]
    assert r["n"] == N_GENERATED
    assert r["read"] + r["recovered"] + r["error"] + r["unclear"] + r["escape"] + r["hang"] + r["generator"] == r["n"]
    assert r["generator"] == 0, r["examples"]  # every input was written
    assert r["escape"] == 0 and r["hang"] == 0, r["examples"]


def test_generated_run_is_ci_sized(generated):
    res, wall = generated
    assert sum(len(v) for v in res.values()) == sum(len(t) for t in GENERATORS.values()) - ("mf4" not in res["numbers"])
    assert wall < 120, wall  # about 40 s on a loaded 2-core machine


def test_generators_reach_what_they_target(tmp_path):
    """The inputs are what they claim: a power tower in a CSV header, a chunk inflating far beyond its size, a
    JSON message deeper than the nesting limit, a DBC ID sent as a 29-bit frame."""
    base = fuzz_mod._Base(tmp_path / "base")

    def case(label, i):
        g, _, t = label.partition("/")
        gi, ti = list(GENERATORS).index(g), list(GENERATORS[g]).index(t)
        folder = tmp_path / label.replace("/", "_") / str(i)
        folder.mkdir(parents=True)
        return fuzz_mod._generated_case(GENERATORS[g][t], base, folder, 0, gi, ti, i)

    kinds = set()
    rng = np.random.default_rng(1)
    for _ in range(400):
        u = fuzz_mod.hostile_unit(rng)
        kinds.add("tower" if u.count("**") + u.count("^") > 2 else "paren" if u.count("(") > 3 else "other")
    assert kinds == {"tower", "paren", "other"}
    headers = [case("units/csv-header", i)[1].read_text(errors="replace").splitlines()[0] for i in range(30)]
    assert any(h.count("**") + h.count("^") > 2 for h in headers)
    # compression: some inflated size beyond 100 times the file's size
    import struct

    import zstandard

    ratios = []
    for i in range(10):
        data = case("compression/mcap-zstd", i)[1].read_bytes()
        for op, a, b in fuzz_mod._mcap_records(data):
            if op == 6:
                body = data[a + 9:b]
                n = struct.unpack_from("<I", body, 28)[0]
                payload = body[32 + n + 8:]
                if payload[:4] == b"\x28\xb5\x2f\xfd":
                    out = zstandard.ZstdDecompressor().stream_reader(payload).read(64 << 20)
                    ratios.append(len(out) / len(data))
    assert max(ratios) > 100, ratios
    # nesting: a message deeper than the reader's limit
    from calib.ingest.limits import MAX_NESTING, json_too_deep
    from mcap.reader import make_reader

    deep = 0
    for i in range(10):
        with open(case("nesting/mcap-json", i)[1], "rb") as fh:
            deep += sum(json_too_deep(m.data, MAX_NESTING) for _, _, m in make_reader(fh).iter_messages())
    assert deep > 0
    # CAN identity: a DBC ID as an extended (8-digit) ID in candump text
    lines = "".join(case("can/candump", i)[1].read_text(errors="replace") for i in range(20))
    assert " 000000B4#" in lines or " 000001C4#" in lines or " 0000003B#" in lines


def test_cases_are_reproducible(tmp_path):
    base = fuzz_mod._Base(tmp_path / "base")
    for label in ("units/csv-header", "compression/blf-zlib", "can/asc", "numbers/mcap", "fields/scenario"):
        g, _, t = label.partition("/")
        gi, ti = list(GENERATORS).index(g), list(GENERATORS[g]).index(t)
        got = []
        for run in range(2):
            folder = tmp_path / f"{g}_{t}_{run}"
            folder.mkdir()
            _, path, _ = fuzz_mod._generated_case(GENERATORS[g][t], base, folder, 3, gi, ti, 5)
            got.append(path.read_bytes())
        assert got[0] == got[1], label


#: Mutated inputs per reader here (`iptm bench fuzz` runs 10,000 by default).
N_MUTATED = 10


@pytest.fixture(scope="module")
def counts(tmp_path_factory):
    return fuzz(n=N_MUTATED, seed=7, folder=tmp_path_factory.mktemp("fuzz"), log=lambda *_: None)


@pytest.mark.parametrize("reader", READERS)
def test_mutated_input_reads_or_fails_cleanly(counts, reader):
    if reader not in counts:
        pytest.skip(f"{reader}: optional library missing")
    c = counts[reader]
    assert c["escape"] == 0 and c["hang"] == 0 and c["unclear"] == 0 and c["printed"] == 0, c["examples"]
    assert c["read"] + c["recovered"] + c["error"] == c["n"] == N_MUTATED


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


# --- the harness itself -------------------------------------------------------------------------------
def _crash_on_odd_length(path):
    """A reader that crashes the process (as a compiled library reading past a buffer would) on some inputs."""
    import os
    import signal

    if len(Path(path).read_bytes()) % 2:
        os.kill(os.getpid(), signal.SIGSEGV)
    return {}


def _mutation_worker(fn, data, path, timeout=None):
    import functools

    return fuzz_mod._Worker(functools.partial(fuzz_mod._mutation_case, fn, data, 0, 0, path), timeout)


def test_a_crashing_reader_is_an_escape_and_the_run_goes_on(tmp_path):
    data = b"0123456789" * 20
    w = _mutation_worker(_crash_on_odd_length, data, tmp_path / "case.bin")
    outcomes = []
    try:
        for i in range(30):
            outcomes.append(w.run(i))
    finally:
        w.close()
    kinds = {o[0] for o in outcomes}
    assert kinds == {"read", "escape"}  # both happen in 30 seeded cases, and every case has an outcome
    crashed = [o[1] for o in outcomes if o[0] == "escape"]
    assert all("died (exit code -11)" in d for d in crashed)
    lengths = [len(fuzz_mod.mutate(data, 0, 0, i)) for i in range(30)]
    assert [o[0] == "escape" for o in outcomes] == [n % 2 == 1 for n in lengths]


def _slow_on_odd_length(path):
    if len(Path(path).read_bytes()) % 2:
        t0 = time.process_time()
        while time.process_time() - t0 < 30:  # a busy hang: the limit is on the case's CPU time
            pass
    return {}


def test_a_hang_is_counted_within_the_time_limit(tmp_path):
    data = b"0123456789" * 20
    w = _mutation_worker(_slow_on_odd_length, data, tmp_path / "case.bin", timeout=1.0)
    t0 = time.perf_counter()
    try:
        got = [w.run(i)[0] for i in range(8)]
    finally:
        w.close()
    lengths = [len(fuzz_mod.mutate(data, 0, 0, i)) for i in range(8)]
    assert got == ["hang" if n % 2 else "read" for n in lengths]
    # a hang costs about its limit (of CPU time: more wall time on a loaded machine) and a new worker, not 30 s
    assert time.perf_counter() - t0 < 8 + (fuzz_mod.HANG_WALL_FACTOR * 1.0 + 5) * got.count("hang")


def _allocate_on_odd_length(path):
    if len(Path(path).read_bytes()) % 2:
        block = np.ones(300 << 17)  # 300 MiB, touched
        assert block.sum() > 0
    return {}


def test_peak_memory_is_measured_per_case(tmp_path):
    data = b"0123456789" * 20
    w = _mutation_worker(_allocate_on_odd_length, data, tmp_path / "case.bin")
    try:
        got = [w.run(i) for i in range(6)]
    finally:
        w.close()
    lengths = [len(fuzz_mod.mutate(data, 0, 0, i)) for i in range(6)]
    added = [r[4] for r in got]
    assert all((a > 250) == (n % 2 == 1) for a, n in zip(added, lengths)), (added, lengths)


def _write_fails(rng, base, folder):
    raise RuntimeError("cannot write this input")


def test_a_generator_failure_is_counted_apart(tmp_path, monkeypatch):
    monkeypatch.setitem(GENERATORS, "units", {"broken": _write_fails})
    res = generate(n=3, seed=0, generators=("units",), folder=tmp_path, log=lambda *_: None)
    r = res["units"]["broken"]
    assert r["generator"] == 3 and r["escape"] == 0
    assert r["examples"][0]["detail"].startswith("RuntimeError: cannot write this input")


def test_failures_are_printed_first_and_fail_the_benchmark(tmp_path, monkeypatch, capsys):
    from calib.errors import IptmError

    def escape(rng, base, folder):
        p = folder / "x.csv"
        p.write_text("x")
        return (lambda path: {}[0]), p, ()

    monkeypatch.setattr(fuzz_mod, "GENERATORS", {"units": {"escapes": escape}})
    with pytest.raises(IptmError, match="2 inputs escaped"):
        fuzz_mod.run(n=2, readers=(), generators=("units",))
    out = capsys.readouterr().out
    summary = out[out.index("summary"):]
    assert summary.index("FAILURES") < summary.index("reader / file kind")
    assert "units/escapes case 0 (and 1 more like it): escape: KeyError: 0" in summary
