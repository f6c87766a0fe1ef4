"""Fuzzing benchmark: hostile and mutated inputs to every reader; nothing but a clean IptmError may come out.

Two kinds of input, each read in a guarded worker process (a hang and a crash are caught, counted, and the
run goes on with a fresh worker):

- **Mutations** (``fuzz``): for each reader (the log formats CSV, MCAP, candump, ASC, BLF, TRC, MDF4, and
  the parameter, scenario and study TOML files) a small valid file is written, then ``n`` mutated copies are
  read. A mutation is 1-4 edits drawn from bit flips, truncations, insertions of random bytes, deletions and
  duplications of a stretch; case ``i`` of reader ``r`` uses ``numpy.random.default_rng([seed, r, i])``, so
  any case can be replayed (``mutate(data, seed, r, i)``).
- **Structure-aware generators** (``generate``, :data:`GENERATORS`): inputs valid in their structure and
  hostile in one respect, for every file kind that respect reaches: unit strings (power towers, huge
  exponents, long products and names, deep or unbalanced parentheses, odd characters, offset-unit algebra)
  in CSV headers, parameter-file ``unit``/``x_unit``/``bounds_unit``, DBC signal units, MCAP topic-map
  units and ``--map`` files; compression ratios (MCAP zstd and LZ4 chunks and BLF zlib containers inflating
  to up to 8 GiB of zeros, or to compressed real records and noise, declaring their true size, less, more,
  nothing or an absurd size, some with lying compressed sizes and names); nesting (JSON messages up to
  1,000,000 levels deep in MCAP, deep topic-map fields, deep arrays and inline tables in parameter,
  scenario, study and map TOML); CAN identities (DBC IDs as 29-bit frames, standard IDs cut from extended
  ones, up to 5,000 buses, odd bus names, IDs beyond 29 bits, DLCs and payloads of 0-65 bytes, duplicated
  frames, OBD-II responses of odd lengths, ``bus=`` naming a missing bus) in candump, ASC, TRC and BLF;
  extreme numbers (1e308, 1e400, -0, NaN/Infinity text, huge integers, denormals, locale digits, hex
  floats) in every reader, in DBC factors/offsets/ranges, in BLF object timestamps/IDs/DLCs and header
  dates, in MDF samples and timestamps; and parameter, scenario and study fields (values of every TOML
  type, NaN, inf, negative, zero, grids down to 1e-9, long [vary] lists, the cases of the hostile-input
  issue). A scenario is loaded and its DP problems built (the size checks run there; nothing is solved); a
  study is loaded and expanded. Case ``i`` of file kind ``t`` of generator ``g`` uses
  ``numpy.random.default_rng([seed, g, t, i])``; :func:`replay` writes it again and reads it in-process.

Each input ends in one of:

- ``read``: read, no damage reported; ``recovered``: read, with a damage report (``LogMeta.damage``);
- ``error``: a clean :class:`calib.errors.IptmError` (one line, naming the file); these three are
  ``answered``;
- ``unclear``: an IptmError whose message is not one line naming the file (or the DBC/map it used);
- ``escape``: any other exception (a bug), or a crash of the process (a compiled library reading past a
  buffer); ``hang``: no answer within :data:`CASE_TIMEOUT_S` of CPU time (``--timeout``; CPU time, so that
  a loaded machine does not turn slow reads into hangs) or :data:`HANG_WALL_FACTOR` times that of wall time;
- ``generator``: this benchmark failed to write the input (a bug of this file).

``printed`` counts reads that wrote anything to stdout/stderr or issued a foreign warning (a library
talking past the project's own reporting). Peak memory is the worker's peak resident size during one case
(reset before each case through ``/proc/self/clear_refs``), with the largest rise within one case; a worker
may add at most :data:`WORKER_MEMORY_MB` MiB of address space (beyond it a read gets a MemoryError, an
escape, instead of the machine's memory).

The truncation check (``n / 20`` cuts per format, 50 to 500) cuts a larger valid log of each format at a
uniformly random byte between 10 % and 100 % of its length and counts the cuts read or recovered with
every sample up to the recovered end time equal to the intact file's. For MCAP (its zstd seed, and the
same messages rewritten with LZ4 chunks, ``mcap-lz4``) it also counts the cuts after which every message
lying before the cut (:func:`mcap_message_positions`) was read, and the log time lost before the cut:
a zstd block decodes only whole, so a cut inside one loses the block's records before the cut.

Run: ``iptm bench fuzz`` (10,000 inputs per reader and per generated file kind; ``--quick``: 300; ``--n``)
or ``python -m iptm.benchmarks.fuzz --n 200 --seed 1 [--generators units,can] [--readers csv,mcap]
[--no-mutations] [--no-truncation] [--timeout 10]``; replay one generated case with
``python -m iptm.benchmarks.fuzz --replay units/csv-header:123``. The benchmark fails (an IptmError, exit
status 2) after printing the failures first and then the table, when any input escapes or hangs.
"""
from __future__ import annotations
import argparse
import contextlib
import io
import json
import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

LOG_READERS = ("csv", "mcap", "candump", "asc", "blf", "trc", "mf4")
TOML_READERS = ("params", "scenario", "study")
READERS = LOG_READERS + TOML_READERS
EXT = {"csv": "csv", "mcap": "mcap", "candump": "log", "asc": "asc", "blf": "blf", "trc": "trc", "mf4": "mf4",
       "params": "toml", "scenario": "toml", "study": "toml"}
KINDS = ("flip", "cut", "insert", "delete", "dup")

_SCENARIO = """\
# fuzz seed: a scenario file
[scenario]
cycle = "nycc"
T_amb = -7.0
soc0 = 0.6

[grids]
soc = 0.02
tcl = 2.0

[run]
strategies = ["rule", "baseline"]
"""

_STUDY = """\
# fuzz seed: a study file
[study]
name = "fuzz"
strategies = ["rule", "baseline"]
reference = "rule"
grids = {soc = 0.02}

[scenario]
soc0 = 0.6

[vary]
T_amb = [-10, 0]
cycle = ["nycc"]
"""


def _small_streams(duration_s=8.0, rate=5.0):
    from testcars.fabricate import fabricate_streams

    rates = {c: rate for c in ("speed_mps", "bat_current_A", "bat_voltage_V", "engine_speed_rpm",
                               "engine_torque_Nm", "fuel_rate_g_per_s")}
    return fabricate_streams(duration_s, dropout=None, rates=rates)


def _write_trc(blf: Path, out: Path) -> Path:
    import can

    with can.BLFReader(str(blf)) as reader, can.TRCWriter(str(out)) as w:
        for msg in reader:
            w.on_message_received(msg)
    return out


def _write_mf4(streams, out: Path) -> Path:
    import asammdf

    from calib import CHANNELS
    from calib.ingest import HUMAN_NAME

    mdf = asammdf.MDF(version="4.10")
    sigs = []
    for ch, s in streams.items():
        unit, scale = CHANNELS[ch][0], 1.0
        if unit == "dimensionless":
            unit, scale = "%", 100.0
        sigs.append(asammdf.Signal(samples=s.to_numpy(float) * scale, timestamps=s.index.to_numpy(float),
                                   name=HUMAN_NAME.get(ch, ch), unit=unit))
    for sg in sigs:
        mdf.append([sg])
    mdf.save(out, overwrite=True)
    mdf.close()
    return out


def make_seed_files(folder, duration_s: float = 8.0, rate: float = 5.0) -> dict[str, Path]:
    """Valid input of every reader in ``folder`` (small by default; larger for the truncation check)."""
    from calib.model import default_parameters
    from calib.ingest import write_streams

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    streams, meta = _small_streams(duration_s, rate)
    out = {}
    for fmt in ("csv", "mcap", "candump", "asc", "blf"):
        out[fmt] = write_streams(streams, meta, folder / f"seed.{EXT[fmt]}", fmt)
    out["trc"] = _write_trc(out["blf"], folder / "seed.trc")
    try:
        out["mf4"] = _write_mf4(streams, folder / "seed.mf4")
    except ImportError:
        pass
    p = folder / "seed_params.toml"
    default_parameters().save(p)
    out["params"] = p
    (folder / "seed_scenario.toml").write_text(_SCENARIO)
    out["scenario"] = folder / "seed_scenario.toml"
    (folder / "seed_study.toml").write_text(_STUDY)
    out["study"] = folder / "seed_study.toml"
    return out


def reader_fn(name: str):
    """path -> damage dict ({} when intact) for the reader ``name``; raises what the reader raises."""
    if name in LOG_READERS:
        from calib.ingest import read_log

        fmt = name

        def run(path):
            return read_log(path, fmt=fmt).meta.damage
        return run
    if name == "params":
        from calib.model import ParameterSet

        return lambda path: (ParameterSet.load(path), {})[1]
    if name == "scenario":
        from iptm.pipeline import load_scenario

        return lambda path: (load_scenario(path), {})[1]
    if name == "study":
        from optimize import load_study

        return lambda path: (load_study(path), {})[1]
    raise KeyError(name)


def mutate(data: bytes, seed: int, reader_index: int, case: int) -> bytes:
    """The mutated copy of ``data`` for one case (reproducible)."""
    rng = np.random.default_rng([seed, reader_index, case])
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        if not b:
            break
        kind = KINDS[int(rng.integers(len(KINDS)))]
        i = int(rng.integers(len(b)))
        if kind == "flip":
            b[i] ^= 1 << int(rng.integers(8))
        elif kind == "cut":
            del b[i:]
        elif kind == "insert":
            b[i:i] = rng.integers(0, 256, int(rng.integers(1, 17)), dtype=np.uint8).tobytes()
        elif kind == "delete":
            del b[i:i + int(rng.integers(1, 65))]
        else:
            j = min(len(b), i + int(rng.integers(1, 257)))
            b[i:i] = b[i:j]
    return bytes(b)




@contextlib.contextmanager
def _fd_capture():
    """Capture what is written to file descriptors 1 and 2 (handlers holding the real stderr, C code)."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        text = []
        try:
            yield lambda: "".join(text)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            tmp.seek(0)
            text.append(tmp.read().decode("utf-8", "replace"))


def _where(exc: BaseException) -> str:
    """The innermost frame of the project's own code (else the innermost frame) an exception passed."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in frames if "/.venv/" not in f.filename and "site-packages" not in f.filename
            and "/lib/python" not in f.filename]
    f = (ours or frames or [None])[-1]
    if f is None:
        return ""
    return f" [at {_short(f.filename)}:{f.lineno} in {f.name}]"


def _short(name: str) -> str:
    """A source path from the package root (``calib/ingest/csvlog.py``), or as it is."""
    for root in ("calib/", "optimize/", "iptm/", "site-packages/"):
        if f"/{root}" in name:
            return (root if root != "site-packages/" else "") + name.split(f"/{root}", 1)[1]
    return name


def classify(fn, path, names=None) -> tuple[str, str, str]:
    """Read ``path``: (outcome, detail, printed) with outcome read/recovered/error/unclear/escape; ``printed``
    is what the read wrote to the console or the first foreign warning it issued ("" when nothing).

    ``error`` is an IptmError whose message is one line naming the file (or one of ``names``, the other files
    the read used: a DBC, a map; a reader marks an error ``names_file = False`` where it is about what was built
    from the file, not the file); any other IptmError is ``unclear``."""
    from calib import IptmError, IptmWarning

    names = [Path(path).name] + [Path(x).name for x in (names or ())]
    out, err = io.StringIO(), io.StringIO()
    detail = ""
    with _fd_capture() as fd_out, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            damage = fn(path)
            outcome = "recovered" if damage else "read"
        except IptmError as exc:
            msg = str(exc)
            named = any(nm in msg for nm in names) or not getattr(exc, "names_file", True)
            outcome = "error" if ("\n" not in msg and named) else "unclear"
            detail = msg[:200]
        except Exception as exc:  # noqa: BLE001 - this is what the harness looks for
            outcome = "escape"
            detail = f"{type(exc).__name__}: {str(exc)[:200]}{_where(exc)}"
    foreign = [w for w in caught if not issubclass(w.category, IptmWarning)]
    raw = fd_out()
    printed = ""
    if out.getvalue() or err.getvalue() or raw:
        printed = (out.getvalue() or err.getvalue() or raw).strip()[:200] or "(blank output)"
    elif foreign:
        w = foreign[0]
        printed = f"{w.category.__name__}: {str(w.message)[:160]} [at {_short(w.filename)}:{w.lineno}]"
    return outcome, detail, printed


def _in_folder(fn):
    """Run ``fn(folder=...)`` in a temporary folder removed afterwards unless the caller gave one."""
    import functools
    import shutil

    @functools.wraps(fn)
    def wrapper(*args, folder=None, **kw):
        if folder is not None:
            return fn(*args, folder=Path(folder), **kw)
        tmp = Path(tempfile.mkdtemp(prefix=f"iptm-{fn.__name__}-"))
        try:
            return fn(*args, folder=tmp, **kw)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return wrapper


#: A read that takes longer than this (s of the worker's CPU time, so that a loaded machine does not make
#: hangs of slow reads) is a hang.
CASE_TIMEOUT_S = 10.0
#: ... and so is a read that has not answered after this many times the limit of wall time (a read blocked
#: without using the CPU).
HANG_WALL_FACTOR = 5.0
#: Writing one input (a generated bomb, a mutated copy) that takes longer than this (s) is a failure of the
#: generator.
GENERATE_TIMEOUT_S = 120.0
#: Address space a worker may add to what it holds when it starts, MiB: a read that needs more gets a
#: MemoryError (an escape) instead of taking the machine's memory.
WORKER_MEMORY_MB = 3072


def _rss_mb(field: str) -> float | None:
    """``VmHWM`` / ``VmRSS`` / ``VmSize`` of this process in MiB (None where /proc is not there)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _cpu_seconds(pid: int) -> float | None:
    """CPU time (user + system, s) a process has used, from ``/proc`` (None where it is not there)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _reset_peak() -> bool:
    """Reset the peak resident size to the current one (Linux >= 4.0), so that each case has its own peak."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _serve(conn, case):
    """Worker loop: case number in, (outcome, detail, printed, peak MiB, added MiB, seconds) out.

    ``case(i)`` writes the input of case ``i`` and returns (reader, path, other file names)."""
    import faulthandler
    import resource

    import calib  # noqa: F401 - its errors, which classify() needs, imported before any case is timed

    faulthandler.disable()  # a crash is reported by its exit code and case number (replay it)
    with contextlib.suppress(OSError, AttributeError):  # Linux: end with the benchmark if it is killed
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    size = _rss_mb("VmSize")
    if size is not None and WORKER_MEMORY_MB:
        limit = int((size + WORKER_MEMORY_MB) * (1 << 20))
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    own_peak = _reset_peak()
    while True:
        i = conn.recv()
        if i is None:
            return
        try:
            fn, path, names = case(i)
        except Exception as exc:  # noqa: BLE001 - the generator's own failure, counted apart from the readers'
            conn.send(("generator", f"{type(exc).__name__}: {str(exc)[:200]}{_where(exc)}", "", 0.0, 0.0, 0.0))
            continue
        conn.send("written")  # the time limit runs from here: writing a large input is not the reader's time
        before = _rss_mb("VmRSS") or 0.0
        if own_peak:
            _reset_peak()
        t0 = time.perf_counter()
        outcome, detail, printed = classify(fn, path, names)
        dt = time.perf_counter() - t0
        peak = _rss_mb("VmHWM") if own_peak else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        conn.send((outcome, detail, printed, peak or 0.0, max((peak or 0.0) - before, 0.0), dt))


class _Worker:
    """A forked process that reads cases; restarted after a crash or a hang.

    ``case(i)`` -> (reader, path, other file names): writes the input of case ``i`` (in the worker)."""

    def __init__(self, case, timeout: float | None = None):
        self.case = case
        self.timeout = CASE_TIMEOUT_S if timeout is None else timeout
        self.proc = None

    def _start(self):
        import multiprocessing as mp

        ctx = mp.get_context("fork")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, self.case), daemon=True)
        self.proc.start()
        child.close()

    def run(self, i):
        """(outcome, detail, printed, peak MiB, added MiB, seconds) of case ``i``; outcome ``hang`` past the
        time limit, ``escape`` when the process died."""
        if self.proc is None or not self.proc.is_alive():
            self._start()
        self.conn.send(i)
        try:
            if not self.conn.poll(GENERATE_TIMEOUT_S):
                outcome, detail = "generator", f"the input was not written within {GENERATE_TIMEOUT_S:g} s"
            else:
                got = self.conn.recv()
                if got != "written":
                    return got
                cpu0, t0 = _cpu_seconds(self.proc.pid), time.perf_counter()
                while True:
                    if self.conn.poll(min(1.0, self.timeout)):
                        return self.conn.recv()
                    wall = time.perf_counter() - t0
                    cpu = _cpu_seconds(self.proc.pid)
                    used = cpu - cpu0 if cpu is not None and cpu0 is not None else wall
                    if used > self.timeout or wall > HANG_WALL_FACTOR * self.timeout:
                        break
                outcome = "hang"
                detail = f"no result after {used:.1f} s of CPU time ({wall:.1f} s of wall time)"
        except (EOFError, ConnectionError):
            self.proc.join(5)
            outcome, detail = "escape", f"the reading process died (exit code {self.proc.exitcode})"
        self.close()
        return outcome, detail, "", 0.0, 0.0, self.timeout if outcome == "hang" else 0.0

    def close(self):
        if self.proc is None:
            return
        if self.proc.is_alive():
            with contextlib.suppress(OSError, ValueError):
                self.conn.send(None)
            self.proc.join(2)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join()
        self.proc = None


#: Outcomes of a case: a result or one clean IptmError is ``answered``; the rest are failures or notes.
OUTCOMES = ("read", "recovered", "error", "unclear", "escape", "hang", "generator")
#: Outcomes that fail the benchmark (an escape or a hang is a bug of the readers, ``generator`` of this file).
FAILURES = ("escape", "hang", "generator")


def _signature(outcome: str, detail: str) -> str:
    """What makes two failures the same: the outcome, the exception type and where it was raised (an escape);
    the message with its numbers and paths blanked (the rest)."""
    import re

    if outcome in ("escape", "generator") and " [at " in detail:
        return f"{outcome}: {detail.split(':', 1)[0]}{detail[detail.rfind(' [at '):]}"
    text = re.sub(r"/\S+/", "/.../", detail)
    return f"{outcome}: {re.sub(r'[0-9.e+-]+', '#', text)[:70]}"


class _Tally:
    """Counts, time and peak memory of the cases of one reader or file kind; the first case of each distinct
    failure (outcome, exception type, place) with its count, and the first few notes (unclear, printed)."""

    MAX_KINDS = 25

    def __init__(self, label: str, n: int):
        self.label, self.n = label, n
        self.counts = dict.fromkeys((*OUTCOMES, "printed"), 0)
        self.kinds: dict[str, dict] = {}
        self.peak_mb = self.added_mb = self.slowest_s = 0.0
        self.peak_case = self.slowest_case = None
        self.t0 = time.perf_counter()
        self.wall = 0.0

    def add(self, i, res):
        outcome, detail, printed, peak, added, dt = res
        self.counts[outcome] += 1
        self.counts["printed"] += bool(printed)
        if peak > self.peak_mb:
            self.peak_mb = peak
        if added > self.added_mb:
            self.added_mb, self.peak_case = added, i
        if dt > self.slowest_s:
            self.slowest_s, self.slowest_case = dt, i
        notes = []
        if outcome in FAILURES or outcome == "unclear":
            notes.append((outcome, detail))
        if printed:
            notes.append(("printed", printed))
        for kind, text in notes:
            sig = _signature(kind, text)
            k = self.kinds.get(sig)
            if k is not None:
                k["count"] += 1
            elif len(self.kinds) < self.MAX_KINDS:
                self.kinds[sig] = {"case": i, "outcome": kind, "detail": text, "count": 1}

    def done(self) -> dict:
        self.wall = time.perf_counter() - self.t0
        c = self.counts
        return {**c, "n": self.n, "answered": c["read"] + c["recovered"] + c["error"], "wall_s": self.wall,
                "peak_mb": self.peak_mb, "added_mb": self.added_mb, "added_mb_case": self.peak_case,
                "slowest_s": self.slowest_s, "slowest_case": self.slowest_case,
                "examples": sorted(self.kinds.values(), key=lambda e: (e["outcome"] not in FAILURES, -e["count"]))}


def _line(label: str, r: dict) -> str:
    return (f"{label:26s} {r['n']:6d} {r['answered']:8d} {r['read']:6d} {r['recovered']:6d} {r['error']:6d} "
            f"{r['unclear']:5d} {r['escape']:5d} {r['hang']:5d} {r['printed']:5d} {r['peak_mb']:7.0f} "
            f"{r['added_mb']:6.0f} {r['slowest_s']:6.2f} {r['wall_s']:7.1f}")


TABLE_HEAD = (f"{'reader / file kind':26s} {'inputs':>6s} {'answered':>8s} {'read':>6s} {'recov':>6s} {'error':>6s} "
              f"{'uncl':>5s} {'esc':>5s} {'hang':>5s} {'print':>5s} {'peakMB':>7s} {'+MB':>6s} {'max s':>6s} "
              f"{'time s':>7s}")
TABLE_NOTE = ("answered = read + recovered (a damage report) + error (one clean IptmError naming the file); "
              "uncl = an IptmError not one line naming the file; esc = any other exception or a dead process; "
              "hang = no answer within the time limit; print = console output or a foreign warning; peakMB = the "
              "worker's peak resident memory during a case, +MB = its rise within one case (max), max s = the "
              "slowest case")


def _run_cases(label, case, n, log, timeout=None) -> dict:
    """Run cases 0..n-1 of ``case`` in a worker; the tally as a dict (and one line in ``log``)."""
    tally = _Tally(label, n)
    worker = _Worker(case, timeout)
    try:
        for i in range(n):
            tally.add(i, worker.run(i))
    finally:
        worker.close()
    res = tally.done()
    log(_line(label, res))
    for ex in res["examples"]:
        log(f"    case {ex['case']} (x{ex['count']}): {ex['outcome']}: {ex['detail']}")
    return res


def _mutation_case(fn, data, seed, r, path, i):
    path.write_bytes(mutate(data, seed, r, i))
    return fn, path, ()


@_in_folder
def fuzz(n: int = 10_000, seed: int = 0, readers=READERS, folder=None, log=print, timeout=None) -> dict:
    """Mutated-input counts per reader (see the module docstring)."""
    import functools

    seeds = make_seed_files(folder / "seeds")
    results = {}
    for r, name in enumerate(READERS):
        if name not in readers:
            continue
        if name not in seeds:
            log(f"{name:9s} skipped (its library is not installed)")
            continue
        data = seeds[name].read_bytes()
        fn = reader_fn(name)
        assert classify(fn, seeds[name])[0] == "read", f"seed file of {name} does not read cleanly"
        case = functools.partial(_mutation_case, fn, data, seed, r, folder / f"case.{EXT[name]}")
        results[name] = _run_cases(f"mutated {name}", case, n, log, timeout)
    return results


# ---------------------------------------------------------------------------------------------------
# structure-aware generators
# ---------------------------------------------------------------------------------------------------
# Each generator builds inputs that are valid in their structure and hostile in one respect (a unit, a
# compression ratio, a nesting depth, a CAN identity, a number, a field of a parameter or scenario file), for
# every file kind through which that respect reaches the workbench. Case ``i`` of target ``t`` of generator
# ``g`` draws from ``numpy.random.default_rng([seed, g, t, i])`` (indices in :data:`GENERATORS`), so every
# case can be written again (:func:`replay`).

def _log_uniform(rng, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _pick(rng, seq):
    return seq[int(rng.integers(len(seq)))]


_UNIT_NAMES = ("m", "s", "km", "h", "km/h", "kg", "g", "W", "kW", "V", "A", "mA", "degC", "degF", "K", "rpm", "N",
               "N*m", "J", "percent", "%", "mile", "hour", "L", "mL", "gallon", "Ah", "ohm", "rad", "delta_degC",
               "dB", "bit", "1", "°C", "µs", "Ω", "kph", "mph", "g/s", "L/h", "kg/s", "1/min", "foo", "nan", "inf",
               "e", "pi", "planck_constant", "speed_of_light", "dimensionless", "kelvin", "degree", "turn")
_ODD_CHARS = ("\x00", "\t", "\r", "\n", "\x7f", "\u202e", "\u0301", "\U0001F600", "\ufeff", "\\", '"', "'", ",",
              ";", "#", "[", "]", "{", "}", "(", ")", "=", "$", "`", "\u00a0", "\u2028", "\ufb00", "\u2460", "²",
              "³", "½", "_", "@", "...", "<", ">", "|", "&", "**", "^", "/", "*", "-", "+", " ", "%", "°", "·")
_BIG_EXPONENTS = ("9", "99", "999", "9999", "99999999", "1e9", "1e308", "1e400", "-9", "-999", "0.5", "1/2", "nan",
                  "inf", "9" * 400, "0", "-0", "4.000001")

#: Kinds of hostile unit strings.
UNIT_KINDS = ("tower", "big_exponent", "long_product", "long_name", "nesting", "nested_power", "odd_chars",
              "numbers", "offset", "random_text", "valid")


def hostile_unit(rng) -> str:
    """A unit string of one of :data:`UNIT_KINDS`: a power tower, a huge exponent, a long product, a long
    name, deep or unbalanced parentheses, odd characters, numbers, offset-unit algebra, random text, or a
    valid unit (so that some inputs are read)."""
    kind = _pick(rng, UNIT_KINDS)
    name = _pick(rng, _UNIT_NAMES)
    if kind == "tower":
        op = _pick(rng, ("**", "^"))
        return name + "".join(op + _pick(rng, ("9", "2", "99", "9.9", "-9")) for _ in range(int(rng.integers(1, 60))))
    if kind == "big_exponent":
        return f"{name}{_pick(rng, ('**', '^', '**-', ' ** '))}{_pick(rng, _BIG_EXPONENTS)}"
    if kind == "long_product":
        n = int(_log_uniform(rng, 2, 100_000))
        ops = ("*", "/", " ", "**2*", "·")
        return "".join(_pick(rng, _UNIT_NAMES) + _pick(rng, ops) for _ in range(n)) + name
    if kind == "long_name":
        return _pick(rng, ("k", "m", "x", "é", "µ", "kilo")) * int(_log_uniform(rng, 10, 1_000_000)) + name
    if kind == "nesting":
        d = int(_log_uniform(rng, 1, 100_000))
        d2 = d if rng.random() < 0.7 else int(rng.integers(0, 2 * d + 1))
        return "(" * d + name + ")" * d2
    if kind == "nested_power":
        d = int(_log_uniform(rng, 1, 10_000))
        return "(" * d + name + "".join(f")**{_pick(rng, ('9', '2', '-1'))}" for _ in range(d))
    if kind == "odd_chars":
        s = list(name)
        for _ in range(int(rng.integers(1, 6))):
            s.insert(int(rng.integers(len(s) + 1)), _pick(rng, _ODD_CHARS))
        return "".join(s)
    if kind == "numbers":
        return _pick(rng, ("1e400 m", "1/0", "0**0", "nan*m", "10**10**10", "1e308*1e308", "0 m", "-1 m",
                           "1e-400/s", "2**1000 W", "(1/0)*m", "m/0", "inf kg", "0.0/0.0"))
    if kind == "offset":
        return _pick(rng, ("degC**2", "degC/s", "degC*degF", "1/degC", "degF**-1", "degC*m", "degC**0.5",
                           "(degC)**9", "degC degC", "percent**4", "delta_degC**9"))
    if kind == "random_text":
        n = int(_log_uniform(rng, 1, 200))
        return "".join(chr(int(rng.integers(1, 0x2FFF))) for _ in range(n))
    return _pick(rng, ("km/h", "mph", "m/s", "kph", "degF", "degC", "K", "%", "A", "V", "g/s", "L/h", "rpm", "kW"))


def _toml_str(s: str) -> str:
    """A TOML basic string of ``s`` (every control character escaped)."""
    out = []
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F or 0xD800 <= ord(ch) < 0xE000:
            out.append(f"\\u{ord(ch) if ord(ch) < 0xD800 else 0xFFFD:04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


#: Number spellings for text formats: extremes, signed zeros, NaN/Infinity text, huge integers, denormals,
#: and near-numbers (locale digits, separators, hex floats).
NUMBER_TEXTS = ("1e308", "-1e308", "1.7976931348623157e308", "1e400", "-1e400", "1e-400", "4.9e-324", "5e-324",
                "-5e-324", "2.2250738585072014e-308", "1e-320", "-0", "-0.0", "+0", "0", "NaN", "nan", "-nan",
                "NAN", "Infinity", "-Infinity", "inf", "-inf", "+inf", "INF", "1e999999999", "9" * 400,
                "1" + "0" * 5000, "18446744073709551616", "-9223372036854775809", "9007199254740993",
                "0x1p-1074", "0x10", "1_000", "\u0661\u0662\u0663", "1,5", "1.5e", "--1", "", " ", ".", "e5",
                "1e+308", "1E308", "0.1e-307", "1" * 30 + ".5", "1e-7", "-1500", "1e300", "3.4e38")
#: The same for TOML (what tomllib accepts, and what it does not).
TOML_NUMBERS = ("1e308", "-1e308", "1e400", "-1e400", "1e-400", "5e-324", "-5e-324", "2.2250738585072014e-308",
                "-0.0", "+0.0", "0", "-0", "nan", "-nan", "+nan", "inf", "-inf", "+inf", "9" * 400, "9" * 5000,
                "9223372036854775807", "-9223372036854775808", "18446744073709551616", "0x7FFFFFFFFFFFFFFF",
                "0b1", "0o7", "1_000", "1e-7", "1e-300", "-1500", "1e300", "-5", "1e9", "-1e9", "0.0", "1", "-1")
#: Values of any TOML type for a field.
TOML_ANY = ('"abc"', '""', '"nan"', '"1e3"', "true", "false", "1979-05-27T07:32:00Z", "1979-05-27", "07:32:00",
            "[]", '[1, "a"]', "[[1], [2]]", "[1.0, 2.0]", "{}", "{a = 1}", '{value = 1}', "[nan, inf]",
            '"' + "x" * 100_000 + '"')


def _toml_number(rng) -> str:
    if rng.random() < 0.6:
        return _pick(rng, TOML_NUMBERS)
    return f"{_pick(rng, ('', '-'))}{_log_uniform(rng, 1e-320, 1e308):.6g}".replace("inf", "1e308")


def _toml_value(rng, numeric: float = 0.7) -> str:
    if rng.random() < numeric:
        return _toml_number(rng)
    if rng.random() < 0.1:
        n = int(_log_uniform(rng, 1, 100_000))
        return "[" + ", ".join(_toml_number(rng) for _ in range(min(n, 50))) + ", 1.0" * max(n - 50, 0) + "]"
    return _pick(rng, TOML_ANY)


def _deep_toml(rng) -> str:
    d = int(_log_uniform(rng, 1, 200_000))
    if rng.random() < 0.5:
        return "[" * d + "1" + "]" * d
    return "{a = " * d + "1" + "}" * d


class _Base:
    """What the generators build on, made once before the workers fork (they share it)."""

    def __init__(self, folder: Path):
        from calib.ingest import PRIUS_DBC, can_frames, mcap_layout
        from calib.model import default_parameters
        from calib import convert

        self.folder = Path(folder)
        self.files = make_seed_files(self.folder / "seeds")
        self.streams, self.meta = _small_streams()
        self.frames = can_frames(self.streams)
        self.dbc_text = PRIUS_DBC.read_text()
        self.text = {k: self.files[k].read_text() for k in ("csv", "candump", "asc", "trc")}
        self.blf = self.files["blf"].read_bytes()
        self.mcap = self.files["mcap"].read_bytes()
        self.params = default_parameters()
        layout = mcap_layout()
        per_topic: dict[str, dict[float, dict]] = {}
        for ch, s in self.streams.items():
            topic, field, unit = layout[ch]
            vals = convert(s.to_numpy(float), _channel_unit(ch), unit)
            for t, v in zip(s.index.to_numpy(float), vals):
                per_topic.setdefault(topic, {}).setdefault(round(float(t), 6), {})[field] = float(v)
        #: (topic, log time ns, {field: value}), time-sorted
        self.messages = sorted(((tp, int(round(t * 1e9)) + 10**18, d) for tp, by_t in per_topic.items()
                                for t, d in by_t.items()), key=lambda m: m[1])

    def warm(self):
        """Import and compile what the readers use before the workers fork, so no case pays for it."""
        from calib.ingest import read_log

        for fmt in LOG_READERS:
            if fmt in self.files:
                read_log(self.files[fmt], fmt=fmt)
        _scenario_reader(self.files["scenario"])
        _study_reader(self.files["study"])


def _channel_unit(ch: str) -> str:
    from calib import CHANNELS

    return CHANNELS[ch][0]


def _log_reader(fmt: str, **kw):
    from calib.ingest import read_log

    def run(path):
        return read_log(path, fmt=fmt, **kw).meta.damage
    return run


def _params_reader(path):
    from calib.model import ParameterSet

    ParameterSet.load(path).model_params()
    return {}


def _scenario_reader(path):
    """Load a scenario file and build the DP problem of each DP strategy it asks for (the size checks run
    where the problem is built; nothing is solved)."""
    from calib import IptmError
    from calib.model import default_parameters
    from iptm.pipeline import load_scenario
    from optimize.formulations import build_problem

    scen, grids, strategies, cycle_log = load_scenario(path)
    if cycle_log is None:
        ps = default_parameters()
        try:
            for f, nx in (("baseline", 1), ("thermal", 2), ("thermal_cabin", 3)):
                if f in strategies:
                    build_problem(ps, scen, grids.of(f), nx)
        except IptmError as exc:
            exc.names_file = False  # about the problem built from the file's fields (it names them), not the file
            raise
    return {}


def _study_reader(path):
    """Load a study file and expand its cases (what ``iptm sweep`` does before it submits anything)."""
    from optimize import load_study

    load_study(path).expand()
    return {}


def _map_reader(log: Path, fmt: str):
    """Read ``log`` with the map file given as the case's path (what ``iptm ingest --map`` does)."""
    from calib.ingest import load_map, read_log

    def run(path):
        maps = load_map(path)
        return read_log(log, fmt=fmt, column_map=maps["columns"] or None, topic_map=maps["topics"] or None,
                        signal_map=maps["signals"] or None).meta.damage
    return run


# --- units ------------------------------------------------------------------------------------------
def _units_csv(rng, base, folder):
    col = int(rng.integers(3))
    units = ["s", "km/h", "degC"]
    units[col] = hostile_unit(rng)
    style = _pick(rng, ("[{}]", "({})", "[{}]"))
    head = ",".join(f"{nm} {style.format(u)}" for nm, u in zip(("time", "speed", "coolant_temp"), units))
    rows = "".join(f"{k * 0.5:g},{10 + k},{20 + k % 3}\n" for k in range(int(rng.integers(2, 30))))
    p = folder / "units.csv"
    p.write_text(head + "\n" + rows, encoding="utf-8", errors="surrogateescape")
    return _log_reader("csv"), p, ()


def _units_params(rng, base, folder):
    ps = base.params
    name = _pick(rng, ps.names())
    p = ps.param(name)
    u = _toml_str(hostile_unit(rng))
    lines = [f"[parameters.{name}]"]
    if p.is_table:
        lines.append("value = [" + ", ".join(repr(float(v)) for v in p.value) + "]")
        lines.append(f"{_pick(rng, ('unit', 'x_unit', 'bounds_unit'))} = {u}")
        if rng.random() < 0.5:
            lines.append("x = [" + ", ".join(repr(float(v)) for v in p.x) + "]")
    else:
        lines.append(f"value = {float(p.value)!r}")
        key = _pick(rng, ("unit", "unit", "bounds_unit"))
        lines.append(f"{key} = {u}")
        if key == "bounds_unit" or rng.random() < 0.3:
            lines.append(f"bounds = [{float(p.bounds[0])!r}, {float(p.bounds[1])!r}]")
    path = folder / "units_params.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return _params_reader, path, ()


def _dbc_with(base, rng, edit) -> str:
    """The shipped DBC with ``edit(match, rng)`` applied to some of its signal lines."""
    import re

    sig = re.compile(r'^( SG_ \S+ : \S+ )\(([^,]+),([^)]+)\) \[([^|]+)\|([^\]]+)\] "([^"]*)"(.*)$', re.M)
    matches = list(sig.finditer(base.dbc_text))
    chosen = set(rng.choice(len(matches), size=int(rng.integers(1, len(matches) + 1)), replace=False).tolist())
    out, pos = [], 0
    for k, m in enumerate(matches):
        out.append(base.dbc_text[pos:m.start()])
        out.append(edit(m, rng) if k in chosen else m.group(0))
        pos = m.end()
    out.append(base.dbc_text[pos:])
    return "".join(out)


def _units_dbc(rng, base, folder):
    text = _dbc_with(base, rng, lambda m, r: (f'{m.group(1)}({m.group(2)},{m.group(3)}) [{m.group(4)}|{m.group(5)}] '
                                              f'"{hostile_unit(r)}"{m.group(7)}'))
    dbc = folder / "units.dbc"
    dbc.write_text(text, encoding="utf-8", errors="surrogateescape")
    p = folder / "units.log"
    p.write_text(base.text["candump"])
    return _log_reader("candump", dbc=dbc), p, (dbc,)


def _units_mcap_map(rng, base, folder):
    ch = _pick(rng, (("/vehicle/speed", "speed", "speed_mps"), ("/engine", "coolant_temp", "coolant_temp_degC"),
                     ("/hv_battery", "soc", "soc"), ("/engine", "fuel_rate", "fuel_rate_g_per_s")))
    tmap = {ch[0]: {ch[1]: f"{ch[2]} [{hostile_unit(rng)}]"}}
    p = folder / "units.mcap"
    p.write_bytes(base.mcap)
    return _log_reader("mcap", topic_map=tmap), p, ()


def _units_map_file(rng, base, folder):
    kind = _pick(rng, ("csv", "mcap", "candump"))
    u = _toml_str(f"speed_mps [{hostile_unit(rng)}]")
    if kind == "csv":
        text = f'[columns]\n"speed [km/h]" = {u}\n'
    elif kind == "mcap":
        text = f'[topics."/vehicle/speed"]\nspeed = {u}\n'
    else:
        text = f'[signals]\n"SPEED.SPEED" = {u}\n'
    log = folder / f"units_log.{EXT[kind]}"
    log.write_bytes(base.files[kind].read_bytes())
    p = folder / "units_map.toml"
    p.write_text(text, encoding="utf-8")
    return _map_reader(log, kind), p, (log,)


# --- compression ------------------------------------------------------------------------------------
#: Inflated sizes the bombs reach, bytes (zeros: cheap at any size; real records and noise are compressed
#: here, so they stay smaller).
BOMB_MAX = {"zeros": 8 << 30, "records": 64 << 20, "noise": 64 << 20}


def _zstd_zeros(size: int) -> bytes:
    """A zstd frame of ``size`` zero bytes made of 128-KiB RLE blocks (4 bytes each: 8 GiB in 262 kB)."""
    block = 1 << 17
    head = b"\x28\xb5\x2f\xfd" + bytes([0x00, 0x58])  # magic; no content size; a 2-MiB window
    sizes = [block] * (size // block) + ([size % block] if size % block or not size else [])
    out = bytearray(head)
    for k, s in enumerate(sizes):
        out += ((s << 3) | (1 << 1) | (k == len(sizes) - 1)).to_bytes(3, "little") + b"\x00"
    return bytes(out)


def _lz4_zeros(size: int) -> bytes:
    """An LZ4 frame of ``size`` zero bytes: one compressed 4-MiB block repeated (2 GiB in 8 MB)."""
    import lz4.block
    import lz4.frame

    head = lz4.frame.LZ4FrameCompressor(block_size=lz4.frame.BLOCKSIZE_MAX4MB, block_linked=False,
                                        content_checksum=False).begin()
    blk = lz4.block.compress(bytes(4 << 20), store_size=False)
    rest = lz4.block.compress(bytes(size % (4 << 20)), store_size=False) if size % (4 << 20) else b""
    out = bytearray(head)
    out += (len(blk).to_bytes(4, "little") + blk) * (size // (4 << 20))
    if rest:
        out += len(rest).to_bytes(4, "little") + rest
    return bytes(out + b"\x00\x00\x00\x00")


def _zlib_zeros(size: int) -> bytes:
    """A zlib stream of ``size`` zero bytes; above 4 MiB one 1-MiB deflate block repeated (1 GiB in 1 MB),
    with the right Adler-32 check."""
    import zlib

    if size < 4 << 20:
        return zlib.compress(bytes(size), 9)
    mib = 1 << 20
    z = bytes(mib)
    c = zlib.compressobj(9)
    first = c.compress(z) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(z) + c.flush(zlib.Z_FULL_FLUSH)
    n = size // mib
    rest = bytes(size - n * mib)
    tail = c.compress(rest) + c.flush()
    adler = ((size % 65521) << 16) | 1  # Adler-32 of zeros: the sum stays 1, the sum of sums counts the bytes
    return first + again * (n - 1) + tail[:-4] + adler.to_bytes(4, "big")


def _repeat_compress(codec: str, period: bytes, size: int) -> bytes:
    """``period`` repeated up to ``size`` bytes, compressed as a stream (never held whole)."""
    import zlib

    if codec == "zstd":
        import zstandard

        c = zstandard.ZstdCompressor(level=1).compressobj()
        feed, end = c.compress, c.flush
    elif codec == "lz4":
        import lz4.frame

        c = lz4.frame.LZ4FrameCompressor(block_linked=False)
        out0 = c.begin()
        feed, end = c.compress, c.flush
    else:
        c = zlib.compressobj(6)
        feed, end = c.compress, c.flush
    parts = [out0] if codec == "lz4" else []
    reps = max(1, (1 << 20) // max(len(period), 1))
    piece = period * reps
    left = size
    while left > 0:
        chunk = piece[:left]
        parts.append(feed(chunk))
        left -= len(chunk)
    parts.append(end())
    return b"".join(parts)


def _bomb_sizes(rng, kind: str) -> tuple[int, int]:
    """(inflated size, declared size): the declaration honest, smaller, larger, absent or absurd."""
    size = int(_log_uniform(rng, 1 << 10, BOMB_MAX[kind]))
    r = rng.random()
    if r < 0.3:
        declared = size
    elif r < 0.6:
        declared = int(rng.integers(0, size))
    elif r < 0.75:
        declared = size + int(_log_uniform(rng, 1, 1 << 34))
    elif r < 0.85:
        declared = 0
    else:
        declared = _pick(rng, ((1 << 32) - 1, 1 << 31, 8 << 30, (1 << 63) - 1, (1 << 64) - 1, 512 << 20))
    return size, declared


def _mcap_records(data: bytes):
    """(opcode, start, end) of each top-level MCAP record, up to the footer."""
    import struct

    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        out.append((op, pos, pos + 9 + length))
        if op == 2:
            break
        pos += 9 + length
    return out


def _mcap_inner_records(base) -> bytes:
    """A schema, a channel and some message records of the seed, as inside a chunk (the period of a bomb
    of real records)."""
    import struct

    def rec(op, body):
        return bytes([op]) + struct.pack("<Q", len(body)) + body

    def s(text: bytes):
        return struct.pack("<I", len(text)) + text

    schema = rec(3, struct.pack("<H", 1) + s(b"iptm.Sample") + s(b"jsonschema") + s(b"{}"))
    chan = rec(4, struct.pack("<HH", 1, 1) + s(b"/vehicle/speed") + s(b"json") + struct.pack("<I", 0))
    msgs = b"".join(rec(5, struct.pack("<HIQQ", 1, k, 10**18 + k * 10**8, 10**18 + k * 10**8)
                        + json.dumps({"speed": 10.0 + k % 7}).encode()) for k in range(64))
    return schema + chan + msgs


def _bomb_payload(rng, codec: str, base, inner: bytes):
    kind = _pick(rng, ("zeros", "zeros", "records", "noise"))
    size, declared = _bomb_sizes(rng, kind)
    if kind == "zeros":
        if codec == "lz4":
            size = min(size, 2 << 30)
        elif codec == "zlib":
            size = min(size, 4 << 30)
        payload = {"zstd": _zstd_zeros, "lz4": _lz4_zeros, "zlib": _zlib_zeros}[codec](size)
    else:
        period = inner if kind == "records" else rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
        payload = _repeat_compress(codec, period, size)
    return payload, size, declared, kind


def _compression_mcap(codec: str):
    def make(rng, base, folder):
        import struct

        data = base.mcap
        recs = _mcap_records(data)
        spots = [a for op, a, _ in recs if op in (6, 0x0F, 3, 4, 0x0C)] or [8]
        inner = _mcap_inner_records(base)
        bombs = []
        for _ in range(int(rng.integers(1, 4))):
            payload, size, declared, kind = _bomb_payload(rng, codec, base, inner)
            label = codec if rng.random() < 0.85 else _pick(rng, ("zstd", "lz4", "", "bz2", "zstd" * 100))
            crc = 0 if rng.random() < 0.5 else int(rng.integers(0, 1 << 32))
            clen = len(payload) if rng.random() < 0.85 else int(_log_uniform(rng, 1, 1 << 63))
            body = (struct.pack("<QQQI", 10**18, 10**18 + 8 * 10**9, declared, crc)
                    + struct.pack("<I", len(label)) + label.encode() + struct.pack("<Q", clen) + payload)
            bombs.append((int(_pick(rng, spots)), bytes([6]) + struct.pack("<Q", len(body)) + body))
        out = bytearray(data)
        for at, bomb in sorted(bombs, key=lambda b: -b[0]):
            out[at:at] = bomb
        p = folder / f"bomb_{codec}.mcap"
        p.write_bytes(bytes(out))
        return _log_reader("mcap"), p, ()
    return make


def _blf_objects(data: bytes):
    """Byte offsets of the top-level objects of a BLF file."""
    import struct

    hsize = struct.unpack_from("<L", data, 4)[0]
    pos, out = hsize, []
    while pos + 16 <= len(data):
        size = struct.unpack_from("<L", data, pos + 8)[0]
        if size < 16:
            break
        out.append(pos)
        pos += size + size % 4
    return out


def _blf_container(payload: bytes, declared: int, method: int = 2) -> bytes:
    import struct

    obj_size = 32 + len(payload)
    return (struct.pack("<4sHHLL", b"LOBJ", 16, 1, obj_size & 0xFFFFFFFF, 10)
            + struct.pack("<H6xL4x", method, declared & 0xFFFFFFFF) + payload + b"\x00" * (obj_size % 4))


def _blf_inner_objects(data: bytes) -> bytes:
    """The uncompressed content of the first container of a BLF (CAN message objects)."""
    import struct
    import zlib

    for at in _blf_objects(data):
        if struct.unpack_from("<L", data, at + 12)[0] == 10:
            size = struct.unpack_from("<L", data, at + 8)[0]
            method = struct.unpack_from("<H", data, at + 16)[0]
            raw = data[at + 32:at + size]
            return zlib.decompress(raw) if method == 2 else raw
    return b""


def _compression_blf(rng, base, folder):
    import struct

    data = bytearray(base.blf)
    objs = _blf_objects(bytes(data))
    inner = _blf_inner_objects(base.blf)
    bombs = []
    for _ in range(int(rng.integers(1, 4))):
        payload, size, declared, kind = _bomb_payload(rng, "zlib", base, inner)
        method = 2 if rng.random() < 0.9 else _pick(rng, (0, 1, 3, 65535))
        bombs.append((int(_pick(rng, objs + [len(data)])), _blf_container(payload, min(declared, (1 << 32) - 1), method)))
    for at, bomb in sorted(bombs, key=lambda b: -b[0]):
        data[at:at] = bomb
    if rng.random() < 0.8:
        struct.pack_into("<Q", data, 16, len(data))  # the header's file size
    p = folder / "bomb.blf"
    p.write_bytes(bytes(data))
    return _log_reader("blf"), p, ()


# --- nesting ----------------------------------------------------------------------------------------
def _write_mcap_raw(path: Path, messages, compression: str = "zstd") -> None:
    """MCAP of (topic, log time ns, JSON bytes) messages, one channel per topic."""
    from mcap.writer import CompressionType, Writer

    kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}[compression]
    with open(path, "wb") as fh:
        w = Writer(fh, compression=kind)
        w.start(profile="", library="iptm-fuzz")
        ids = {}
        for topic, t_ns, data in messages:
            if topic not in ids:
                ids[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=0)
            w.add_message(ids[topic], log_time=t_ns, data=data, publish_time=t_ns)
        w.finish()


def _deep_json(rng, value: str = "1.0", most: int = 4_000_000) -> bytes:
    d = min(int(_log_uniform(rng, 1, 1_000_000)), max(most // 4, 1))
    kind = _pick(rng, ("array", "object", "mixed", "unbalanced", "in_string", "wide"))
    if kind == "array":
        return ("[" * d + value + "]" * d).encode()
    if kind == "object":
        return ('{"a": ' * d + value + "}" * d).encode()
    if kind == "mixed":
        return ('[{"a": ' * (d // 2) + value + "}]" * (d // 2)).encode()
    if kind == "unbalanced":
        return ("[" * d + value + "]" * int(rng.integers(0, d + 1))).encode()
    if kind == "in_string":
        return ('{"s": "' + "[" * d + '", "v": ' + value + "}").encode()
    return ("[" + ",".join(["[]"] * d) + "]").encode()


#: Bytes of deep JSON one generated MCAP holds at most (the messages are deep, the file stays small).
DEEP_BYTES = 4 << 20


def _nesting_mcap(rng, base, folder):
    msgs = []
    deep_share = _log_uniform(rng, 1e-3, 1.0)
    left = DEEP_BYTES
    for topic, t_ns, d in base.messages:
        data = json.dumps(d).encode()
        if rng.random() < deep_share and left > 0:
            fld = _pick(rng, list(d))
            inner = _deep_json(rng, repr(float(d[fld])), left)
            left -= len(inner)
            data = ('{"' + fld + '": ').encode() + inner + b"}" if rng.random() < 0.7 else inner
        msgs.append((topic, t_ns, data))
    tmap = None
    if rng.random() < 0.3:  # a map that reaches deep into the messages
        tmap = {"/vehicle/speed": {".".join(["a"] * int(_log_uniform(rng, 1, 100_000))): "speed_mps [m/s]"}}
    p = folder / "deep.mcap"
    _write_mcap_raw(p, msgs, _pick(rng, ("zstd", "lz4", "")))
    return _log_reader("mcap", topic_map=tmap), p, ()


def _nesting_toml(kind: str):
    def make(rng, base, folder):
        deep = _deep_toml(rng)
        if kind == "params":
            name = _pick(rng, base.params.names())
            key = _pick(rng, ("value", "bounds", "prior_sd", "x", "unit", "note", "stderr"))
            text = f"[parameters.{name}]\n{key} = {deep}\n"
            if key != "value":
                text += f"value = {base.params.param(name).value!r}\n"
            fn = _params_reader
        elif kind == "scenario":
            sec = _pick(rng, ("scenario", "grids", "run"))
            key = _pick(rng, {"scenario": ("T_amb", "duration_s", "cycle", "soc0"), "grids": ("soc", "tcl"),
                              "run": ("strategies",)}[sec])
            text = f"[{sec}]\n{key} = {deep}\n"
            fn = _scenario_reader
        elif kind == "study":
            sec = _pick(rng, ("study", "scenario", "vary", "params"))
            key = _pick(rng, ("name", "strategies", "grids", "T_amb", "files", "montecarlo"))
            text = f"[{sec}]\n{key} = {deep}\n"
            fn = _study_reader
        else:
            text = f"[columns]\n\"speed [km/h]\" = {deep}\n"
            log = folder / "deep_log.csv"
            log.write_text(base.text["csv"])
            p = folder / "deep_map.toml"
            p.write_text(text)
            return _map_reader(log, "csv"), p, (log,)
        p = folder / f"deep_{kind}.toml"
        p.write_text(text)
        return fn, p, ()
    return make


# --- CAN identity -----------------------------------------------------------------------------------
_ODD_BUSES = ("", " ", "can0 ", "vcan-\u00fc", "x" * 300, "1", "0", "-1", "can\x00", "\U0001d520an", "../etc",
              "#", "(", "can0#123", "CAN0", "can00", "99999", "4294967296", "nan", "can0\tcan1")
#: CAN IDs beyond and at the edges of the standard and extended ranges, and the OBD-II ones.
ODD_IDS = (0, 1, 0x7FF, 0x800, 0xFFF, 0x1FFFFFFF, 0x20000000, 0x7FFFFFFF, 0xFFFFFFFF, 1 << 32, 0x7DF, 0x7E8,
           0x7EF, 0x7F0, 0x18DAF110, 0x18DB33F1, 0xB4, 0x3B, 0x1C4, 0x6FF)


def _can_frames(rng, base):
    """Frames of the seed drive with CAN identities made hostile: (t, bus, id, extended, data, dlc) lists."""
    fr = base.frames
    n = len(fr["t"])
    t = [float(x) for x in fr["t"]]
    ids = [int(x) for x in fr["id"]]
    ext = [i > 0x7FF for i in ids]
    data = [bytes(fr["data"][k, :fr["dlc"][k]]) for k in range(n)]
    dlc = [len(d) for d in data]
    bus = ["can0"] * n
    for op in rng.choice(("extended", "standard", "buses", "odd_bus", "ids", "dlc", "dup", "obd"),
                         size=int(rng.integers(1, 5))):
        sel = np.flatnonzero(rng.random(n) < _log_uniform(rng, 0.01, 1.0)).tolist()
        if op == "extended":  # the DBC's IDs as 29-bit IDs of the same value
            for k in sel:
                ext[k] = True
        elif op == "standard":
            for k in sel:
                ids[k] &= 0x7FF
                ext[k] = False
        elif op == "buses":
            m = int(_log_uniform(rng, 2, 5000))
            names = [f"can{j}" for j in range(m)]
            for k in sel:
                bus[k] = _pick(rng, names)
        elif op == "odd_bus":
            name = _pick(rng, _ODD_BUSES)
            for k in sel:
                bus[k] = name
        elif op == "ids":
            for k in sel:
                ids[k] = int(_pick(rng, ODD_IDS)) if rng.random() < 0.7 else int(rng.integers(0, 1 << 30))
                ext[k] = ids[k] > 0x7FF if rng.random() < 0.8 else not ext[k]
        elif op == "dlc":
            for k in sel:
                m = int(_pick(rng, (0, 1, 7, 8, 9, 12, 15, 16, 48, 64, 65)))
                data[k] = rng.integers(0, 256, m, dtype=np.uint8).tobytes()
                dlc[k] = m if rng.random() < 0.7 else int(rng.integers(0, 16))
        elif op == "dup":
            for k in sorted(sel, reverse=True):
                for lst in (t, ids, ext, data, dlc, bus):
                    lst.insert(k, lst[k])
            n = len(t)
        elif op == "obd":
            for k in sel:
                ids[k], ext[k] = int(_pick(rng, (0x7E8, 0x7E9, 0x7EF, 0x18DAF110))), False
                m = int(rng.integers(0, 9))
                data[k] = bytes([m & 15, 0x41, int(_pick(rng, (0x05, 0x0C, 0x0D, 0x10, 0x2F, 0x46, 0x5B, 0x5E,
                                                                 0x00, 0xFF)))]) + rng.integers(
                    0, 256, 5, dtype=np.uint8).tobytes()
                dlc[k] = 8
            ext = [e if i <= 0x7FF else True for i, e in zip(ids, ext)]
        n = len(t)
    return t, bus, ids, ext, data, dlc


def _can_case(fmt: str):
    def make(rng, base, folder):
        t, bus, ids, ext, data, dlc = _can_frames(rng, base)
        p = folder / f"can.{EXT[fmt]}"
        t0 = 1.7e9
        if fmt == "candump":
            lines = []
            for k in range(len(t)):
                idt = f"{ids[k]:08X}" if ext[k] else f"{ids[k]:03X}"
                lines.append(f"({t0 + t[k]:.6f}) {bus[k]} {idt}#{'#1' if len(data[k]) > 8 else ''}{data[k].hex().upper()}\n")
            p.write_text("".join(lines), encoding="utf-8", errors="surrogateescape")
        elif fmt == "asc":
            head = "".join(base.text["asc"].splitlines(keepends=True)[:5])
            lines = [head]
            names = {}
            for k in range(len(t)):
                ch = bus[k] if rng.random() < 0.1 else str(names.setdefault(bus[k], len(names) + 1))
                lines.append(f" {t[k]:.6f} {ch}  {ids[k]:X}{'x' if ext[k] else ''}             Rx   d {dlc[k]:x} "
                             f"{data[k].hex(' ').upper()}\n")
            lines.append("End TriggerBlock\n")
            p.write_text("".join(lines), encoding="utf-8", errors="surrogateescape")
        elif fmt == "trc":
            head = "".join(ln for ln in base.text["trc"].splitlines(keepends=True) if ln.startswith(";"))
            lines = [head]
            names = {}
            for k in range(len(t)):
                ch = bus[k] if rng.random() < 0.1 else str(names.setdefault(bus[k], len(names) + 1))
                idt = f"{ids[k]:08X}" if ext[k] else f"{ids[k]:04X}"
                lines.append(f"{k:7d} {t[k] * 1000:13.3f} DT {ch:>2s} {idt:>8s} Rx -  {dlc[k]:<2d}   "
                             f"{data[k].hex(' ').upper()}\n")
            p.write_text("".join(lines), encoding="utf-8", errors="surrogateescape")
        else:
            import can

            names = {}
            with can.BLFWriter(str(p)) as w:
                for k in range(len(t)):
                    fd = len(data[k]) > 8
                    msg = can.Message(timestamp=t0 + t[k], arbitration_id=ids[k] & (0x1FFFFFFF if ext[k] else 0x7FFFFFFF),
                                      is_extended_id=ext[k], data=data[k][:64], is_fd=fd,
                                      dlc=len(data[k][:64]) if fd else min(dlc[k], 15),
                                      channel=names.setdefault(bus[k], len(names)) % 65535, check=False)
                    w.on_message_received(msg)
        used = sorted(set(bus))
        b = None if rng.random() < 0.7 else (_pick(rng, used) if rng.random() < 0.7 else _pick(rng, _ODD_BUSES))
        return _log_reader(fmt, bus=b), p, ()
    return make


# --- extreme numbers --------------------------------------------------------------------------------
def _number_text(rng) -> str:
    if rng.random() < 0.75:
        return _pick(rng, NUMBER_TEXTS)
    return repr(float(_pick(rng, (1e308, -1e308, 5e-324, -0.0, 2.0**63, 2.0**64, 1e19, 1e16, 1e-310))))


def _poison_text(rng, text: str, skip: str | None) -> str:
    """``text`` with some of its numbers (the first of a line half the time: a time stamp) replaced by
    :data:`NUMBER_TEXTS`."""
    import re

    num = re.compile(r"(?<![\w.#])[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?(?![\w.])")
    lines = text.split("\n")
    idx = [j for j, ln in enumerate(lines) if ln and not (skip and ln.startswith(skip)) and num.search(ln)]
    if not idx:
        return text
    for _ in range(int(_log_uniform(rng, 1, 2 * len(idx)))):
        j = int(_pick(rng, idx))
        ms = list(num.finditer(lines[j]))
        if not ms:  # its numbers already replaced by words
            continue
        m = ms[0] if rng.random() < 0.5 else _pick(rng, ms)
        lines[j] = lines[j][:m.start()] + _number_text(rng) + lines[j][m.end():]
    return "\n".join(lines)


def _numbers_text(fmt: str, skip: str | None):
    def make(rng, base, folder):
        p = folder / f"numbers.{EXT[fmt]}"
        p.write_text(_poison_text(rng, base.text[fmt], skip), encoding="utf-8")
        return _log_reader(fmt), p, ()
    return make


def _numbers_dbc(rng, base, folder):
    def edit(m, r):
        vals = [m.group(k) for k in (2, 3, 4, 5)]
        for k in r.choice(4, size=int(r.integers(1, 5)), replace=False):
            vals[k] = _number_text(r)
        return f'{m.group(1)}({vals[0]},{vals[1]}) [{vals[2]}|{vals[3]}] "{m.group(6)}"{m.group(7)}'

    dbc = folder / "numbers.dbc"
    dbc.write_text(_dbc_with(base, rng, edit), encoding="utf-8")
    p = folder / "numbers_dbc.log"
    p.write_text(base.text["candump"])
    return _log_reader("candump", dbc=dbc), p, (dbc,)


def _numbers_mcap(rng, base, folder):
    msgs = []
    share = _log_uniform(rng, 1e-3, 1.0)
    for topic, t_ns, d in base.messages:
        parts = []
        for f, v in d.items():
            parts.append(f'"{f}": {_number_text(rng) if rng.random() < share else repr(v)}')
        if rng.random() < share * 0.2:
            t_ns = int(_pick(rng, (0, 1, (1 << 64) - 1, 1 << 63, (1 << 63) - 1, t_ns - 10**12, t_ns + 10**18)))
        msgs.append((topic, t_ns, ("{" + ", ".join(parts) + "}").encode()))
    p = folder / "numbers.mcap"
    _write_mcap_raw(p, msgs, _pick(rng, ("zstd", "lz4", "")))
    return _log_reader("mcap"), p, ()


def _blf_edit_objects(data: bytes, edit) -> bytes:
    """A BLF with ``edit(bytearray)`` applied to the uncompressed content of each container (same length),
    the containers compressed again."""
    import struct
    import zlib

    hsize = struct.unpack_from("<L", data, 4)[0]
    out = bytearray(data[:hsize])
    for at in _blf_objects(data):
        size = struct.unpack_from("<L", data, at + 8)[0]
        obj = data[at:at + size + size % 4]
        if struct.unpack_from("<L", data, at + 12)[0] == 10 and struct.unpack_from("<H", data, at + 16)[0] == 2:
            inner = bytearray(zlib.decompress(data[at + 32:at + size]))
            edit(inner)
            obj = _blf_container(zlib.compress(bytes(inner)), len(inner))
        out += obj
    struct.pack_into("<Q", out, 16, len(out))
    return bytes(out)


def _numbers_blf(rng, base, folder):
    import struct

    def edit(inner: bytearray):
        pos = 0
        while True:
            pos = inner.find(b"LOBJ", pos)
            if pos < 0 or pos + 48 > len(inner):
                return
            if rng.random() < 0.3:
                what = int(rng.integers(4))
                if what == 0:  # the object's timestamp (ns or 10 us)
                    struct.pack_into("<Q", inner, pos + 24, int(_pick(rng, (0, (1 << 64) - 1, 1 << 63, 10**19,
                                                                            int(rng.integers(0, 1 << 63))))))
                elif what == 1:  # its flags: the time unit
                    struct.pack_into("<L", inner, pos + 16, int(_pick(rng, (0, 1, 2, 0xFFFFFFFF))))
                elif what == 2:  # the CAN ID field (with the extended flag bit)
                    struct.pack_into("<L", inner, pos + 36, int(_pick(rng, ODD_IDS + (0x80000000 | 0xB4,))) & 0xFFFFFFFF)
                else:  # the DLC
                    inner[pos + 35] = int(rng.integers(0, 256))
            pos += 4

    data = bytearray(_blf_edit_objects(base.blf, edit))
    if rng.random() < 0.3:  # the header's start and stop times (SYSTEMTIME: year, month, weekday, day, ...)
        for k in range(16):
            if rng.random() < 0.3:
                struct.pack_into("<H", data, 40 + 2 * k, int(_pick(rng, (0, 13, 32, 60, 1000, 65535))))
    p = folder / "numbers.blf"
    p.write_bytes(bytes(data))
    return _log_reader("blf"), p, ()


_FLOAT_EXTREMES = (1e308, -1e308, np.inf, -np.inf, np.nan, -0.0, 0.0, 5e-324, -5e-324, 2.2250738585072014e-308,
                   1e-320, 2.0**63, 2.0**64, 1e19, 3.4e38)


def _numbers_mf4(rng, base, folder):
    import asammdf

    from calib.ingest import HUMAN_NAME

    mdf = asammdf.MDF(version="4.10")
    share = _log_uniform(rng, 1e-3, 1.0)
    for ch, s in base.streams.items():
        v = s.to_numpy(float).copy()
        t = s.index.to_numpy(float).copy()
        unit = _channel_unit(ch)
        if unit == "dimensionless":  # written in % as loggers do (before the extremes: they stay as drawn)
            unit = "%"
            v = v * 100.0
        hit = rng.random(len(v)) < share
        v[hit] = rng.choice(_FLOAT_EXTREMES, size=int(hit.sum()))
        if rng.random() < 0.2:
            th = rng.random(len(t)) < share
            t[th] = rng.choice(_FLOAT_EXTREMES, size=int(th.sum()))
        mdf.append([asammdf.Signal(samples=v, timestamps=t, name=HUMAN_NAME.get(ch, ch), unit=unit)])
    p = folder / "numbers.mf4"
    mdf.save(p, overwrite=True)
    mdf.close()
    return _log_reader("mf4"), p, ()


def _numbers_params(rng, base, folder):
    lines = []
    for name in rng.choice(base.params.names(), size=int(rng.integers(1, 4)), replace=False):
        p = base.params.param(str(name))
        lines.append(f"[parameters.{name}]")
        if p.is_table:
            vals = [_toml_number(rng) if rng.random() < 0.3 else repr(float(v)) for v in p.value]
            lines.append(f"value = [{', '.join(vals)}]")
            if rng.random() < 0.3:
                lines.append(f"x = [{', '.join(_toml_number(rng) if rng.random() < 0.3 else repr(float(v)) for v in p.x)}]")
        else:
            lines.append(f"value = {_toml_number(rng) if rng.random() < 0.8 else repr(float(p.value))}")
        for key in ("bounds", "prior_sd", "stderr", "prior_value", "informed"):
            if rng.random() < 0.2:
                if key == "bounds":
                    lines.append(f"bounds = [{_toml_number(rng)}, {_toml_number(rng)}]")
                else:
                    lines.append(f"{key} = {_toml_number(rng)}")
    path = folder / "numbers_params.toml"
    path.write_text("\n".join(lines) + "\n")
    return _params_reader, path, ()


def _scenario_numeric_fields():
    from dataclasses import fields

    from optimize.formulations import DPScenario

    return [f.name for f in fields(DPScenario) if f.name not in ("cycle", "terminal", "cont_cycle")]


_SHORT_CYCLES = ('"nycc"', '"artemis_urban"', '"udds"')


def _numbers_scenario(rng, base, folder):
    lines = ["[scenario]", f"cycle = {_pick(rng, _SHORT_CYCLES)}"]
    names = _scenario_numeric_fields()
    chosen = set(rng.choice(names, size=int(rng.integers(1, 5)), replace=False).tolist())
    if "duration_s" not in chosen:
        lines.append(f"duration_s = {int(rng.integers(10, 61))}")
    for nm in chosen:
        lines.append(f"{nm} = {_toml_number(rng)}")
    lines.append("[grids]")
    for g in ("soc", "tcl", "tcab", "pbat", "qheat"):
        if rng.random() < 0.3:
            lines.append(f"{g} = {_toml_number(rng)}")
    lines += ["[run]", 'strategies = ["rule", "baseline", "thermal", "thermal_cabin"]']
    p = folder / "numbers_scenario.toml"
    p.write_text("\n".join(lines) + "\n")
    return _scenario_reader, p, ()


def _numbers_study(rng, base, folder):
    names = _scenario_numeric_fields()
    lines = ["[study]", 'strategies = ["rule", "baseline"]']
    if rng.random() < 0.3:
        lines.append(f"hold_s = {_toml_number(rng)}")
    if rng.random() < 0.3:
        lines.append(f"grids = {{soc = {_toml_number(rng)}}}")
    lines += ["[scenario]", f"cycle = {_pick(rng, _SHORT_CYCLES)}"]
    for nm in rng.choice(names, size=int(rng.integers(0, 4)), replace=False):
        lines.append(f"{nm} = {_toml_number(rng)}")
    lines.append("[vary]")
    for nm in rng.choice(names, size=int(rng.integers(1, 3)), replace=False):
        lines.append(f"{nm} = [{', '.join(_toml_number(rng) for _ in range(int(rng.integers(1, 5))))}]")
    p = folder / "numbers_study.toml"
    p.write_text("\n".join(lines) + "\n")
    return _study_reader, p, ()


# --- parameter and scenario fields ------------------------------------------------------------------
#: The cases of the hostile-input issue, among the random ones.
ISSUE_PARAMS = (
    "[parameters.m_kg]\nvalue = -1500\nbounds = [-1e9, 1e9]\n",
    "[parameters.C_bat_Ah]\nvalue = 1e300\nbounds = [-inf, inf]\n",
    "[parameters.C_bat_Ah]\nvalue = 0\n",
    "[parameters.C_bat_Ah]\nvalue = 0\nbounds = [0, 20]\n",
    "[parameters.eta_em]\nvalue = 0\nbounds = [0, 1]\n",
    "[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = -5\n",
    "[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = 0\n",
    "[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = nan\n",
    '[parameters.C_eng_J_per_K]\nvalue = 80000\nprior_sd = "abc"\n',
    '[parameters.m_kg]\nvalue = 1500\nunit = "kg**9**9**9"\n',
)
ISSUE_SCENARIOS = (
    "[scenario]\ncycle = \"nycc\"\nduration_s = nan\n",
    "[scenario]\ncycle = \"nycc\"\nduration_s = 20\nT_amb = nan\n",
    "[scenario]\ncycle = \"nycc\"\nduration_s = 20\n[grids]\nsoc = 1e-7\n",
    "[scenario]\ncycle = \"nycc\"\nduration_s = 20\nQ_heat_min = 2000\nQ_heat_max = 1000\n",
)
_PATHS = ('"/dev/null"', '"/"', '"."', '"nope.csv"', '"../../etc/passwd"', '"' + "x" * 5000 + '"', '"\\u0000"',
          '"from log"', '"nycc"', '"artemis_urban"', '"udds"', '"hwfet"', '"us06"', '"/dev/zero"')


def _fields_params(rng, base, folder):
    from calib.model import ENTRY_FIELDS

    if rng.random() < 0.1:
        text = _pick(rng, ISSUE_PARAMS)
    else:
        lines = []
        if rng.random() < 0.1:
            lines.append(f"meta = {_toml_value(rng, 0.2)}" if rng.random() < 0.5 else "[meta]\nname = 5")
        if rng.random() < 0.05:
            lines.append(f"parameters = {_toml_value(rng, 0.3)}")
        else:
            names = base.params.names() + ["m", "C_bat", "unknown", ""]
            for _ in range(int(rng.integers(1, 4))):
                name = _pick(rng, names)
                if rng.random() < 0.1:
                    lines.append(f'parameters.{_toml_str(name)} = {_toml_value(rng)}')
                    continue
                lines.append(f"[parameters.{_toml_str(name)}]")
                keys = list(rng.choice(ENTRY_FIELDS + ("junk",), size=int(rng.integers(1, 6)), replace=False))
                if "value" not in keys and rng.random() < 0.8:
                    keys.append("value")
                for k in keys:
                    lines.append(f"{k} = {_toml_value(rng, 0.6 if k in ('value', 'bounds', 'prior_sd') else 0.3)}")
        text = "\n".join(lines) + "\n"
    p = folder / "fields_params.toml"
    p.write_text(text, encoding="utf-8")
    return _params_reader, p, ()


def _grid_step(rng) -> str:
    if rng.random() < 0.6:
        return f"{_log_uniform(rng, 1e-9, 1e4):.3g}"
    return _toml_value(rng, 0.7)


def _fields_scenario(rng, base, folder):
    from dataclasses import fields

    from optimize.formulations import DPScenario

    if rng.random() < 0.1:
        text = _pick(rng, ISSUE_SCENARIOS)
    else:
        names = [f.name for f in fields(DPScenario)] + ["junk", "cycle_log"]
        lines = ["[scenario]"]
        sc = {}
        for nm in rng.choice(names, size=int(rng.integers(1, 6)), replace=False):
            if nm in ("cycle", "cont_cycle", "cycle_log"):
                sc[nm] = _pick(rng, _PATHS) if rng.random() < 0.5 else _toml_value(rng, 0.2)
            elif nm == "terminal":
                sc[nm] = _pick(rng, ('"free"', '"match"', '"valued"', '"continued"', '"x"', "1", "[]"))
            else:
                sc[nm] = _toml_value(rng)
        sc.setdefault("cycle", _pick(rng, _SHORT_CYCLES))
        if "duration_s" not in sc and rng.random() < 0.9:
            sc["duration_s"] = str(int(rng.integers(10, 61)))
        lines += [f"{k} = {v}" for k, v in sc.items()]
        if rng.random() < 0.7:
            lines.append("[grids]")
            for g in rng.choice(("soc", "tcl", "tcab", "pbat", "qheat", "junk"), size=int(rng.integers(1, 4)),
                                replace=False):
                lines.append(f"{g} = {_grid_step(rng)}")
        lines.append("[run]")
        strat = ('"rule"', '"baseline"', '"thermal"', '"thermal_cabin"', '"x"', "1", '""')
        lines.append("strategies = [" + ", ".join(_pick(rng, strat) for _ in range(int(rng.integers(0, 5)))) + "]"
                     if rng.random() < 0.9 else f"strategies = {_toml_value(rng, 0.3)}")
        if rng.random() < 0.05:
            lines.append(f"[{_pick(rng, ('junk', 'scenario.x', 'grids.soc'))}]")
        text = "\n".join(lines) + "\n"
    p = folder / "fields_scenario.toml"
    p.write_text(text, encoding="utf-8")
    return _scenario_reader, p, ()


def _fields_study(rng, base, folder):
    names = _scenario_numeric_fields()
    params_file = str(base.files["params"])
    lines = ["[study]"]
    for k in rng.choice(("name", "strategies", "reference", "grids", "hold_s", "junk"), size=int(rng.integers(0, 4)),
                        replace=False):
        v = {"strategies": '["rule", "baseline"]', "reference": '"rule"', "grids": "{soc = 0.02}"}.get(k)
        lines.append(f"{k} = {v if v and rng.random() < 0.5 else _toml_value(rng, 0.4)}")
    lines += ["[scenario]", f"cycle = {_pick(rng, _SHORT_CYCLES)}", "duration_s = 20"]
    for nm in rng.choice(names, size=int(rng.integers(0, 3)), replace=False):
        lines.append(f"{nm} = {_toml_value(rng)}")
    if rng.random() < 0.8:
        lines.append("[vary]")
        for nm in rng.choice(names + ["cycle", "junk"], size=int(rng.integers(1, 4)), replace=False):
            n = int(_log_uniform(rng, 1, 20_000))
            vals = ", ".join(_toml_number(rng) if rng.random() < 0.2 else f"{0.01 * k:g}" for k in range(n))
            lines.append(f"{nm} = [{vals}]" if rng.random() < 0.9 else f"{nm} = {_toml_value(rng, 0.3)}")
    if rng.random() < 0.3:
        files = _pick(rng, (f"{_toml_str(params_file)}", "[]", '"/dev/null"', '"/dev/zero"', '"nope.toml"', "5",
                            f"[{_toml_str(params_file)}, \"/\"]"))
        lines += ["[params]", f"files = {files}"]
        if rng.random() < 0.5:
            lines.append(f"montecarlo = {{artifact = {_toml_str(params_file)}, n = {_toml_number(rng)}}}")
    if rng.random() < 0.2:
        lines += ["[[case]]", f"{_pick(rng, names + ['junk'])} = {_toml_value(rng)}"]
    if rng.random() < 0.2:
        lines += ["[link]", f"{_pick(rng, names + ['junk'])} = {_toml_value(rng, 0.1)}"]
    p = folder / "fields_study.toml"
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return _study_reader, p, ()


#: generator -> {file kind: case maker (rng, base, folder) -> (reader, path, other files)}
GENERATORS = {
    "units": {"csv-header": _units_csv, "params-unit": _units_params, "dbc-unit": _units_dbc,
              "mcap-topic-map-unit": _units_mcap_map, "map-file-unit": _units_map_file},
    "compression": {"mcap-zstd": _compression_mcap("zstd"), "mcap-lz4": _compression_mcap("lz4"),
                    "blf-zlib": _compression_blf},
    "nesting": {"mcap-json": _nesting_mcap, "params-toml": _nesting_toml("params"),
                "scenario-toml": _nesting_toml("scenario"), "study-toml": _nesting_toml("study"),
                "map-file-toml": _nesting_toml("map")},
    "can": {"candump": _can_case("candump"), "asc": _can_case("asc"), "trc": _can_case("trc"),
            "blf": _can_case("blf")},
    "numbers": {"csv": _numbers_text("csv", "#"), "mcap": _numbers_mcap, "candump": _numbers_text("candump", "#"),
                "candump-dbc": _numbers_dbc, "asc": _numbers_text("asc", None), "trc": _numbers_text("trc", None),
                "blf": _numbers_blf, "mf4": _numbers_mf4, "params": _numbers_params, "scenario": _numbers_scenario,
                "study": _numbers_study},
    "fields": {"params": _fields_params, "scenario": _fields_scenario, "study": _fields_study},
}


def _generated_case(make, base, folder, seed, g, t, i):
    rng = np.random.default_rng([seed, g, t, i])
    return make(rng, base, folder)


@_in_folder
def generate(n: int = 10_000, seed: int = 0, generators=tuple(GENERATORS), folder=None, log=print,
             timeout=None) -> dict:
    """Counts per generator and file kind (see the module docstring): ``{generator: {kind: tally}}``."""
    import functools

    base = _Base(folder)
    if "mf4" not in base.files:
        log("numbers/mf4 skipped (asammdf is not installed)")
    base.warm()
    results = {}
    for g, (gname, targets) in enumerate(GENERATORS.items()):
        if gname not in generators and not any(x.startswith(gname + "/") for x in generators):
            continue
        results[gname] = {}
        for t, (tname, make) in enumerate(targets.items()):
            if tname == "mf4" and "mf4" not in base.files:
                continue
            if gname not in generators and f"{gname}/{tname}" not in generators:
                continue
            case_dir = folder / "cases" / gname / tname
            case_dir.mkdir(parents=True, exist_ok=True)
            case = functools.partial(_generated_case, make, base, case_dir, seed, g, t)
            results[gname][tname] = _run_cases(f"{gname}/{tname}", case, n, log, timeout)
    return results


def replay(label: str, case: int, seed: int = 0, folder=".") -> Path:
    """Write case ``case`` of ``generator/kind`` (e.g. ``units/csv-header``) into ``folder`` and read it
    here, in this process, so that an escape shows its whole traceback. Returns the input's path."""
    gname, _, tname = label.partition("/")
    g = list(GENERATORS).index(gname)
    t = list(GENERATORS[gname]).index(tname)
    folder = Path(folder)
    base = _Base(folder / "replay-base")
    fn, path, _ = _generated_case(GENERATORS[gname][tname], base, folder, seed, g, t, case)
    print(f"input: {path}")
    fn(path)
    return path


def rewrite_mcap(src, dst, compression: str) -> Path:
    """Copy an MCAP file with the ``mcap`` library, its chunks compressed with ``compression``."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    kind = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "": CompressionType.NONE}[compression]
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        reader = make_reader(fin)
        w = Writer(fout, compression=kind)
        w.start()
        schemas, channels = {}, {}
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if channel.id not in channels:
                sid = 0
                if schema is not None:
                    if schema.id not in schemas:
                        schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                    sid = schemas[schema.id]
                channels[channel.id] = w.register_channel(channel.topic, channel.message_encoding, sid,
                                                          channel.metadata)
            w.add_message(channels[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        for md in reader.iter_metadata():
            w.add_metadata(md.name, md.metadata)
        w.finish()
    return Path(dst)


def _ext_length(nibble: int, comp: bytes, i: int) -> tuple[int, int]:
    """An LZ4 length from its token nibble and, when that is 15, the extension bytes (255 continues);
    written here from the LZ4 block format, apart from the reader's, for an independent reference."""
    if nibble == 15:
        while True:
            nibble += comp[i]
            i += 1
            if comp[i - 1] != 255:
                break
    return nibble, i


def _lz4_progress(comp: bytes) -> tuple[list[int], list[int]]:
    """(compressed bytes in, bytes decodable) through an LZ4 frame, for ``np.interp(out, d, e)``.

    An LZ4 block is a run of sequences (token, literals, offset, match), each decodable once its bytes are
    in; a literal run gives its bytes one by one. Only the lengths are parsed, nothing is decoded.
    """
    e_pts, d_pts = [0], [0]
    flg = comp[4]
    p = 7 + (8 if flg & 0x08 else 0) + (4 if flg & 0x01 else 0)
    block_sum = 4 if flg & 0x10 else 0
    out = 0
    while p + 4 <= len(comp):
        size = int.from_bytes(comp[p:p + 4], "little")
        if size == 0:
            break
        raw, size = bool(size & 0x80000000), size & 0x7FFFFFFF
        a, b = p + 4, p + 4 + size
        if raw:
            e_pts += [a, b]
            d_pts += [out, out + size]
            out += size
        else:
            i = a
            while i < b:
                token = comp[i]
                i += 1
                lit, i = _ext_length(token >> 4, comp, i)
                e_pts += [i, i + lit]
                d_pts += [out, out + lit]
                i += lit
                out += lit
                if i >= b:
                    break  # the last sequence has literals only
                i += 2
                ml, i = _ext_length(token & 15, comp, i)
                # the match's bytes all need its last length byte: a step, not a slope
                e_pts += [i, i]
                d_pts += [out + 1e-6, out + ml + 4]
                out += ml + 4
        p = b + block_sum
    keep = [0] + [k for k in range(1, len(d_pts)) if d_pts[k] > d_pts[k - 1]]  # first input giving an output
    return [e_pts[k] for k in keep], [d_pts[k] for k in keep]


def mcap_message_positions(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(file position, log time in s) of every message of an intact MCAP, in file order.

    The position is where the message's record ends in the file. Inside a compressed chunk it is placed by
    the codec's progress. zstd: the compressed data is fed to a streaming decompressor 64 bytes at a time,
    which gives (compressed bytes in, bytes out) where output appears (each block end), and a message
    between two such points is placed linearly between them, so a reader that cannot decode the last,
    incomplete block is counted as losing the messages that block holds before the cut. LZ4: the exact
    point where each byte becomes decodable, from the sequence lengths (:func:`_lz4_progress`). Read with
    the ``mcap`` library's summary and the codecs, not with the reader.
    """
    import struct

    import zstandard
    from mcap.reader import make_reader

    summary = make_reader(io.BytesIO(data)).get_summary()
    pos, times = [], []
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        c1 = ci.chunk_start_offset + ci.chunk_length
        c0 = c1 - ci.compressed_size
        comp = data[c0:c1]
        if ci.compression == "zstd":
            d = zstandard.ZstdDecompressor().decompressobj()
        else:
            d = None
        if ci.compression == "lz4":
            import lz4.frame

            raw = lz4.frame.decompress(comp)
            e_pts, d_pts = _lz4_progress(comp)
        elif d is None:
            raw, e_pts, d_pts = comp, [0, len(comp)], [0, len(comp)]
        else:
            parts, e_pts, d_pts, got = [], [0], [0], 0
            for i in range(0, len(comp), 64):
                out = d.decompress(comp[i:i + 64])
                if out:
                    got += len(out)
                    parts.append(out)
                    e_pts.append(min(i + 64, len(comp)))
                    d_pts.append(got)
            raw = b"".join(parts)
        q, ends = 0, []
        while q + 9 <= len(raw):
            op, length = raw[q], struct.unpack_from("<Q", raw, q + 1)[0]
            end = q + 9 + length
            if op == 5:  # message: channel id u16, sequence u32, log_time u64
                ends.append(end)
                times.append(struct.unpack_from("<Q", raw, q + 9 + 6)[0] * 1e-9)
            q = end
        pos.extend(c0 + np.interp(np.asarray(ends, float), np.asarray(d_pts, float), np.asarray(e_pts, float)))
    return np.asarray(pos), np.asarray(times)


@_in_folder
def truncation_check(n: int = 200, seed: int = 0, readers=LOG_READERS, folder=None, log=print) -> dict:
    """Random cuts of a valid 120-s log per format: read or recovered, nothing before the cut lost."""
    from calib import IptmError
    from calib.ingest import read_streams

    seeds = make_seed_files(folder / "seeds", duration_s=120.0, rate=10.0)
    cases = []  # (label, reader, seed file, rng key)
    for r, fmt in enumerate(LOG_READERS):
        if fmt in readers and fmt in seeds:
            cases.append((fmt, fmt, seeds[fmt], [seed, r]))
            if fmt == "mcap":  # the same messages in LZ4 chunks (what the reader can decode differs)
                lz4_path = rewrite_mcap(seeds[fmt], folder / "seeds" / "seed_lz4.mcap", "lz4")
                cases.append(("mcap-lz4", fmt, lz4_path, [seed, r, 1]))
    results = {}
    for name, fmt, seed_path, key in cases:
        data = seed_path.read_bytes()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref, _ = read_streams(seed_path, fmt=fmt)
        rng = np.random.default_rng(key)
        ok = lost = failed = 0
        kept = []
        # Where each message lies in the file (MCAP only): what a cut leaves before it, to count what the
        # reader did not give back of it. The line/object formats are read record by record.
        msg_pos = msg_t = None
        if fmt == "mcap":
            msg_pos, msg_t = mcap_message_positions(data)
            msg_t = msg_t - msg_t.min()
        whole_before = 0
        behind = []
        first_fail = ""
        path = folder / f"cut.{EXT[fmt]}"
        t0 = time.perf_counter()
        for _ in range(n):
            cut = int(rng.integers(int(0.1 * len(data)), len(data) + 1))
            path.write_bytes(data[:cut])
            with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
                warnings.simplefilter("ignore")
                try:
                    streams, meta = read_streams(path, fmt=fmt)
                except IptmError as exc:
                    failed += 1
                    first_fail = first_fail or f"cut at {cut} of {len(data)}: {str(exc)[:160]}"
                    if msg_pos is not None:
                        before = msg_t[msg_pos <= cut]
                        behind.append(float(before.max()) if len(before) else 0.0)
                        whole_before += not len(before)
                    continue
            t_end = (meta.damage or {}).get("last_time_s")
            if t_end is None:
                t_end = max(s.index[-1] for s in streams.values())
            same = set(streams) <= set(ref)
            for ch, s in streams.items():
                if not same:
                    break
                a, b = s[s.index <= t_end], ref[ch][ref[ch].index <= t_end]
                same = len(a) == len(b) and np.array_equal(a.to_numpy(), b.to_numpy())
            ok += same
            lost += not same
            if msg_pos is not None:
                before = msg_t[msg_pos <= cut]
                gap = max(0.0, float(before.max()) - t_end) if len(before) else 0.0
                behind.append(gap)
                whole_before += same and gap == 0.0
            kept.append(t_end / max(s_.index[-1] for s_ in ref.values()) / (cut / len(data)))
        wall = time.perf_counter() - t0
        results[name] = {"n": n, "read_or_recovered_whole": ok, "lost_before_cut": lost, "error": failed,
                         "median_time_kept_per_byte_kept": float(np.median(kept)) if kept else None,
                         "wall_s": wall, "first_failure": first_fail}
        if msg_pos is not None:
            b = np.asarray(behind)
            results[name].update({"nothing_lost_before_cut": whole_before,
                                  "time_lost_before_cut_s": {"median": float(np.median(b)),
                                                             "p90": float(np.quantile(b, 0.9)),
                                                             "max": float(b.max())}})
        log(f"{name:9s} cuts {n:5d}  read/recovered with nothing lost {ok:5d} ({100 * ok / n:5.1f} %)  "
            f"lost data before the cut {lost:4d}  error {failed:4d}  {wall:6.1f} s")
        if msg_pos is not None:
            tl = results[name]["time_lost_before_cut_s"]
            log(f"    every message before the cut read: {whole_before} ({100 * whole_before / n:5.1f} %); "
                f"log time lost before the cut: median {tl['median']:.2f} s, 90 % {tl['p90']:.2f} s, "
                f"max {tl['max']:.2f} s (of {msg_t.max():.0f} s)")
        if first_fail:
            log(f"    {first_fail}")
    return results




def _summary(res: dict, log=print) -> list[str]:
    """Print the failures first, then the table of every reader and file kind; returns the failures."""
    rows = []
    for name, r in res.get("mutations", {}).items():
        rows.append((f"mutated {name}", r))
    for g, kinds in res.get("generators", {}).items():
        for k, r in kinds.items():
            rows.append((f"{g}/{k}", r))
    failures = []
    for label, r in rows:
        for ex in r["examples"]:
            if ex["outcome"] in FAILURES:
                failures.append(f"{label} case {ex['case']} (and {ex['count'] - 1} more like it): {ex['outcome']}: "
                                f"{ex['detail']}")
    if failures:
        log(f"FAILURES ({sum(sum(r[o] for o in FAILURES) for _, r in rows)} inputs):")
        for f in failures:
            log("  " + f)
    log("")
    log(TABLE_HEAD)
    for label, r in rows:
        log(_line(label, r))
    if rows:
        tot = {k: sum(r[k] for _, r in rows) for k in ("n", "answered", "read", "recovered", "error", "unclear",
                                                       "escape", "hang", "printed", "wall_s")}
        tot.update(peak_mb=max(r["peak_mb"] for _, r in rows), added_mb=max(r["added_mb"] for _, r in rows),
                   slowest_s=max(r["slowest_s"] for _, r in rows))
        log(_line("all", tot))
    log(TABLE_NOTE)
    return failures


def run(quick: bool = False, n: int | None = None, seed: int = 0, readers=READERS, generators=tuple(GENERATORS),
        mutations: bool = True, truncation: bool = True, timeout: float | None = None, json_path=None) -> dict:
    """Entry point of ``iptm bench fuzz``: raises an IptmError after the table when an input escapes or hangs
    (``json_path``: the figures are written there first, failing or not)."""
    from calib import IptmError

    n = n or (300 if quick else 10_000)
    timeout = CASE_TIMEOUT_S if timeout is None else timeout
    print(f"fuzz: {n} inputs per reader and per generated file kind, seed {seed}, {timeout:g} s per input (cpu "
          f"count {os.cpu_count()}, load {os.getloadavg()[0]:.1f})")
    t0 = time.perf_counter()
    res = {}
    if mutations and readers:
        print(TABLE_HEAD)
        res["mutations"] = fuzz(n=n, seed=seed, readers=readers, timeout=timeout)
    if generators:
        print(TABLE_HEAD)
        res["generators"] = generate(n=n, seed=seed, generators=generators, timeout=timeout)
    if truncation and readers:
        n_cut = min(500, max(50, n // 20))
        print(f"truncation check: {n_cut} random cuts per log format")
        res["truncation"] = truncation_check(n=n_cut, seed=seed, readers=readers)
    res["wall_s"] = time.perf_counter() - t0
    print(f"\nsummary ({res['wall_s']:.0f} s in all):")
    failures = _summary(res)
    if json_path:
        from calib import write_json

        write_json(json_path, res)
    if failures:
        n_bad = sum(r[o] for part in (res.get("mutations", {}), *res.get("generators", {}).values())
                    for r in part.values() for o in FAILURES)
        raise IptmError(f"fuzz: {n_bad} inputs escaped, hung or could not be generated (listed above); replay a "
                        "generated case with python -m iptm.benchmarks.fuzz --replay GENERATOR/KIND:CASE")
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000, help="inputs per reader and per generated file kind")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--readers", default=",".join(READERS), help="readers of the mutations and truncations "
                                                                  "('' for none)")
    ap.add_argument("--generators", default=",".join(GENERATORS), help="structure-aware generators, or "
                    "single file kinds as GENERATOR/KIND (e.g. numbers/blf); '' for none")
    ap.add_argument("--no-mutations", action="store_true")
    ap.add_argument("--no-truncation", action="store_true")
    ap.add_argument("--timeout", type=float, default=CASE_TIMEOUT_S, help="seconds per input before it is a hang")
    ap.add_argument("--replay", metavar="GENERATOR/KIND:CASE", help="write one generated case here and read it "
                                                                    "in this process (full traceback)")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    if a.replay:
        label, _, case = a.replay.rpartition(":")
        replay(label, int(case), seed=a.seed, folder=tempfile.mkdtemp(prefix="iptm-fuzz-replay-"))
        return 0
    pick = lambda s, known: tuple(x for x in s.split(",") if x) if s else ()  # noqa: E731
    gens = pick(a.generators, GENERATORS)
    bad = [g for g in gens if g.partition("/")[0] not in GENERATORS
           or (g.partition("/")[2] and g.partition("/")[2] not in GENERATORS[g.partition("/")[0]])]
    bad += [r for r in pick(a.readers, READERS) if r not in READERS]
    if bad:
        ap.error(f"unknown generator or reader {bad[0]!r}: generators {', '.join(GENERATORS)}; readers "
                 f"{', '.join(READERS)}")
    from calib import IptmError

    try:
        run(n=a.n, seed=a.seed, readers=pick(a.readers, READERS), generators=gens, mutations=not a.no_mutations,
            truncation=not a.no_truncation, timeout=a.timeout, json_path=a.json)
    except IptmError as exc:
        print(f"error: {exc}")
        return 2
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
