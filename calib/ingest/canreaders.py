""".asc, .trc and .blf readers that keep going past damage.

python-can's readers stop at the first bad record (a garbled ASC/TRC line raises; a truncated or corrupt
BLF container ends the file or raises), and some of them skip odd lines without a word. These subclasses
reuse python-can's own record parsing but drive the loop themselves: every record that parses is
yielded as a :class:`can.Message`; every piece that does not is yielded as a :class:`Bad` (what, where,
which bytes), so the caller can count it, say what was lost, or raise it under ``strict``.

BLF: the file is a sequence of ``LOBJ`` objects, mostly zlib-compressed ``LOG_CONTAINER`` objects holding
the frames. A container that ends with the file (a logger that lost power) is inflated as far as it
goes; a complete container whose zlib stream fails its check is dropped whole (its frames cannot be
trusted); an object header that is not ``LOBJ`` is skipped by searching for the next one. A container
is inflated in bounded steps, never past its declared uncompressed size nor the file's inflate budget
(:mod:`calib.ingest.limits`); one that would is dropped by name.
"""
from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass

import can
from can.io import blf as _blf

from calib.errors import LogFormatError
from calib.ingest.limits import InflateBudget, InflateRefused, Overflow, inflate_zlib

_ASC_TRIGGER = re.compile(r"begin\s+triggerblock\s+\w+\s+(?P<datetime_string>.+)", re.IGNORECASE)
_ASC_END = re.compile(r"end\s+triggerblock", re.IGNORECASE)
_ASC_START_MEAS = re.compile(r"^\d+\.\d+\s+Start of measurement")
# A classic frame line: time, channel, hex ID (optionally 'x'), then anything.
_ASC_FRAME_LIKE = re.compile(r"^\d+\.\d+\s+\d+\s+[0-9A-Fa-f]+x?\s")


@dataclass
class Bad:
    """A damaged piece of a CAN log."""

    err: LogFormatError
    byte_range: tuple[int, int] | None = None
    truncated: bool = False


class _Lines:
    """Iterate a text file counting lines (python-can's readers iterate ``self.file``)."""

    def __init__(self, fh):
        self.fh = fh
        self.n = 0
        self.cut = False  # the last line read has no line end: the file was cut inside it

    def __iter__(self):
        return self

    def __next__(self):
        line = next(self.fh)
        self.n += 1
        self.cut = not line.endswith("\n")
        return line

    def close(self):
        self.fh.close()


def _open_text(path):
    return _Lines(open(path, "r", encoding="utf-8", errors="surrogateescape", newline=None))


class RecoveringASCReader(can.ASCReader):
    """python-can's ASC reader, one line at a time: a line that should be a frame and is not is a :class:`Bad`."""

    def __init__(self, path):
        self._path = str(path)
        self._lines = _open_text(path)
        super().__init__(self._lines)

    def __iter__(self):
        self._extract_header()
        for _line in self.file:
            line = _line.strip()
            if not line or line.startswith("//"):
                continue
            m = _ASC_TRIGGER.match(line)
            if m:
                self.start_time = 0.0
                continue
            if _ASC_END.match(line) or _ASC_START_MEAS.match(line):
                continue
            where = f"line {self._lines.n}"
            if self._lines.cut:
                yield Bad(LogFormatError(self._path, "line cut short (no line end)", where))
                continue
            if not can.io.asc.ASC_MESSAGE_REGEX.match(line):
                # Vector ASC files hold other events (statistics, J1939, chip state) that are not frames
                # and python-can skips; a line that does not start with a time or looks like a frame
                # that fails to parse is damage.
                head = line.split(None, 1)[0]
                try:
                    float(head)
                    framelike = bool(_ASC_FRAME_LIKE.match(line))
                except ValueError:
                    framelike = True
                if framelike:
                    yield Bad(LogFormatError(self._path, f"not an ASC frame line: {_show(line)}", where))
                continue
            kw = {}
            try:
                ts, channel, rest = line.split(None, 2)
                kw["timestamp"] = float(ts) + self.start_time
                if channel == "CANFD":
                    kw["is_fd"] = True
                    msg = self._process_fd_can_frame(rest, kw)
                elif channel.isdigit():
                    kw["channel"] = int(channel) - 1
                    msg = self._process_classic_can_frame(rest, kw)
                else:
                    continue
            except (ValueError, IndexError, TypeError) as exc:
                yield Bad(LogFormatError(self._path, f"bad ASC frame line ({_why(exc)}): {_show(line)}", where))
                continue
            yield msg
        self.stop()


class RecoveringTRCReader(can.TRCReader):
    """python-can's TRC reader, one line at a time: a line that fails to parse is a :class:`Bad`."""

    def __init__(self, path):
        self._path = str(path)
        self._lines = _open_text(path)
        super().__init__(self._lines)

    def _one(self, line):
        where = f"line {self._lines.n}"
        if self._lines.cut:
            return Bad(LogFormatError(self._path, "line cut short (no line end)", where))
        try:
            cols = tuple(line.split(maxsplit=self._num_columns))
            msg = self._parse_cols(cols)
        except (ValueError, IndexError, KeyError, TypeError) as exc:
            return Bad(LogFormatError(self._path, f"bad TRC line ({_why(exc)}): {_show(line)}", where))
        return msg

    def __iter__(self):
        try:
            first = self._extract_header()
        except (ValueError, IndexError, KeyError, NotImplementedError) as exc:
            raise LogFormatError(self._path, f"bad TRC header: {_why(exc)}") from None
        if first is not None:
            r = self._one(first.strip())
            if r is not None:
                yield r
        for line in self.file:
            temp = line.strip()
            if not temp or temp.startswith(";"):
                continue
            r = self._one(temp)
            if r is not None:
                yield r
        self.stop()


class RecoveringBLFReader(can.BLFReader):
    """python-can's BLF reader with its outer loop replaced to read up to (and past) damage."""

    def __init__(self, path):
        self._path = str(path)
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            head = fh.read(8)
        # python-can reads the header's own size field blindly; a garbled one would ask for gigabytes.
        if len(head) < 8 or head[:4] != b"LOGG":
            raise LogFormatError(path, "not a BLF file (no LOGG signature)")
        hsize = struct.unpack_from("<L", head, 4)[0]
        if not _blf.FILE_HEADER_STRUCT.size <= hsize <= min(size, 1 << 16):
            raise LogFormatError(path, f"corrupt BLF file header (header size {hsize})")
        super().__init__(str(path))
        self._actual_size = size
        self.hit_truncation = False

    def _find_lobj(self, start: int) -> int | None:
        f = self.file
        pos = start
        while pos < self._actual_size:
            f.seek(pos)
            block = f.read(1 << 16)
            if len(block) < 4:
                return None
            k = block.find(b"LOBJ")
            if k >= 0:
                return pos + k
            pos += len(block) - 3
        return None

    def _bad(self, problem, a, b, truncated=False):
        return Bad(LogFormatError(self._path, problem, f"bytes {a}-{b}"), (a, b), truncated)

    def __iter__(self):
        f = self.file
        hsize = _blf.OBJ_HEADER_BASE_STRUCT.size
        pos = f.tell()
        while True:
            f.seek(pos)
            head = f.read(hsize)
            if not head:
                break
            if len(head) < hsize:
                self.hit_truncation = True
                yield self._bad("file ends inside an object header", pos, self._actual_size, True)
                break
            sig, _, _, obj_size, obj_type = _blf.OBJ_HEADER_BASE_STRUCT.unpack(head)
            if sig != b"LOBJ" or obj_size < hsize:
                nxt = self._find_lobj(pos + 1)
                end = self._actual_size if nxt is None else nxt
                yield self._bad("garbled object header", pos, end)
                self._tail = b""
                if nxt is None:
                    break
                pos = nxt
                continue
            body = f.read(min(obj_size - hsize, self._actual_size - pos - hsize))
            cut = len(body) < obj_size - hsize
            if cut and self.file_size and self._actual_size >= self.file_size:
                # The file is as long as its header says: the object's size field is what is wrong.
                nxt = self._find_lobj(pos + 1)
                end = self._actual_size if nxt is None else nxt
                yield self._bad("object size runs past the end of the file", pos, end)
                self._tail = b""
                if nxt is None:
                    break
                pos = nxt
                continue
            if obj_type == _blf.LOG_CONTAINER:
                refused = None  # why a container was not inflated (limits of calib.ingest.limits)
                if len(body) < _blf.LOG_CONTAINER_STRUCT.size:
                    data, ok = b"", False
                else:
                    method, declared = _blf.LOG_CONTAINER_STRUCT.unpack_from(body)
                    cdata = body[_blf.LOG_CONTAINER_STRUCT.size:]
                    if method == _blf.NO_COMPRESSION:
                        data, ok = cdata, True
                    elif method == _blf.ZLIB_DEFLATE:
                        try:
                            data, ok = _inflate(cdata, not cut, declared, InflateBudget.of(self, self._path))
                        except InflateRefused as exc:
                            data, ok, refused = b"", False, exc.problem
                    else:
                        data, ok = b"", False
                if ok:
                    yield from self._parse_container_recovering(data, pos)
                elif refused or not cut:
                    yield self._bad(f"container at byte {pos} {refused}" if refused else
                                    "corrupt compressed container dropped", pos, min(pos + obj_size, self._actual_size))
                    self._tail = b""
            if cut:
                self.hit_truncation = True
                yield self._bad(f"file ends inside the object at byte {pos} (read up to the cut)",
                                self._actual_size, self._actual_size, True)
                break
            pos = pos + obj_size + obj_size % 4
        self.stop()

    def _parse_data(self, data: bytes):
        """Frame the objects of a container here and let python-can parse each one alone.

        python-can's own loop trusts each object's size field: a garbled size of 0 makes it log
        "Unknown object header version" forever without moving on.
        """
        parse_one = super()._parse_data
        hsize = _blf.OBJ_HEADER_BASE_STRUCT.size
        n = len(data)
        pos = 0
        while True:
            self._pos = pos
            k = data.find(b"LOBJ", pos, pos + 8)
            if k < 0:
                if pos + 8 > n:
                    return  # the rest continues in the next container
                raise _blf.BLFParseError("Could not find next object")
            if k + hsize > n:
                return
            obj_size = _blf.OBJ_HEADER_BASE_STRUCT.unpack_from(data, k)[3]
            if obj_size < hsize:
                raise _blf.BLFParseError(f"object size {obj_size} is smaller than its header")
            if k + obj_size > n:
                return
            try:
                yield from parse_one(data[k:k + obj_size])
            except struct.error:
                self._pos = k
                raise _blf.BLFParseError("object too short for its type") from None
            pos = k + obj_size

    def _parse_container_recovering(self, data: bytes, obj_pos: int):
        if self._tail:
            data = b"".join((self._tail, data))
        start = 0
        while True:
            self._pos = 0
            try:
                for msg in self._parse_data(data[start:] if start else data):
                    yield msg
                break
            except struct.error:
                break
            except _blf.BLFParseError:
                bad_at = start + self._pos
                nxt = data.find(b"LOBJ", bad_at + 1)
                yield Bad(LogFormatError(self._path, "garbled object inside a container",
                                         f"container at byte {obj_pos}"))
                if nxt < 0:
                    self._pos = len(data) - start
                    break
                start = nxt
        self._tail = data[start + self._pos:]


def _inflate(cdata: bytes, complete: bool, declared: int = 0, budget: InflateBudget | None = None
             ) -> tuple[bytes, bool]:
    """Inflate a container's zlib stream in bounded steps: (output, ok). A cut stream gives what it holds (ok).

    The output is capped by the container's ``declared`` uncompressed size (0: not declared) and by what is
    left of the file's ``budget`` (see :mod:`calib.ingest.limits`).

    Raises
    ------
    InflateRefused
        The declared size is over the budget, or the stream inflates past its cap.
    """
    budget = budget if budget is not None else InflateBudget("")
    cap = budget.cap(declared)
    try:
        out, ok = inflate_zlib(cdata, cap, complete)
    except Overflow:
        budget.spend(cap)
        raise budget.overflow(declared) from None
    budget.spend(len(out))
    return bytes(out), ok


def _show(line: str) -> str:
    return repr(line.encode("utf-8", "replace").decode("utf-8", "replace")[:60])


def _why(exc: Exception) -> str:
    s = str(exc).splitlines()[0][:80] if str(exc) else type(exc).__name__
    return s.encode("utf-8", "replace").decode("utf-8", "replace")


READERS = {"asc": RecoveringASCReader, "trc": RecoveringTRCReader, "blf": RecoveringBLFReader}
