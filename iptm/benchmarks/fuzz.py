"""Fuzzing benchmark: mutated inputs to every reader; nothing but a clean IptmError may come out.

For each reader (the log formats CSV, MCAP, candump, ASC, BLF, TRC, MDF4, and the parameter, scenario
and study TOML files) a small valid file is written, then ``n`` mutated copies are read. A mutation is 1-4
edits drawn from bit flips, truncations, insertions of random bytes, deletions and duplications of a
stretch; case ``i`` of reader ``r`` uses ``numpy.random.default_rng([seed, r, i])``, so any case can be
replayed (``mutate(data, seed, r, i)``). Each read ends in one of:

- ``read``: read, no damage reported;
- ``recovered``: read, with a damage report (``LogMeta.damage``) and one LogDamageWarning;
- ``error``: a clean :class:`calib.errors.IptmError` (one line, naming the file);
- ``escape``: any other exception (a bug), a crash of the process (a compiled library reading past a
  buffer) or a read that does not end within ``CASE_TIMEOUT_S``, listed with its case number.

Reads run in a forked worker process, so a crash or a hang is counted as an escape of that case and the
run goes on with a fresh worker.

``printed`` counts reads that wrote anything to stdout/stderr or issued a foreign warning (a library
talking past the project's own reporting); ``unclear`` counts IptmErrors whose message is not one line
naming the file.

The truncation check (``n / 20`` cuts per format, 50 to 500) cuts a larger valid log of each format at a
uniformly random byte between 10 % and 100 % of its length and counts the cuts read or recovered with
every sample up to the recovered end time equal to the intact file's. For MCAP (its zstd seed, and the
same messages rewritten with LZ4 chunks, ``mcap-lz4``) it also counts the cuts after which every message
lying before the cut (:func:`mcap_message_positions`) was read, and the log time lost before the cut:
a zstd block decodes only whole, so a cut inside one loses the block's records before the cut.

Run: ``iptm bench fuzz`` (10,000 mutated inputs per reader; ``--quick``: 300) or
``python -m iptm.benchmarks.fuzz --n 200 --seed 1``.
"""
from __future__ import annotations

import argparse
import contextlib
import io
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
    from calib.ingest.fabricate import fabricate_streams

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

    from calib.drivelog import CHANNELS
    from calib.ingest.common import HUMAN_NAME

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
    from calib.model.params import default_parameters
    from calib.ingest.writers import write_streams

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
        from calib.model.params import ParameterSet

        return lambda path: (ParameterSet.load(path), {})[1]
    if name == "scenario":
        from iptm.pipeline import load_scenario

        return lambda path: (load_scenario(path), {})[1]
    if name == "study":
        from optimize.sweep import load_study

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


def classify(fn, path) -> tuple[str, str, bool]:
    """Read ``path``: (outcome, detail, printed) with outcome read/recovered/error/unclear/escape."""
    from calib.errors import IptmError, IptmWarning

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
            outcome = "error" if ("\n" not in msg and Path(path).name in msg) else "unclear"
            detail = msg[:200]
        except Exception as exc:  # noqa: BLE001 - this is what the harness looks for
            outcome = "escape"
            detail = f"{type(exc).__name__}: {str(exc)[:200]}"
    foreign = [w for w in caught if not issubclass(w.category, IptmWarning)]
    raw = fd_out()
    printed = bool(out.getvalue() or err.getvalue() or foreign or raw)
    if printed and not detail:
        detail = (out.getvalue() or err.getvalue() or raw or str(foreign[0].message))[:200]
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


#: A read that takes longer than this (s) is a hang: counted as an escape.
CASE_TIMEOUT_S = 120.0


def _serve(conn, fn, data, seed, r, path):
    """Worker loop: case number in, (outcome, detail, printed) out."""
    import faulthandler

    faulthandler.disable()  # a crash is reported by its exit code and case number (replay with ``mutate``)
    while True:
        i = conn.recv()
        if i is None:
            return
        path.write_bytes(mutate(data, seed, r, i))
        conn.send(classify(fn, path))


class _Worker:
    """A forked process that reads the mutated cases; restarted after a crash or a hang."""

    def __init__(self, fn, data, seed, r, path):
        self.args = (fn, data, seed, r, path)
        self.proc = None

    def _start(self):
        import multiprocessing as mp

        ctx = mp.get_context("fork")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, *self.args), daemon=True)
        self.proc.start()
        child.close()

    def run(self, i):
        if self.proc is None or not self.proc.is_alive():
            self._start()
        self.conn.send(i)
        try:
            if self.conn.poll(CASE_TIMEOUT_S):
                return self.conn.recv()
            detail = f"no result within {CASE_TIMEOUT_S:g} s (hang)"
        except (EOFError, ConnectionError):
            self.proc.join(5)
            detail = f"the reading process died (exit code {self.proc.exitcode})"
        self.close()
        return "escape", detail, False

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


@_in_folder
def fuzz(n: int = 10_000, seed: int = 0, readers=READERS, folder=None, log=print) -> dict:
    """Mutated-input counts per reader (see the module docstring)."""
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
        counts = dict.fromkeys(("read", "recovered", "error", "unclear", "escape", "printed"), 0)
        examples = []
        path = folder / f"case.{EXT[name]}"
        t0 = time.perf_counter()
        worker = _Worker(fn, data, seed, r, path)
        for i in range(n):
            outcome, detail, printed = worker.run(i)
            counts[outcome] += 1
            counts["printed"] += printed
            if (outcome in ("escape", "unclear") or printed) and len(examples) < 5:
                examples.append({"case": i, "outcome": outcome, "printed": printed, "detail": detail})
        worker.close()
        wall = time.perf_counter() - t0
        results[name] = {**counts, "n": n, "wall_s": wall, "examples": examples}
        log(f"{name:9s} n={n:6d}  read {counts['read']:6d}  recovered {counts['recovered']:6d}  "
            f"clean error {counts['error']:6d}  unclear {counts['unclear']:4d}  escape {counts['escape']:4d}  "
            f"printed {counts['printed']:4d}  {wall:7.1f} s")
        for ex in examples:
            log(f"    case {ex['case']}: {ex['outcome']}{' (printed)' if ex['printed'] else ''}: {ex['detail']}")
    return results


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
    from calib.errors import IptmError
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


def run(quick: bool = False, n: int | None = None, seed: int = 0, readers=READERS) -> dict:
    """Entry point of ``iptm bench fuzz``."""
    n = n or (300 if quick else 10_000)
    print(f"fuzz: {n} mutated inputs per reader, seed {seed} (cpu count {os.cpu_count()}, "
          f"load {os.getloadavg()[0]:.1f})")
    res = {"mutations": fuzz(n=n, seed=seed, readers=readers)}
    n_cut = min(500, max(50, n // 20))
    print(f"truncation check: {n_cut} random cuts per log format")
    res["truncation"] = truncation_check(n=n_cut, seed=seed, readers=readers)
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--readers", default=",".join(READERS))
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    res = run(n=a.n, seed=a.seed, readers=tuple(a.readers.split(",")))
    if a.json:
        from calib.fileio import write_json

        write_json(a.json, res)


if __name__ == "__main__":
    main()
