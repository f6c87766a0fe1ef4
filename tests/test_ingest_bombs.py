"""Decompression bombs and deep nesting in logs: each is refused by name, the rest of the log is read, and
reading answers within 10 s and 500 MB above the process's baseline (measured in a child process).

The bombs are built here, in memory, from a known drive: zstd and LZ4 chunks that inflate far beyond the
size they declare, a chunk that truly declares 8 GiB, a JSON message nested 100,000 levels deep among
normal ones, and a BLF container whose zlib stream inflates to 1 GiB.
"""
import json
import os
import re
import struct
import subprocess
import sys
import warnings
import zlib
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from calib.errors import LogFormatError
from calib.ingest import read_streams
from calib.ingest.canreaders import Bad, RecoveringBLFReader
from testcars.fabricate import fabricate_streams
from calib.ingest.limits import MAX_INFLATE_MB, RAISE_HINT, json_too_deep, size_text
from calib.ingest.writers import write_streams

ROOT = Path(__file__).resolve().parents[1]
GiB = 1 << 30

# Reads a log in a child process: prints what was read, the seconds it took and the peak memory it added
# to a baseline taken after a read of the intact log (every module and allocator arena warmed up).
_PROBE = r"""
import json, resource, sys, time, warnings
warnings.simplefilter("ignore")
from calib.ingest import read_streams
from calib.ingest.canreaders import Bad, RecoveringBLFReader

def read(path):
    if path.endswith(".blf"):
        got = list(RecoveringBLFReader(path))
        bad = [str(x.err) for x in got if isinstance(x, Bad)]
        return {"frames": sum(not isinstance(x, Bad) for x in got), "bad": bad}
    s, m = read_streams(path)
    return {"counts": {c: m.channel_counts[c]["kept"] for c in s}, "damage": m.damage, "notes": m.notes}

read(sys.argv[2])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
try:
    out = read(sys.argv[1])
except Exception as exc:
    out = {"error": f"{type(exc).__name__}: {exc}"}
out["seconds"] = time.perf_counter() - t
out["extra_mb"] = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024
print(json.dumps(out))
"""


def _probe(bomb: Path, intact: Path, env=None) -> dict:
    run = subprocess.run([sys.executable, "-c", _PROBE, str(bomb), str(intact)], capture_output=True, text=True,
                         timeout=120, cwd=ROOT, env={**os.environ, **(env or {})})
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["seconds"] < 10, out
    assert out["extra_mb"] < 500, out
    return out


def zstd_rle_frame(size: int) -> bytes:
    """A zstd frame of ``size`` zero bytes, made of 128-KiB RLE blocks (4 bytes each: 1 GiB in 32 kB)."""
    block = 1 << 17
    n = size // block
    head = b"\x28\xb5\x2f\xfd" + bytes([0x00, 0x58])  # magic; no content size; a 2-MiB window
    body = (((block << 3) | (1 << 1)).to_bytes(3, "little") + b"\x00") * (n - 1)
    return head + body + (((block << 3) | (1 << 1) | 1).to_bytes(3, "little") + b"\x00")


def zlib_zeros(size_mib: int) -> bytes:
    """A zlib stream of ``size_mib`` MiB of zeros, built from one repeated 1-MiB deflate block (1 GiB in
    1 MB), with the right Adler-32 check."""
    z = bytes(1 << 20)
    c = zlib.compressobj(9)
    first = c.compress(z) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(z) + c.flush(zlib.Z_FULL_FLUSH)  # after a full flush, the same input packs the same
    tail = c.flush()[:-4]
    adler = 1
    for _ in range(size_mib):
        adler = zlib.adler32(z, adler)
    return first + again * (size_mib - 1) + tail + adler.to_bytes(4, "big")


def _records(data: bytes):
    """(opcode, start, end) of each top-level MCAP record."""
    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        out.append((op, pos, pos + 9 + length))
        if op == 2:  # footer
            break
        pos += 9 + length
    return out


def chunk_record(payload: bytes, declared: int, compression: str = "zstd", t_ns=(0, 0)) -> bytes:
    body = (struct.pack("<QQQI", t_ns[0], t_ns[1], declared, 0) + struct.pack("<I", len(compression))
            + compression.encode() + struct.pack("<Q", len(payload)) + payload)
    return bytes([6]) + struct.pack("<Q", len(body)) + body


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A known 300-s drive as MCAP (two zstd chunks), and what reading it gives."""
    streams, meta = fabricate_streams(300, seed=7)
    p = write_streams(streams, meta, tmp_path_factory.mktemp("drive") / "drive.mcap", "mcap")
    s, m = read_streams(p)
    assert not m.damage and sum(op == 6 for op, _, _ in _records(p.read_bytes())) == 2
    return p, s, m


def _with_bomb(drive_path: Path, bomb: bytes, dst: Path) -> tuple[Path, int]:
    """The drive with ``bomb`` (a chunk record) before its second chunk; returns the path and the bomb's byte."""
    data = drive_path.read_bytes()
    second = [a for op, a, _ in _records(data) if op == 6][1]
    dst.write_bytes(data[:second] + bomb + data[second:])
    return dst, second


def _same_as_intact(out: dict, m) -> None:
    assert out["counts"] == {c: v["kept"] for c, v in m.channel_counts.items()}


def test_zstd_chunk_that_inflates_past_its_declared_size(tmp_path, drive):
    src, s_ref, m_ref = drive
    frame = zstd_rle_frame(GiB)
    assert len(frame) < 33_000
    p, at = _with_bomb(src, chunk_record(frame, declared=4096, t_ns=(10**9, 2 * 10**9)), tmp_path / "b.mcap")
    out = _probe(p, src)
    _same_as_intact(out, m_ref)
    dmg = out["damage"]
    assert dmg["pieces_lost"] == 1 and dmg["where"] == [f"chunk at byte {at}"]
    assert list(dmg["problems"]) == ["inflates beyond its declared 4096 bytes (a decompression bomb or damage), "
                                     "dropped"]
    assert any(n.startswith(f"chunk at byte {at} (log time") for n in out["notes"])
    # in this process too: the values of every channel are those of the intact drive
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s, m = read_streams(p)
    assert any(f"chunk at byte {at}" in str(w.message) for w in caught)
    for ch in s_ref:
        np.testing.assert_array_equal(s[ch].to_numpy(), s_ref[ch].to_numpy())
    with pytest.raises(LogFormatError, match=rf"\(chunk at byte {at}\): inflates beyond its declared 4096 bytes \("):
        read_streams(p, strict=True)


def test_chunk_that_declares_8_gib_is_not_inflated(tmp_path, drive):
    src, _, m_ref = drive
    p, at = _with_bomb(src, chunk_record(zstd_rle_frame(8 * GiB), declared=8 * GiB), tmp_path / "b8.mcap")
    assert p.stat().st_size - src.stat().st_size < 270_000
    out = _probe(p, src)
    _same_as_intact(out, m_ref)
    dmg = out["damage"]
    assert dmg["where"] == [f"chunk at byte {at}"]
    note = [n for n in out["notes"] if n.startswith(f"chunk at byte {at}")]
    # the drive's first chunk was inflated before it
    first = [a for op, a, _ in _records(src.read_bytes()) if op == 6][0]
    left = (MAX_INFLATE_MB << 20) - struct.unpack_from("<Q", src.read_bytes(), first + 9 + 16)[0]
    problem = (f"declares 8 GiB, over the {size_text(left, down=True)} left of the {MAX_INFLATE_MB} MiB inflate "
               "budget (raise IPTM_MAX_INFLATE_MB)")
    assert "510.99 MiB left" in problem
    assert len(note) == 1 and note[0].endswith(f"it {problem} - {RAISE_HINT}")
    assert list(dmg["problems"]) == [problem]


def test_lz4_chunk_that_inflates_past_its_declared_size(tmp_path, drive):
    src, _, m_ref = drive
    frame = lz4.frame.compress(bytes(256 << 20))
    p, at = _with_bomb(src, chunk_record(frame, declared=1 << 20, compression="lz4"), tmp_path / "l.mcap")
    out = _probe(p, src)
    _same_as_intact(out, m_ref)
    assert out["damage"]["where"] == [f"chunk at byte {at}"]
    assert list(out["damage"]["problems"])[0].startswith("inflates beyond its declared 1 MiB (")
    # cut inside the bomb (a file that ends in it): the cut block is capped too
    cut = tmp_path / "lcut.mcap"
    cut.write_bytes(p.read_bytes()[:at + 9 + 60 + len(frame) // 2])
    out = _probe(cut, src)
    assert out["damage"]["where"][0] == f"chunk at byte {at}"


def test_budget_is_per_file_and_set_by_the_environment(tmp_path, drive):
    """A chunk of the intact drive (1 MiB) over a 0.5-MiB budget is refused by name; the other is read
    (the channel records lost with the first are taken from the file's summary section)."""
    src, _, m_ref = drive
    out = _probe(src, src, env={"IPTM_MAX_INFLATE_MB": "0.5"})
    first = [a for op, a, _ in _records(src.read_bytes()) if op == 6][0]
    assert out["damage"]["where"] == [f"chunk at byte {first}"]
    assert any(n.startswith(f"chunk at byte {first} (log time") and n.endswith(
        f"it declares 1.01 MiB, over the 524288 bytes inflate budget (raise IPTM_MAX_INFLATE_MB) - {RAISE_HINT}")
        for n in out["notes"])
    assert 0 < sum(out["counts"].values()) < sum(v["kept"] for v in m_ref.channel_counts.values())
    for bad in ("0", "-3", "lots", "nan"):
        run = subprocess.run([sys.executable, "-c", "import sys; from calib.ingest import read_streams; "
                              "read_streams(sys.argv[1])", str(src)], capture_output=True, text=True, timeout=120,
                             cwd=ROOT, env={**os.environ, "IPTM_MAX_INFLATE_MB": bad})
        assert run.returncode != 0
        assert f"IPTM_MAX_INFLATE_MB={bad!r} is not a positive number of MiB" in run.stderr


def deep_mcap(path, n: int = 1000) -> None:
    """``n`` messages on two topics in zstd chunks, message 500 of /vehicle/speed nested 100,000 levels deep."""
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start()
        c = w.register_channel(topic="/vehicle/speed", message_encoding="json", schema_id=0)
        e = w.register_channel(topic="/engine", message_encoding="json", schema_id=0)
        for k in range(n):
            ns = k * 10**8
            data = json.dumps({"speed": k / 100}).encode()
            if k == 500:
                data = b'{"speed": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
            w.add_message(c, log_time=ns, data=data, publish_time=ns)
            w.add_message(e, log_time=ns, data=json.dumps({"speed": 800.0 + k}).encode(), publish_time=ns)
        w.finish()


def test_deeply_nested_message_is_refused_alone(tmp_path):
    """One message nested 100,000 levels deep, in a zstd chunk among normal ones: only it is lost."""
    p = tmp_path / "deep.mcap"
    n = 1000
    deep_mcap(p, n)
    out = _probe(p, p)
    assert out["counts"] == {"speed_mps": n - 1, "engine_speed_rpm": n}
    assert out["damage"]["where"] == ["message 1001 on /vehicle/speed"]
    assert list(out["damage"]["problems"]) == ["nested deeper than 64 levels"]
    with pytest.raises(LogFormatError, match=r"\(message 1001 on /vehicle/speed\): nested deeper than 64 levels"):
        read_streams(p, strict=True)


def test_nesting_limit_is_64_levels(tmp_path):
    p = tmp_path / "n.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE)
        w.start()
        c = w.register_channel(topic="/obd", message_encoding="json", schema_id=0)
        for k, depth in enumerate((64, 65, 64)):
            obj = 5.0 + k
            for _ in range(depth):
                obj = {"x": obj}
            w.add_message(c, log_time=k * 10**9, data=json.dumps(obj).encode(), publish_time=0)
        w.finish()
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        s, m = read_streams(p, topic_map={"/obd": {".".join(["x"] * 64): "speed_mps [m/s]"}})
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), [5.0, 7.0])
    assert m.damage["where"] == ["message 2 on /obd"]
    assert json_too_deep(b'{"a": "[[[[' + b"[" * 100 + b'"}') is False  # brackets in a string do not nest
    assert json_too_deep(b'["\\\\"' + b"[" * 64 + b"]") is True  # an escaped backslash ends no string


def _blf_objects(data: bytes):
    hsize = struct.unpack_from("<L", data, 4)[0]
    pos, out = hsize, []
    while pos + 16 <= len(data):
        size = struct.unpack_from("<L", data, pos + 8)[0]
        out.append(pos)
        pos += size + size % 4
    return out


def _blf_container(payload: bytes, declared: int) -> bytes:
    obj_size = 16 + 16 + len(payload)
    obj = (struct.pack("<4sHHLL", b"LOBJ", 16, 1, obj_size, 10) + struct.pack("<H6xL4x", 2, declared)
           + payload)
    return obj + b"\x00" * (obj_size % 4)


@pytest.fixture(scope="module")
def blf(tmp_path_factory):
    """A BLF of 3,000 known frames in several containers, none cut across two (48-byte frame objects)."""
    import can

    p = tmp_path_factory.mktemp("blf") / "frames.blf"
    with can.BLFWriter(str(p), max_container_size=48 * 300) as w:
        for k in range(3000):
            w.on_message_received(can.Message(timestamp=1.0 + k / 100, arbitration_id=0x100 + k % 7,
                                              data=struct.pack("<Q", k), is_extended_id=False, channel=0))
    assert len(_blf_objects(p.read_bytes())) > 3
    return p


def _insert_blf(src: Path, obj: bytes, dst: Path) -> tuple[Path, int]:
    data = bytearray(src.read_bytes())
    at = _blf_objects(bytes(data))[2]
    data[at:at] = obj
    struct.pack_into("<Q", data, 16, len(data))  # the header's file size
    dst.write_bytes(bytes(data))
    return dst, at


def test_blf_zlib_bomb_is_refused_by_name(tmp_path, blf):
    p, at = _insert_blf(blf, _blf_container(zlib_zeros(1024), declared=128 * 1024), tmp_path / "z.blf")
    out = _probe(p, blf)
    assert out["frames"] == 3000
    assert len(out["bad"]) == 1
    assert (f"(bytes {at}-" in out["bad"][0] and f"container at byte {at} inflates beyond its declared 131072 bytes "
            "(a decompression bomb or damage), dropped" in out["bad"][0])
    # the frames after it are the ones written
    got = [x for x in RecoveringBLFReader(str(p)) if not isinstance(x, Bad)]
    assert [struct.unpack("<Q", bytes(x.data))[0] for x in got] == list(range(3000))


def test_blf_container_declaring_more_than_the_budget(tmp_path, blf):
    p, at = _insert_blf(blf, _blf_container(zlib_zeros(2), declared=(1 << 32) - 1), tmp_path / "d.blf")
    out = _probe(p, blf)
    assert out["frames"] == 3000 and len(out["bad"]) == 1
    # the containers before it inflated a few kB of the budget
    assert re.search(rf"container at byte {at} declares 4.00 GiB, over the {MAX_INFLATE_MB - 1}\.\d\d MiB left of "
                     rf"the {MAX_INFLATE_MB} MiB inflate budget \(raise IPTM_MAX_INFLATE_MB\)$", out["bad"][0])


def test_one_record_inflates_to_64_mib_at_most_unless_the_budget_is_set(tmp_path, drive, monkeypatch):
    """A chunk that honestly declares 200 MiB is within the 512-MiB file budget but over what one record may
    hold in memory: refused by name without being inflated; with the budget set, the user trusts the file."""
    from calib.ingest.limits import MAX_RECORD_MB, InflateBudget, InflateRefused

    monkeypatch.delenv("IPTM_MAX_INFLATE_MB", raising=False)
    b = InflateBudget(tmp_path / "x.mcap")
    with pytest.raises(InflateRefused, match=f"declares 200 MiB, more than the {MAX_RECORD_MB} MiB one record"):
        b.cap(200 << 20)
    assert b.cap(None) == MAX_RECORD_MB << 20 and b.cap(1 << 20) == 1 << 20
    monkeypatch.setenv("IPTM_MAX_INFLATE_MB", "1024")
    assert InflateBudget(tmp_path / "x.mcap").cap(200 << 20) == 200 << 20
