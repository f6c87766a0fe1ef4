"""Damaged logs: read up to the damage, lose nothing before it, say what was lost; strict refuses them."""
import io
import struct
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib.errors import LogDamageWarning, LogFormatError
from calib.ingest import read_log, read_streams

LOGS = Path(__file__).resolve().parents[1] / "logs"
DRIVE = "winter_warm_restart"


@pytest.fixture(scope="module")
def intact():
    """Streams of the bundled drive, per format (read once)."""
    cache = {}

    def get(ext):
        if ext not in cache:
            with warnings.catch_warnings():
                warnings.simplefilter("error", LogDamageWarning)  # the bundled files are intact
                cache[ext] = read_streams(LOGS / f"{DRIVE}.{ext}")
        return cache[ext]
    return get


def _read_damaged(path, **kw):
    with pytest.warns(LogDamageWarning) as rec:
        streams, meta = read_streams(path, **kw)
    assert len([w for w in rec if issubclass(w.category, LogDamageWarning)]) == 1  # one warning per log
    assert meta.damage and meta.damage["recovered"]
    return streams, meta


def _same_before(streams, ref, t_end):
    """Every channel equals the intact file's samples up to t_end (nothing before the damage lost)."""
    assert set(streams) == set(ref)
    for ch, s in streams.items():
        r = ref[ch][ref[ch].index <= t_end]
        a = s[s.index <= t_end]
        assert len(a) == len(r), ch
        np.testing.assert_array_equal(a.index.to_numpy(), r.index.to_numpy())
        np.testing.assert_array_equal(a.to_numpy(), r.to_numpy())


@pytest.mark.parametrize("ext,frac", [("mcap", 0.8), ("mcap", 0.45), ("blf", 0.63), ("log", 0.6), ("csv", 0.7)])
def test_truncated_drive_reads_to_the_cut(tmp_path, intact, ext, frac):
    src = LOGS / f"{DRIVE}.{ext}"
    data = src.read_bytes()
    p = tmp_path / f"cut.{ext}"
    p.write_bytes(data[: int(len(data) * frac)])
    streams, meta = _read_damaged(p)
    ref, ref_meta = intact(ext)
    t_last = meta.damage["last_time_s"]
    duration = max(s.index[-1] for s in ref.values())
    # Data is kept nearly to the cut (the byte fraction, less the summary/index bytes and a CSV/text row).
    assert t_last >= 0.8 * frac * duration, (t_last, duration)
    _same_before(streams, ref, t_last)
    assert "summary" in meta.damage and "after" in meta.damage["summary"]
    # The resampled table is the intact table up to the cut (the last, partly filled second excepted).
    log = read_log(p) if ext != "mcap" else None
    if log is not None:
        full = read_log(src)
        n = int(t_last) - 1
        pd.testing.assert_frame_equal(log.data.iloc[:n], full.data.iloc[:n], check_freq=False)
        assert "[RECOVERED]" in log.label()
    with pytest.raises(LogFormatError):
        read_streams(p, strict=True)


def test_truncated_mcap_as_in_the_field_report(tmp_path, intact):
    """An MCAP cut at 1.5 MB (a recorder killed mid-drive) was rejected whole."""
    p = tmp_path / "killed.mcap"
    p.write_bytes((LOGS / f"{DRIVE}.mcap").read_bytes()[:1_500_000])
    streams, meta = _read_damaged(p)
    assert meta.damage["last_time_s"] > 900
    _same_before(streams, intact("mcap")[0], meta.damage["last_time_s"])


def test_truncated_blf_of_each_bundled_drive(tmp_path):
    for src in sorted(LOGS.glob("winter_*.blf")):
        data = src.read_bytes()
        p = tmp_path / src.name
        p.write_bytes(data[: int(len(data) * 0.55)])
        streams, meta = _read_damaged(p)
        ref, _ = read_streams(src)
        _same_before(streams, ref, meta.damage["last_time_s"])
        assert meta.damage["truncated_at_byte"] is not None


def test_candump_cut_mid_line(tmp_path, intact):
    data = (LOGS / f"{DRIVE}.log").read_bytes()
    cut = int(len(data) * 0.6)
    cut = data.index(b"\n", cut) - 8  # inside the payload of a line
    p = tmp_path / "cut.log"
    p.write_bytes(data[:cut])
    streams, meta = _read_damaged(p)
    _same_before(streams, intact("log")[0], meta.damage["last_time_s"])


def _garble_line(data: bytes, frac: float) -> tuple[bytes, int]:
    """Replace the line at ``frac`` of the file with garbage; returns the data and its 1-based line number."""
    a = data.index(b"\n", int(len(data) * frac)) + 1
    b = data.index(b"\n", a)
    return data[:a] + b"\x8f#!garbled@@@," + b"\xff" * 7 + data[b:], data[:a].count(b"\n") + 1


@pytest.mark.parametrize("ext", ["csv", "log"])
def test_one_garbled_line_in_the_middle(tmp_path, intact, ext):
    src = LOGS / f"{DRIVE}.{ext}"
    data, lineno = _garble_line(src.read_bytes(), 0.5)
    p = tmp_path / f"garbled.{ext}"
    p.write_bytes(data)
    streams, meta = _read_damaged(p)
    assert meta.damage["pieces_lost"] == 1 and meta.damage["where"] == [f"line {lineno}"]
    assert f"line {lineno}" in meta.damage["summary"]
    ref, _ = intact(ext)
    # Every sample of the intact file is there but the garbled line's.
    n_lost = sum(len(ref[ch]) - len(streams[ch]) for ch in ref)
    assert 1 <= n_lost <= len(ref)  # one row (CSV) or one frame (candump)
    a, b = meta.damage["spans_s"][0]
    for ch in ref:
        keep = (ref[ch].index <= a + 1e-6) | (ref[ch].index >= b - 1e-6)  # stream times are rounded to 1 us
        np.testing.assert_array_equal(streams[ch].to_numpy(), ref[ch][keep].to_numpy())
    with pytest.raises(LogFormatError, match=f"line {lineno}"):
        read_streams(p, strict=True)


def test_garbled_timestamp_costs_one_frame_not_the_rest(tmp_path):
    lines = [f"({10 + i * 0.01:.6f}) can0 0B4#00000000000A6600" for i in range(200)]
    lines[100] = lines[100].replace("(11.", "(91.")  # a digit flipped: a jump of 80 s and back
    p = tmp_path / "t.log"
    p.write_text("\n".join(lines) + "\n")
    streams, meta = _read_damaged(p)
    assert len(streams["speed_mps"]) == 199
    assert meta.damage["where"] == ["line 101"]


def test_nothing_readable_is_an_error(tmp_path):
    p = tmp_path / "junk.log"
    p.write_text("not a candump line\n" * 50)
    with pytest.raises(LogFormatError, match="no CAN frames"):
        read_log(p)
    q = tmp_path / "junk.mcap"
    q.write_bytes((LOGS / f"{DRIVE}.mcap").read_bytes()[:300])
    with pytest.raises(LogFormatError):
        read_log(q)


def test_cli_ingest_reports_and_strict_refuses(tmp_path, capsys):
    from iptm.cli import main

    p = tmp_path / "cut.blf"
    data = (LOGS / f"{DRIVE}.blf").read_bytes()
    p.write_bytes(data[:300_000])
    assert main(["ingest", str(p), "--out", str(tmp_path / "o.parquet")]) == 0
    out = capsys.readouterr()
    assert "RECOVERED" in out.out and "iptm: warning:" in out.err
    assert main(["ingest", str(p), "--strict", "--out", str(tmp_path / "o2.parquet")]) == 2
    assert "truncated" in capsys.readouterr().err
    assert not (tmp_path / "o2.parquet").exists()


def test_library_chatter_is_reported_not_printed(tmp_path, capfd):
    """python-can logs "Unknown object header version" for a garbled BLF object: it becomes damage."""
    import struct

    import can

    p = tmp_path / "u.blf"
    with can.BLFWriter(str(p), compression_level=0) as w:  # uncompressed, so one object can be garbled
        for i in range(200):
            w.on_message_received(can.Message(timestamp=1000 + i * 0.01, arbitration_id=0xB4, is_extended_id=False,
                                              data=bytes.fromhex("00000000000A6600")))
    d = bytearray(p.read_bytes())
    k = d.find(b"LOBJ", d.find(b"LOBJ") + 4)  # the first frame inside the container
    k = d.find(b"LOBJ", k + 400)
    struct.pack_into("<H", d, k + 6, 2048)  # its header version
    p.write_bytes(bytes(d))
    streams, meta = _read_damaged(p)
    assert len(streams["speed_mps"]) == 199
    assert "Unknown object header version (2048)" in meta.damage["summary"]
    out = capfd.readouterr()
    assert "Unknown object" not in out.out + out.err
    with pytest.raises(LogFormatError, match="Unknown object header version"):
        read_streams(p, strict=True)


def test_strict_on_calibrate_and_run_refuses_a_damaged_log(tmp_path, capsys):
    from iptm.cli import main

    p = tmp_path / "cut.log"
    data = (LOGS / f"{DRIVE}.log").read_bytes()
    p.write_bytes(data[: len(data) // 2])
    assert main(["calibrate", str(p), "--strict", "--quiet", "--out", str(tmp_path / "c.toml")]) == 2
    assert "line cut short" in capsys.readouterr().err
    assert main(["run", str(p), "--strict", "--quiet", "--reports", str(tmp_path / "r"),
                 "--cache", str(tmp_path / "cache")]) == 2
    assert "line cut short" in capsys.readouterr().err
    assert not (tmp_path / "c.toml").exists()


@pytest.mark.timeout(60)
def test_blf_object_with_size_zero_does_not_hang(tmp_path):
    """python-can's own loop never moves past an object whose size field reads 0."""
    import struct

    import can

    p = tmp_path / "z.blf"
    with can.BLFWriter(str(p), compression_level=0) as w:
        for i in range(100):
            w.on_message_received(can.Message(timestamp=1000 + i * 0.01, arbitration_id=0xB4, is_extended_id=False,
                                              data=bytes.fromhex("00000000000A6600")))
    d = bytearray(p.read_bytes())
    k = d.find(b"LOBJ", d.find(b"LOBJ") + 4)
    k = d.find(b"LOBJ", k + 400)
    struct.pack_into("<HHL", d, k + 4, 32, 7, 0)  # unknown header version and size 0
    p.write_bytes(bytes(d))
    streams, meta = _read_damaged(p)
    assert len(streams["speed_mps"]) == 99


def _mcap_chunks(data: bytes):
    """The chunk indexes of an intact MCAP (the ``mcap`` library's summary), in file order."""
    from mcap.reader import make_reader

    summary = make_reader(io.BytesIO(data)).get_summary()
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset), summary.statistics


def _message_records(raw: bytes):
    """(record end offset, log time in s) of the message records in decompressed chunk data."""
    out, q = [], 0
    while q + 9 <= len(raw):
        op, length = raw[q], struct.unpack_from("<Q", raw, q + 1)[0]
        if op == 5:
            out.append((q + 9 + length, struct.unpack_from("<Q", raw, q + 9 + 6)[0] * 1e-9))
        q += 9 + length
    return out


def _rows(streams, t_end=np.inf):
    return sum(int((s.index <= t_end).sum()) for s in streams.values())


def test_mcap_cut_in_a_zstd_chunk_keeps_its_whole_blocks(tmp_path, intact):
    """The bundled drive (four zstd chunks of 1 MB) cut 60 % into its second chunk's compressed data.

    zstd decodes a block only whole, so the reader must give every record of the chunk's whole blocks (as
    zstandard's streaming decoder yields them) and lose only the cut block. Dropping the cut chunk whole
    would keep the first chunk's 20,728 samples (0-306 s); its whole blocks add 10,341 (to 459 s); the
    cut block's records before the cut (about 1,970 samples, 459-488 s) cannot be decoded.
    """
    import zstandard

    data = (LOGS / f"{DRIVE}.mcap").read_bytes()
    chunks, stats = _mcap_chunks(data)
    c = chunks[1]
    c1 = c.chunk_start_offset + c.chunk_length
    c0 = c1 - c.compressed_size
    cut = c0 + int(0.6 * c.compressed_size)
    p = tmp_path / "cut.mcap"
    p.write_bytes(data[:cut])
    streams, meta = _read_damaged(p)
    ref, _ = intact("mcap")
    t_last = meta.damage["last_time_s"]
    _same_before(streams, ref, t_last)

    full = zstandard.ZstdDecompressor().decompress(data[c0:c1], max_output_size=c.uncompressed_size)
    blocks = zstandard.ZstdDecompressor().decompressobj().decompress(data[c0:cut])
    assert full.startswith(blocks) and 0 < len(blocks) < len(full)
    t0 = stats.message_start_time * 1e-9
    in_blocks = [t for end, t in _message_records(full) if end <= len(blocks)]
    assert t_last == pytest.approx(max(in_blocks) - t0, abs=1e-6)

    t_chunk0 = chunks[0].message_end_time * 1e-9 - t0
    n_whole_chunk = _rows(ref, t_chunk0)
    n_read = _rows(streams)
    assert n_read > n_whole_chunk + 10_000, (n_read, n_whole_chunk)
    # The lost block is named: its bytes and the time from which nothing was read.
    assert c0 < meta.damage["truncated_at_byte"] < cut
    assert "zstd block" in meta.damage["summary"] and f"from byte {meta.damage['truncated_at_byte']}" in \
        ", ".join(meta.damage["where"])


def test_mcap_cut_in_an_lz4_chunk_reads_to_the_cut(tmp_path):
    """LZ4 sequences decode front to back, so a cut LZ4 chunk gives its records up to the cut itself.

    The bundled drive rewritten with LZ4 chunks by the ``mcap`` library; each cut falls inside an LZ4
    block, whose records ``lz4.frame`` alone would not give.
    """
    import lz4.frame

    from iptm.benchmarks.fuzz import mcap_message_positions, rewrite_mcap

    src = rewrite_mcap(LOGS / f"{DRIVE}.mcap", tmp_path / "lz4.mcap", "lz4")
    data = src.read_bytes()
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogDamageWarning)
        ref, _ = read_streams(src)
    chunks, stats = _mcap_chunks(data)
    assert {c.compression for c in chunks} == {"lz4"}
    t0 = stats.message_start_time * 1e-9
    pos, t_msg = mcap_message_positions(data)
    c = chunks[1]
    c1 = c.chunk_start_offset + c.chunk_length
    c0 = c1 - c.compressed_size
    full = lz4.frame.decompress(data[c0:c1])
    for frac in (0.13, 0.37, 0.61, 0.89):
        cut = c0 + int(frac * c.compressed_size)
        p = tmp_path / "cut.mcap"
        p.write_bytes(data[:cut])
        streams, meta = _read_damaged(p)
        t_last = meta.damage["last_time_s"]
        _same_before(streams, ref, t_last)
        whole_blocks = lz4.frame.LZ4FrameDecompressor().decompress(data[c0:cut])
        t_blocks = max(t for end, t in _message_records(full) if end <= len(whole_blocks)) - t0
        t_before = t_msg[pos <= cut].max() - t0  # the last message whose sequences all lie before the cut
        assert t_last > t_blocks + 1.0, (frac, t_last, t_blocks)
        assert t_last == pytest.approx(t_before, abs=1e-6), (frac, t_last, t_before)


def _mdf_blocks(data: bytes) -> dict:
    """address -> (block id, length, link count) of every MDF4 block reachable from the HD block."""
    out, todo = {}, [64]
    while todo:
        a = todo.pop()
        if a and a not in out:
            length, n_links = struct.unpack_from("<QQ", data, a + 8)
            out[a] = (data[a:a + 4], length, n_links)
            todo.extend(struct.unpack_from(f"<{n_links}Q", data, a + 24))
    return dict(sorted(out.items()))


def _streaming_layout(data: bytes) -> bytes:
    """The same MDF4 file with its data blocks moved after every definition block, links remapped.

    This is how a streaming logger lays a file out (definitions first, records appended at the end); asammdf
    itself writes the definitions after the data.
    """
    blocks = _mdf_blocks(data)
    is_data = {a: blocks[a][0] in (b"##DT", b"##DL", b"##DZ", b"##HL", b"##SD") for a in blocks}
    order = [a for a in blocks if not is_data[a]] + [a for a in blocks if is_data[a]]
    new, at = {}, 64
    for a in order:
        new[a] = at
        at += -(-blocks[a][1] // 8) * 8
    out = bytearray(data[:64])
    for a in order:
        _, length, n_links = blocks[a]
        blk = bytearray(data[a:a + length])
        for i in range(n_links):
            link = struct.unpack_from("<Q", blk, 24 + 8 * i)[0]
            if link:
                struct.pack_into("<Q", blk, 24 + 8 * i, new[link])
        out += blk + bytes(-length % 8)
    return bytes(out)


def _one_group_mf4(path):
    """A 120-s MDF4 file, one channel group (every channel on one time base), written by asammdf."""
    asammdf = pytest.importorskip("asammdf")
    from calib.drivelog import CHANNELS
    from calib.ingest.common import HUMAN_NAME
    from testcars.fabricate import fabricate_streams

    streams, _ = fabricate_streams(120.0, dropout=None, rates={c: 10.0 for c in (
        "speed_mps", "bat_current_A", "bat_voltage_V", "engine_speed_rpm", "fuel_rate_g_per_s")})
    t = np.arange(0.0, 119.0, 0.1)
    sigs = [asammdf.Signal(samples=np.interp(t, s.index.to_numpy(float), s.to_numpy(float)), timestamps=t,
                           name=HUMAN_NAME.get(ch, ch), unit=CHANNELS[ch][0])
            for ch, s in streams.items() if CHANNELS[ch][0] != "dimensionless"]
    mdf = asammdf.MDF(version="4.10")
    mdf.append(sigs)
    mdf.save(path, overwrite=True)
    mdf.close()
    return path


def test_cut_mdf4_with_definitions_first_reads_its_whole_records(tmp_path):
    """A streaming logger's layout (definitions, then records) cut short: every whole record is read."""
    asammdf = pytest.importorskip("asammdf")
    data = _streaming_layout(_one_group_mf4(tmp_path / "one.mf4").read_bytes())
    intact_path = tmp_path / "stream.mf4"
    intact_path.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogDamageWarning)
        ref, _ = read_streams(intact_path)
    with asammdf.MDF(str(intact_path)) as mdf:  # record size and data start, from asammdf
        cg = mdf.groups[0].channel_group
        record = cg.samples_byte_nr + cg.invalidation_bytes_nr
        n_all = cg.cycles_nr
    dt = [a for a, b in _mdf_blocks(data).items() if b[0] == b"##DT"]
    assert len(dt) == 1 and dt[0] > max(a for a, b in _mdf_blocks(data).items() if b[0] != b"##DT")
    for frac in (0.3, 0.77):
        cut = int(len(data) * frac)
        p = tmp_path / "cut.mf4"
        p.write_bytes(data[:cut])
        streams, meta = _read_damaged(p)
        n_whole = (cut - dt[0] - 24) // record  # whole records before the cut
        assert 0 < n_whole < n_all
        assert {len(s) for s in streams.values()} == {n_whole}
        _same_before(streams, ref, meta.damage["last_time_s"])
        assert meta.damage["truncated_at_byte"] == cut and "unfinalised" in meta.damage["summary"]
        with pytest.raises(LogFormatError, match="truncated"):
            read_streams(p, strict=True)


def test_cut_mdf4_written_by_asammdf_names_why_nothing_is_left(tmp_path):
    """asammdf writes the channel definitions after the data: a cut file's records cannot be decoded."""
    data = _one_group_mf4(tmp_path / "one.mf4").read_bytes()
    p = tmp_path / "cut.mf4"
    p.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(LogFormatError, match=r"channel definitions \(DG/CG/CN blocks\) lie after the cut"):
        read_streams(p)
