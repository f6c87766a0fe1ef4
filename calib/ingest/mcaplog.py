"""MCAP logs with JSON-encoded messages (the ``mcap`` package).

Timestamps are the messages' ``log_time`` (ns). The topic/field -> channel map is configuration:
``{topic: {field: "channel [unit]"}}`` (a dotted field reaches into nested objects). The default,
:data:`DEFAULT_TOPIC_MAP`, is the layout :mod:`calib.ingest.writers` produces; pass ``topic_map`` to read other
layouts (its topics replace the default's topics of the same name; other default topics stay).
Messages slightly out of log-time order are sorted and counted in ``meta.notes``.

A channel (one publisher of one topic with one schema) is the unit of identity: a topic map key
``"/engine"`` reads the one channel on that topic, and a topic published on several channels is refused
with their ids, schemas and message counts, never merged. ``"/engine#7"`` reads channel 7 of ``/engine``
only (and replaces the default map's ``/engine``). JSON numbers that are not finite (``NaN``,
``Infinity``, ``1e400``) are dropped and counted per channel in ``meta.channel_counts``.
Compressed chunks are inflated within the limits of :mod:`calib.ingest.limits`.
"""
from __future__ import annotations

import io
import json
import math
import mmap
import re
import struct
import zlib

import numpy as np
from mcap.data_stream import ReadDataStream

from calib.drivelog import LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.ingest.common import check_nonempty, make_series, parse_target, to_channel_unit
from calib.ingest.damage import Damage, quiet_libraries
from calib.ingest.limits import (
    MAX_NESTING,
    RAISE_HINT,
    InflateBudget,
    InflateRefused,
    Overflow,
    inflate_lz4_frame,
    inflate_zstd,
    json_too_deep,
)

#: Default topic -> field -> "channel [unit]" map (the layout the log writers produce).
DEFAULT_TOPIC_MAP: dict[str, dict[str, str]] = {
    "/vehicle/speed": {"speed": "speed_mps [m/s]"},
    "/vehicle/grade": {"grade": "grade_rad [rad]"},
    "/hv_battery": {
        "current": "bat_current_A [A]",
        "voltage": "bat_voltage_V [V]",
        "soc": "soc [%]",
        "temperature": "bat_temp_degC [degC]",
    },
    "/engine": {
        "speed": "engine_speed_rpm [rpm]",
        "torque": "engine_torque_Nm [N*m]",
        "fuel_rate": "fuel_rate_g_per_s [g/s]",
        "coolant_temp": "coolant_temp_degC [degC]",
        "bay_temp": "bay_temp_degC [degC]",
    },
    "/hvac": {
        "cabin_temp": "cabin_temp_degC [degC]",
        "vent_temp": "vent_temp_degC [degC]",
        "setpoint": "hvac_setpoint_degC [degC]",
        "heater_power": "heater_power_W [W]",
        "blower_flow": "blower_flow_kg_per_s [kg/s]",
    },
    "/environment": {"ambient_temp": "ambient_temp_degC [degC]"},
}

#: A log time stepping back by more than this is an error; smaller steps are sorted.
MAX_BACKSTEP_S = 1.0


_CHANNEL_KEY = re.compile(r"^(?P<topic>.+)#(?P<id>[0-9]{1,5})$")


def _resolve_map(path, topic_map):
    """(by topic, by (topic, channel id)): field -> (channel, unit) for each topic-map entry.

    A key ``topic#id`` reads that channel of the topic only; it replaces the default map's entry for the
    topic unless the given map also names the bare topic.
    """
    given = dict(topic_map or {})
    chosen = set()
    for key in given:
        m = _CHANNEL_KEY.match(str(key))
        if m:
            chosen.add(m["topic"])
    tmap = {k: dict(v) for k, v in DEFAULT_TOPIC_MAP.items() if k not in chosen}
    for topic, fields in given.items():
        if not isinstance(fields, dict):
            raise LogFormatError(path, f"topic map entry {topic!r} must be a table field -> 'channel [unit]'")
        tmap[topic] = dict(fields)
    by_topic, by_id = {}, {}
    for key, fields in tmap.items():
        out = {}
        for field, target in fields.items():
            ch, unit = parse_target(target, path, f"topic map {key} {field}")
            if unit is None:
                raise LogFormatError(path, f"topic map {key} {field}: no unit", hint="write 'channel [unit]'")
            out[field] = (ch, unit)
        m = _CHANNEL_KEY.match(str(key))
        if m:
            by_id[(m["topic"], int(m["id"]))] = out
        else:
            by_topic[key] = out
    return by_topic, by_id


def _get(obj, dotted: str):
    for part in dotted.split("."):
        if not isinstance(obj, dict) or part not in obj:
            return None
        obj = obj[part]
    return obj


_MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_METADATA, _OP_DATA_END = 0x0C, 0x0F
_KNOWN_OPS = set(range(1, 0x10))
_U64 = struct.Struct("<Q")
_MSG_HEAD = struct.Struct("<HIQQ")
_CHUNK_HEAD = struct.Struct("<QQQI")
# Where a chunk record's body would start, seen from its compression name (resynchronisation anchor).
_ANCHORS = {b"\x04\x00\x00\x00zstd": "zstd", b"\x03\x00\x00\x00lz4": "lz4"}


def _inflate_chunk(compression: str, b, cap: int):
    """Inflate a (possibly cut) chunk body as far as it goes, to at most ``cap`` bytes.

    zstd gives the output of every whole block (a compressed zstd block is decoded from both ends, so a
    cut one gives nothing); LZ4 gives every byte up to the cut (see :func:`_lz4_prefix`). Raises
    :class:`~calib.ingest.limits.Overflow` when the body holds more than ``cap`` bytes.
    """
    if compression == "":
        return bytes(b)
    if compression == "zstd":
        return inflate_zstd(b, cap)
    if compression == "lz4":
        return _lz4_prefix(b, cap)
    raise LogFormatError("", f"unsupported MCAP chunk compression {compression[:20]!r}")


def _zstd_whole_blocks_end(b) -> int | None:
    """Offset in a zstd frame (maybe cut short) where its last whole block ends; None if not one frame."""
    if len(b) < 6 or bytes(b[:4]) != b"\x28\xb5\x2f\xfd":
        return None
    fhd = b[4]
    single = bool(fhd & 0x20)
    fcs = (1 if single else 0, 2, 4, 8)[fhd >> 6]
    p = 5 + (0 if single else 1) + (0, 1, 2, 4)[fhd & 3] + fcs
    while p + 3 <= len(b):
        h = b[p] | (b[p + 1] << 8) | (b[p + 2] << 16)
        size = 1 if (h >> 1) & 3 == 1 else h >> 3  # an RLE block stores one byte
        if p + 3 + size > len(b):
            break
        p += 3 + size
        if h & 1:
            break
    return min(p, len(b))


def _lz4_length(nibble: int, src: bytes, i: int):
    """An LZ4 literal or match length: the token's nibble, extended by bytes while they are 255 when the
    nibble is 15. Returns (length, next index), or (None, i) when the block ends inside the extension."""
    if nibble != 15:
        return nibble, i
    n = len(src)
    while i < n:
        nibble += src[i]
        i += 1
        if src[i - 1] != 255:
            return nibble, i
    return None, i


def _lz4_block_prefix(src: bytes, out: bytearray, cap: int) -> None:
    """Append to ``out`` what an LZ4 block (maybe cut short) decodes to, up to its first missing byte.

    LZ4 sequences are read front to back (token, literals, offset, match), so a cut block still gives every
    sequence before the cut; ``out`` holds the frame's earlier output, which linked blocks refer back to.
    Raises :class:`~calib.ingest.limits.Overflow` before ``out`` would grow past ``cap`` bytes.
    """
    i, n = 0, len(src)
    while i < n:
        token = src[i]
        i += 1
        lit, i = _lz4_length(token >> 4, src, i)
        if lit is None:
            return
        if len(out) + min(lit, n - i) > cap:
            raise Overflow
        out += src[i:i + lit]  # a literal run cut short is still the right bytes
        i += lit
        if i + 2 > n:
            return
        off = src[i] | (src[i + 1] << 8)
        i += 2
        ml, i = _lz4_length(token & 15, src, i)
        if ml is None:
            return
        ml += 4
        if off == 0 or off > len(out):
            return  # not LZ4 any more (damage): stop at the last good byte
        if len(out) + ml > cap:
            raise Overflow
        start = len(out) - off
        if off >= ml:
            out += out[start:start + ml]
        else:  # an overlapping match repeats the last ``off`` bytes
            while ml > 0:
                k = min(ml, off)
                out += out[start:start + k]
                start += k
                ml -= k


def _lz4_prefix(b, cap: int) -> bytes:
    """Inflate an LZ4 frame (maybe cut short) to at most ``cap`` bytes: whole blocks by lz4.frame, then the
    cut block by hand."""
    b = bytes(b)
    try:
        whole, d = inflate_lz4_frame(b, cap)
    except RuntimeError:
        return b""  # damaged before the cut: the caller reports the chunk
    if d.eof or len(b) < 7 or b[:4] != b"\x04\x22\x4d\x18":
        return whole
    flg = b[4]
    block_sum = 4 if flg & 0x10 else 0
    p = 4 + 2 + (8 if flg & 0x08 else 0) + (4 if flg & 0x01 else 0) + 1  # magic, FLG, BD, size, dict id, HC
    while p + 4 <= len(b):  # skip the whole blocks (lz4.frame decoded them) to where the cut one starts
        size = int.from_bytes(b[p:p + 4], "little")
        if size == 0:
            return whole
        raw, size = bool(size & 0x80000000), size & 0x7FFFFFFF
        if p + 4 + size + block_sum > len(b):
            out = whole
            data = b[p + 4:p + 4 + size]
            if raw:
                if len(out) + len(data) > cap:
                    raise Overflow
                out += data
            else:
                _lz4_block_prefix(data, out, cap)
            return out
        p += 4 + size + block_sum
    return whole


class _McapScan:
    """Walk an MCAP file's records in order, keeping what can be trusted (see :func:`read_mcap_streams`)."""

    def __init__(self, path, buf, dmg: Damage, on_message, budget: InflateBudget):
        self.path = path
        self.buf = buf
        self.n = len(buf)
        self.dmg = dmg
        self.on_message = on_message  # (channel, log_time_s, data, index, scan) -> bool (a good message)
        self.budget = budget
        self.channels = {}
        self.schemas = {0: "no schema"}  # schema id -> name
        self.redefined: dict[int, str] = {}  # channel id defined again differently -> its topics
        self.refused: list[str] = []  # chunks not inflated, in full
        self.metadata = {}
        self.footer = False
        self.data_end = False  # the data section ended whole: a cut after it loses only the index
        self.cut_in_summary = False
        self.undecoded_from = None  # first byte of a cut chunk's compressed data that gave no records
        self.i = 0  # messages seen
        self.t_last = -math.inf  # last good message time, s (file clock)

    def bad(self, problem, where, byte_range=None, t_span=None):
        self.dmg.bad(LogFormatError(self.path, problem, where), None if t_span else self.t_last,
                     byte_range=byte_range, t_span=t_span)

    def preload_summary(self):
        """Take the schemas and channels of a whole file's summary section (which repeats them), so that the
        messages of a channel whose record was lost with a refused or damaged chunk are still read. A summary
        that fails its CRC adds nothing."""
        from mcap.records import Channel, Schema

        buf, n = self.buf, self.n
        f = n - 8 - 29  # the footer record: opcode, length 20, summary start, summary offset start, CRC
        if f < 8 or bytes(buf[n - 8:]) != _MAGIC or buf[f] != _OP_FOOTER or _U64.unpack_from(buf, f + 1)[0] != 20:
            return
        start = _U64.unpack_from(buf, f + 9)[0]
        crc = struct.unpack_from("<I", buf, f + 25)[0]
        if not 8 <= start < f or (crc and zlib.crc32(buf[start:f + 25]) != crc):
            return
        found_s, found_c = {}, {}
        pos = start
        try:
            while pos + 9 <= f:
                op, end = buf[pos], pos + 9 + _U64.unpack_from(buf, pos + 1)[0]
                if end > f:
                    return
                if op == _OP_SCHEMA:
                    s = Schema.read(ReadDataStream(io.BytesIO(bytes(buf[pos + 9:end]))))
                    found_s[s.id] = s.name or f"schema {s.id}"
                elif op == _OP_CHANNEL:
                    ch = Channel.read(ReadDataStream(io.BytesIO(bytes(buf[pos + 9:end]))))
                    found_c[ch.id] = ch
                pos = end
        except Exception:  # noqa: BLE001 - an unreadable summary adds nothing: the data section stands alone
            return
        self.schemas.update(found_s)
        self.channels.update(found_c)

    def run(self):
        buf, n = self.buf, self.n
        if bytes(buf[:8]) != _MAGIC:
            self.bad("bad MCAP magic", "byte 0", (0, 8))
        self.preload_summary()
        pos = 8
        ends_whole = bytes(buf[-8:]) == _MAGIC and n > 16
        while pos < n and not self.footer:
            if pos + 9 > n:
                if self.data_end and not self.dmg.strict:
                    self.cut_in_summary = True
                else:
                    self.dmg.truncated(pos, n, self.t_last, "file ends inside a record header")
                break
            op = buf[pos]
            length = _U64.unpack_from(buf, pos + 1)[0]
            body = pos + 9
            if op not in _KNOWN_OPS and op < 0x80 or length > n - body:
                if length > n - body and op == _OP_CHUNK and not ends_whole:
                    self._chunk(body, n, cut=True)
                    if self.undecoded_from is None:
                        self.dmg.truncated(n, None, self.t_last,
                                           f"file ends inside the chunk at byte {pos} (read up to the cut)")
                    else:
                        self.dmg.truncated(self.undecoded_from, n, self.t_last,
                                           f"file ends inside a zstd block of the chunk at byte {pos} "
                                           "(zstd decodes whole blocks only)")
                    break
                if not ends_whole and length > n - body and op in _KNOWN_OPS:
                    if self.data_end and not self.dmg.strict:
                        self.cut_in_summary = True
                    else:
                        self.dmg.truncated(pos, n, self.t_last, "file ends inside a record")
                    break
                nxt = self._resync(pos + 1)
                self.bad(f"garbled record header (opcode 0x{op:02X}, length {length})", f"byte {pos}",
                         (pos, nxt if nxt is not None else n))
                if nxt is None:
                    break
                pos = nxt
                continue
            end = body + length
            try:
                self._record(op, body, end)
            except LogFormatError:
                raise
            except Exception as exc:  # noqa: BLE001 - mcap record parsers raise struct/EndOfFile/Unicode errors
                self.bad(f"unreadable record (opcode 0x{op:02X}): {_why(exc)}", f"byte {pos}", (pos, end))
            pos = end
        return self

    def _resync(self, start):
        """Offset of the next plausible chunk record after ``start``, or None."""
        best = None
        for anchor in _ANCHORS:
            k = self.buf.find(anchor, start + 37)
            while k >= 0:
                cand = k - 37
                if self.buf[cand] == _OP_CHUNK:
                    length = _U64.unpack_from(self.buf, cand + 1)[0]
                    clen = len(anchor) - 4
                    data_len_at = cand + 9 + 28 + 4 + clen
                    if data_len_at + 8 <= self.n:
                        data_len = _U64.unpack_from(self.buf, data_len_at)[0]
                        if length == 28 + 4 + clen + 8 + data_len and cand + 9 + length <= self.n:
                            best = cand if best is None else min(best, cand)
                            break
                k = self.buf.find(anchor, k + 1)
        return best

    def _record(self, op, a, b):
        buf = self.buf
        if op == _OP_MESSAGE:
            self._message(a, b, f"byte {a - 9}")
        elif op == _OP_CHANNEL:
            self._channel(buf[a:b], f"byte {a - 9}")
        elif op == _OP_SCHEMA:
            self._schema(buf[a:b])
        elif op == _OP_CHUNK:
            self._chunk(a, b, cut=False)
        elif op == _OP_METADATA:
            from mcap.records import Metadata

            md = Metadata.read(ReadDataStream(io.BytesIO(bytes(buf[a:b]))))
            self.metadata[md.name] = dict(md.metadata)
        elif op == _OP_FOOTER:
            self.footer = True
        elif op == _OP_DATA_END:
            self.data_end = True

    def _schema(self, body):
        from mcap.records import Schema

        s = Schema.read(ReadDataStream(io.BytesIO(bytes(body))))
        self.schemas[s.id] = s.name or f"schema {s.id}"

    def _channel(self, body, where):
        """Keep a channel record. The summary section repeats each channel; a second record with the same
        id and another topic, encoding or schema makes that id's messages ambiguous: they are dropped."""
        from mcap.records import Channel

        ch = Channel.read(ReadDataStream(io.BytesIO(bytes(body))))
        old = self.channels.get(ch.id)
        if old is not None and (old.topic, old.message_encoding, old.schema_id) != (
                ch.topic, ch.message_encoding, ch.schema_id):
            if ch.id not in self.redefined:
                self.redefined[ch.id] = f"{old.topic!r} ({old.message_encoding}) and {ch.topic!r} " \
                                        f"({ch.message_encoding})"
                self.bad(f"channel id {ch.id} defined twice, as {self.redefined[ch.id]} - its later messages "
                         "are dropped", where)
            return
        self.channels[ch.id] = ch

    def _message(self, a, b, where, data_buf=None):
        buf = self.buf if data_buf is None else data_buf
        if b - a < _MSG_HEAD.size:
            raise ValueError("message record too short")
        cid, _seq, log_time, _pub = _MSG_HEAD.unpack_from(buf, a)
        self.i += 1
        ch = self.channels.get(cid)
        if ch is None:
            self.bad(f"message on unknown channel id {cid}", f"message {self.i}")
            return
        if cid in self.redefined:
            self.bad(f"message on channel id {cid}, which the file defines twice (as {self.redefined[cid]})",
                     f"message {self.i}")
            return
        t = log_time * 1e-9
        if self.on_message(ch, t, bytes(buf[a + _MSG_HEAD.size:b]), self.i, self):
            self.t_last = max(self.t_last, t)

    def _refuse(self, exc: InflateRefused, where, byte_range, span):
        self.refused.append(f"{where} (log time {span[0]:.3f}-{span[1]:.3f} s on the file's clock) not read: "
                            f"it {exc.problem}" + (f" - {RAISE_HINT}" if "budget" in exc.problem else ""))
        self.bad(exc.problem, where, byte_range, t_span=span)

    def _chunk(self, a, b, cut: bool):
        buf = self.buf
        if b - a < 28 + 4:
            raise ValueError("chunk record too short")
        t_start, t_end, usize, crc = _CHUNK_HEAD.unpack_from(buf, a)
        clen = struct.unpack_from("<I", buf, a + 28)[0]
        if clen > 16:
            raise ValueError("bad compression name length")
        comp = bytes(buf[a + 32:a + 32 + clen]).decode("ascii")
        p = a + 32 + clen
        dlen = _U64.unpack_from(buf, p)[0]
        p += 8
        stop = min(b, p + dlen)
        where = f"chunk at byte {a - 9}"
        span = (t_start * 1e-9, t_end * 1e-9)
        cap = None
        try:
            if comp:
                cap = self.budget.cap(usize)  # a record declaring more than is left is not inflated at all
            data = _inflate_chunk(comp, buf[p:stop], cap)
        except LogFormatError as exc:
            raise LogFormatError(self.path, exc.problem, where) from None
        except InflateRefused as exc:
            self._refuse(exc, where, (a - 9, b), span)
            return
        except Overflow:
            self.budget.spend(cap)
            self._refuse(self.budget.overflow(usize), where, (a - 9, b), span)
            return
        if comp:
            self.budget.spend(len(data))
        if cut:
            whole = _zstd_whole_blocks_end(buf[p:stop]) if comp == "zstd" else None
            self.undecoded_from = None if whole is None or p + whole >= stop else p + whole
        if not cut:
            if len(data) != usize or (crc and zlib.crc32(data) != crc):
                self.bad("corrupt chunk (size or CRC does not match) dropped", where, (a - 9, b), t_span=span)
                return
        q, m = 0, len(data)
        while q < m:
            if q + 9 > m:
                if not cut:
                    self.bad("chunk ends inside a record", where, t_span=(self.t_last, span[1]))
                return
            op = data[q]
            length = _U64.unpack_from(data, q + 1)[0]
            s, e = q + 9, q + 9 + length
            if e > m:
                if not cut:
                    self.bad("chunk ends inside a record", where, t_span=(self.t_last, span[1]))
                return
            if op < 0x10 and op not in (_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
                # Opcode 0 is reserved and the other known records do not belong in a chunk: not MCAP any more.
                self.bad(f"record of opcode 0x{op:02X} inside a chunk, rest of the chunk dropped", where,
                         t_span=(self.t_last, span[1]))
                return
            try:
                if op == _OP_MESSAGE:
                    self._message(s, e, where, data_buf=data)
                elif op == _OP_CHANNEL:
                    self._channel(data[s:e], where)
                elif op == _OP_SCHEMA:
                    self._schema(data[s:e])
            except LogFormatError:
                raise
            except Exception as exc:  # noqa: BLE001 - one record inside a chunk whose framing holds: skip it
                self.bad(f"unreadable record in chunk: {_why(exc)}", where, t_span=(self.t_last, span[1]))
            q = e


def _why(exc: Exception) -> str:
    return (str(exc).splitlines()[0][:100] if str(exc) else type(exc).__name__).encode("utf-8", "replace").decode()


def read_mcap_streams(path, topic_map: dict | None = None, strict: bool = False):
    """Read an MCAP log of JSON messages into streams.

    The file's records are walked in order (as ``mcap recover`` does), so a file cut short (a recorder
    killed mid-drive) gives every message before the cut. Of the last, cut chunk, every complete record its
    data still decodes to is read: uncompressed and LZ4 chunks up to the cut; zstd chunks up to their last
    whole zstd block, since a zstd block decodes only whole (its sequences are read from its end). The
    records of that cut block (up to 128 kB uncompressed) are lost and named in the damage.
    A chunk whose CRC or size does not match is dropped whole; so is a chunk that declares more than is left
    of the inflate budget or inflates beyond its declared size (:mod:`calib.ingest.limits`; named in
    ``meta.notes``). A message that is not JSON or nests deeper than
    :data:`~calib.ingest.limits.MAX_NESTING` levels is skipped, and so is a mapped field that is not a
    number (the message's other fields are kept); a garbled record header is skipped by finding the next
    chunk. What was lost is in ``meta.damage``; under ``strict`` the first damage is raised instead.
    Non-finite numbers are dropped and counted in ``meta.channel_counts`` (as are values outside a
    channel's physical range).

    Parameters
    ----------
    path : str or Path
    topic_map : dict, optional
        ``{topic: {field: "channel [unit]"}}``, merged over :data:`DEFAULT_TOPIC_MAP`. A key
        ``"topic#id"`` reads channel ``id`` of the topic only (and replaces the default entry of the topic).
    strict : bool
        Raise on any damage.

    Returns
    -------
    (Streams, LogMeta)

    Raises
    ------
    LogFormatError
        Empty file, nothing readable, a topic that is not JSON-encoded, no mapped topic, a mapped topic
        published on several channels, a bad ``IPTM_MAX_INFLATE_MB``; any damage under ``strict``.
    """
    check_nonempty(path)
    by_topic, by_id = _resolve_map(path, topic_map)
    budget = InflateBudget(path)
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format="mcap")
    dmg = Damage(path, strict=strict, unit="message")
    parts: dict[tuple[str, str], tuple[list, list]] = {}  # (topic-map key, field) -> (times, values)
    label_fields: dict[str, dict] = {}  # topic-map key -> field -> (channel, unit)
    per_channel: dict[int, list] = {}  # channel id -> [topic, encoding, schema name, messages]
    not_json: dict[str, tuple[str, int]] = {}  # topic-map key -> (encoding, first message)
    state = {"t_first": math.inf, "t_prev": -math.inf, "n_back": 0, "max_back": 0.0, "n_msgs": 0}
    topics_seen = set()

    def on_message(channel, t, data, i, scan) -> bool:
        where = f"message {i} on {channel.topic}"
        if not math.isfinite(t):
            scan.bad("log time is not finite", where)
            return False
        if t < state["t_prev"]:
            back = state["t_prev"] - t
            if back > MAX_BACKSTEP_S:
                scan.bad(f"log time goes back by {back:.3f} s", where)
                return False
            state["n_back"] += 1
            state["max_back"] = max(state["max_back"], back)
        else:
            state["t_prev"] = t
        topics_seen.add(channel.topic)
        rec = per_channel.setdefault(channel.id, [channel.topic, channel.message_encoding,
                                                  scan.schemas.get(channel.schema_id, f"schema {channel.schema_id}"), 0])
        rec[3] += 1
        label, fields = f"{channel.topic}#{channel.id}", by_id.get((channel.topic, channel.id))
        if fields is None:
            label, fields = channel.topic, by_topic.get(channel.topic)
        if fields:
            label_fields[label] = fields
            if channel.message_encoding != "json":
                not_json.setdefault(label, (channel.message_encoding, i))
            else:
                if json_too_deep(data):
                    scan.bad(f"nested deeper than {MAX_NESTING} levels", where)
                    return False
                try:
                    obj = json.loads(data)
                except (ValueError, UnicodeDecodeError, RecursionError):
                    scan.bad("message is not valid JSON", where)
                    return False
                bad, kept = None, 0
                for field in fields:
                    v = _get(obj, field)
                    if v is None:
                        continue
                    if isinstance(v, bool) or not isinstance(v, (int, float)):
                        bad = bad or f"field {field!r} is not a number: {str(v)[:40]!r}"
                        continue
                    try:
                        x = float(v)
                    except OverflowError:  # an integer beyond any float: not finite, counted as such
                        x = math.inf if v > 0 else -math.inf
                    tl, vl = parts.setdefault((label, field), ([], []))
                    tl.append(t)
                    vl.append(x)
                    kept += 1
                if bad:
                    # the message's other fields are kept: the loss is this value, at this time
                    scan.bad(bad, where, t_span=(t, t) if kept else None)
                    if not kept:
                        return False
        state["n_msgs"] += 1
        state["t_first"] = min(state["t_first"], t)
        if dmg._open_span is not None:
            dmg.good(t)
        return True

    with quiet_libraries() as chatter:
        try:
            with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                scan = _McapScan(path, mm, dmg, on_message, budget).run()
                metadata = scan.metadata
                if scan.cut_in_summary:
                    meta.notes.append("the file is cut in its summary (index) section, after all the data: "
                                      "no message lost")
        except LogFormatError:
            raise
        except Exception as exc:  # noqa: BLE001 - last resort: an mmap/OS error is still a clean message
            raise LogFormatError(path, f"corrupt or truncated MCAP file: {_why(exc)}") from None
    meta.notes.extend(scan.refused)
    for text in chatter:
        dmg.bad(LogFormatError(path, f"{text[:80].replace(':', ' -')} (reported by the mcap library)", "mcap"))
    for name in ("iptm", "drive_log"):
        if name in metadata:
            d = metadata[name]
            meta.synthetic = d.get("synthetic", "").lower() in ("true", "1", "yes")
            meta.vehicle_id = d.get("vehicle_id", "")
            meta.start_time = d.get("start_time") or None
    if state["n_msgs"] == 0:
        # name the records that were refused (a decompression bomb: "chunk at byte N ... declared ...")
        extra = f" ({'; '.join(scan.refused or dmg.where or list(dmg.problems))})" if dmg or scan.refused else ""
        if dmg.truncated_at is not None and "zstd" in extra:
            extra += " - the cut falls in the chunk's first zstd block (up to 128 kB of records)"
        raise LogFormatError(path, "MCAP file holds no readable messages" + extra)
    _check_channels(path, by_topic, by_id, per_channel, scan.channels, meta)
    for label, (enc, i) in not_json.items():
        raise LogFormatError(path, f"topic {label} is {enc!r}-encoded, only JSON is supported", f"message {i}")
    if not label_fields:
        raise LogFormatError(path, f"no topic matches the topic map (topics in file: {', '.join(sorted(topics_seen))[:200]})",
                             hint="pass a topic map (--map) naming topic, field, channel and unit")
    if state["n_back"]:
        meta.notes.append(f"{state['n_back']} message(s) out of log-time order by up to "
                          f"{state['max_back'] * 1e3:.1f} ms were sorted")
    meta.damage = dmg.finish(state["t_first"], state["t_prev"])
    if meta.damage and not metadata:
        meta.notes.append("the file's metadata record (synthetic flag, vehicle id) was lost with the damage")
    t_first = state["t_first"]
    streams = {}
    for (label, field), (tl, vl) in parts.items():
        ch, unit = label_fields[label][field]
        v = to_channel_unit(np.asarray(vl), unit, ch, path, f"topic {label} field {field}")
        t = np.asarray(tl) - t_first
        if ch in streams or ch in meta.channel_sources:
            raise LogFormatError(path, f"two fields map to channel {ch}", f"topic {label} field {field}")
        s = make_series(t, v, ch, meta=meta)
        if len(s):
            streams[ch] = s
        meta.channel_sources[ch] = f"{label}.{field}"
        meta.original_units[ch] = unit
    return streams, meta


def _check_channels(path, by_topic, by_id, per_channel, channels, meta) -> None:
    """Refuse a topic-map topic published on several channels; say which channels a ``topic#id`` key
    leaves unread.

    Raises
    ------
    LogFormatError
        A bare topic key matched by messages of two or more channels, or a ``topic#id`` key whose channel
        is on another topic.
    """
    def describe(ids):
        return "; ".join(f"id {c}: schema {per_channel[c][2]!r}, {per_channel[c][1]}, {per_channel[c][3]} messages"
                         for c in ids)

    for (topic, cid) in by_id:
        ch = channels.get(cid)
        if ch is not None and ch.topic != topic:
            raise LogFormatError(path, f"topic map entry '{topic}#{cid}' names channel {cid}, which is on topic "
                                       f"{ch.topic!r}", "topic map",
                                 hint=f"use '{ch.topic}#{cid}', or the id of a channel on {topic}")
    for topic in by_topic:
        ids = sorted(c for c, rec in per_channel.items() if rec[0] == topic and (topic, c) not in by_id)
        if len(ids) > 1:
            raise LogFormatError(path, f"topic {topic} is published on {len(ids)} channels ({describe(ids)}); "
                                       "they are not merged", "topic map",
                                 hint=f"give the channel in the topic map as '{topic}#{ids[-1]}' (one entry per "
                                      "channel to read)")
    chosen = {tp for tp, _ in by_id}
    for topic in sorted(chosen):
        unread = sorted(c for c, rec in per_channel.items()
                        if rec[0] == topic and (topic, c) not in by_id and topic not in by_topic)
        if unread:
            picked = ", ".join(str(c) for tp, c in sorted(by_id) if tp == topic)
            meta.notes.append(f"topic {topic}: channel(s) not read ({describe(unread)}) - the topic map reads "
                              f"channel {picked}")
