"""What reading one log may cost: bytes inflated from its compressed records, nesting of its messages.

A compressed record (an MCAP chunk, a BLF container) says how large it is once inflated. A hostile or
damaged one may inflate far beyond that (33 kB of zstd can inflate to 1 GiB) or declare gigabytes. So every
stream is inflated in bounded steps and never past the smaller of

- the record's declared size (one byte more proves the declaration wrong: the record is refused), and
- what is left of the file's budget, :data:`MAX_INFLATE_MB` MiB by default, or the environment variable
  ``IPTM_MAX_INFLATE_MB`` (a record that declares more than is left is refused without being inflated), and
  :data:`MAX_RECORD_MB` MiB for one record unless that variable is set (one record is in memory whole).

Memory and time spent on a bomb are then bounded by the budget, whatever its compression ratio. A refused
record is damage of that record only: the readers name it and read the rest of the file.

Structured (JSON) messages nested deeper than :data:`MAX_NESTING` levels are refused before they are
parsed (Python's parser recurses once per level).
"""
from __future__ import annotations

import io
import math
import os
import re
import zlib

import numpy as np

from calib.errors import LogFormatError

#: Environment variable that sets the inflate budget per file, in MiB.
ENV_MAX_INFLATE_MB = "IPTM_MAX_INFLATE_MB"
#: Default budget of bytes inflated from one file's compressed records, MiB.
MAX_INFLATE_MB = 512
#: Most bytes one record may inflate to, MiB, unless ``IPTM_MAX_INFLATE_MB`` is set (then the budget): one record
#: is in memory whole, so this bounds the memory a read costs. MCAP writers chunk at about 1 MiB, BLF
#: containers hold about 128 kB.
MAX_RECORD_MB = 64
#: Deepest nesting of a JSON message that is read (a dotted topic-map field needs one level per dot).
MAX_NESTING = 64
#: Output of one inflation step, bytes: the most a stream can allocate past its cap.
STEP = 1 << 20
#: How to read a record refused for the budget (for notes and docs).
RAISE_HINT = (f"the inflate budget is per file, {MAX_INFLATE_MB} MiB unless the environment variable "
              f"{ENV_MAX_INFLATE_MB} gives another number of MiB: raise it to read a trusted file whole")


class InflateRefused(Exception):
    """A compressed record that was not inflated, or not past its cap. ``problem`` is one line saying why
    (no colon, so a damage summary keeps it whole)."""

    def __init__(self, problem: str):
        super().__init__(problem)
        self.problem = problem


def size_text(n: float, down: bool = False) -> str:
    """Bytes for a message: ``8 GiB``, ``510.99 MiB``, ``131072 bytes``; a fraction is rounded up (a size
    declared), or down with ``down`` (a budget left), so that a refused size never reads as within it."""
    for unit, k in (("GiB", 1 << 30), ("MiB", 1 << 20)):
        if n >= k:
            if n % k == 0:
                return f"{n // k} {unit}"
            x = (math.floor if down else math.ceil)(n * 100 / k) / 100
            return f"{x:.2f} {unit}"
    return f"{int(n)} bytes"


def max_inflate_bytes(path) -> int:
    """The inflate budget per file in bytes: ``IPTM_MAX_INFLATE_MB`` if set, else :data:`MAX_INFLATE_MB`."""
    raw = os.environ.get(ENV_MAX_INFLATE_MB, "").strip()
    if not raw:
        return MAX_INFLATE_MB << 20
    try:
        mb = float(raw)
    except ValueError:
        mb = math.nan
    if not (math.isfinite(mb) and 0 < mb <= 1 << 30):
        raise LogFormatError(path, f"environment variable {ENV_MAX_INFLATE_MB}={raw[:20]!r} is not a positive "
                                   "number of MiB", ENV_MAX_INFLATE_MB,
                             hint=f"set it to e.g. 2048, or unset it for the default {MAX_INFLATE_MB} MiB")
    return max(int(mb * (1 << 20)), 1)


class InflateBudget:
    """The bytes one file's compressed records may still inflate to.

    Parameters
    ----------
    path : str or Path
        The file (for the message of a bad ``IPTM_MAX_INFLATE_MB``).
    limit : int, optional
        Budget in bytes; default :func:`max_inflate_bytes`.
    """

    def __init__(self, path, limit: int | None = None):
        self.limit = max_inflate_bytes(path) if limit is None else int(limit)
        chosen = limit is not None or bool(os.environ.get(ENV_MAX_INFLATE_MB, "").strip())
        self.record_limit = self.limit if chosen else min(self.limit, MAX_RECORD_MB << 20)
        self.used = 0

    @classmethod
    def of(cls, owner, path) -> "InflateBudget":
        """The budget kept on ``owner`` (one reader of one file), made on first use."""
        b = getattr(owner, "_inflate_budget", None)
        if b is None:
            b = cls(path)
            owner._inflate_budget = b
        return b

    @property
    def left(self) -> int:
        return max(self.limit - self.used, 0)

    def _budget_text(self) -> str:
        left = f"the {size_text(self.left, down=True)} left of " if self.used else ""
        return f"{left}the {size_text(self.limit)} inflate budget (raise {ENV_MAX_INFLATE_MB})"

    def cap(self, declared: int | None) -> int:
        """The most bytes a record declaring ``declared`` bytes (None or 0: not declared) may inflate to.

        Raises
        ------
        InflateRefused
            The declared size alone is over what is left of the budget.
        """
        if declared and declared > self.left:
            raise InflateRefused(f"declares {size_text(declared)}, over {self._budget_text()}")
        if declared and declared > self.record_limit:
            raise InflateRefused(f"declares {size_text(declared)}, more than the {size_text(self.record_limit)} one "
                                 f"record may inflate to (raise {ENV_MAX_INFLATE_MB})")
        return int(declared) if declared else min(self.left, self.record_limit)

    def spend(self, n: int) -> None:
        self.used += int(n)

    def overflow(self, declared: int | None) -> InflateRefused:
        """The refusal of a stream that inflated past :meth:`cap`."""
        if declared:
            return InflateRefused(f"inflates beyond its declared {size_text(declared)} (a decompression bomb "
                                  "or damage), dropped")
        return InflateRefused(f"inflates beyond {self._budget_text()}")


class Overflow(Exception):
    """A stream holds more than its cap (internal: turned into :class:`InflateRefused` by the caller)."""


def inflate_zstd(data, cap: int) -> bytearray:
    """Inflate zstd frame(s) up to ``cap`` bytes, in steps of :data:`STEP`.

    A stream cut short or damaged gives what it decoded before the cut (zstd outputs whole blocks only).

    Raises
    ------
    Overflow
        The stream holds more than ``cap`` bytes (at most ``cap + 1`` were produced).
    """
    import zstandard

    out = bytearray()
    reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True)
    try:
        while True:
            piece = reader.read(min(STEP, cap + 1 - len(out)))
            if not piece:
                break
            out += piece
            if len(out) > cap:
                raise Overflow
    except zstandard.ZstdError:
        pass
    return out


def inflate_lz4_frame(data, cap: int):
    """Inflate an LZ4 frame up to ``cap`` bytes, in steps of :data:`STEP`: (output, decompressor).

    The decompressor tells whether the frame ended (``eof``). Raises :class:`Overflow` past ``cap`` and
    RuntimeError (lz4's) on damage.
    """
    import lz4.frame

    d = lz4.frame.LZ4FrameDecompressor()
    out = bytearray()
    src = bytes(data)
    while True:
        piece = d.decompress(src, max_length=min(STEP, cap + 1 - len(out)))
        src = b""
        out += piece
        if len(out) > cap:
            raise Overflow
        if d.eof or not piece:
            return out, d


def inflate_zlib(data, cap: int, complete: bool) -> tuple[bytearray, bool]:
    """Inflate a zlib stream up to ``cap`` bytes, in steps of :data:`STEP`: (output, ok).

    ``ok`` is False on a zlib error, or when a ``complete`` stream does not reach its end (its check
    cannot have passed); a stream known to be cut gives what it holds, ok.

    Raises
    ------
    Overflow
        The stream holds more than ``cap`` bytes.
    """
    z = zlib.decompressobj()
    out = bytearray()
    view = memoryview(data)
    pos = 0
    try:
        while not z.eof:
            if z.unconsumed_tail:
                src = z.unconsumed_tail
            elif pos < len(view):
                src = view[pos:pos + STEP]
                pos += STEP
            else:
                break
            out += z.decompress(src, min(STEP, cap + 1 - len(out)))  # max_length >= 1: 0 means unbounded
            if len(out) > cap:
                raise Overflow
    except zlib.error:
        return bytearray(), False
    return out, (z.eof if complete else True)


# A JSON string (brackets inside it do not nest).
_JSON_STRING = re.compile(rb'"(?:[^"\\]++|\\.)*+"?', re.DOTALL)
_DEPTH_STEP = np.zeros(256, dtype=np.int8)
_DEPTH_STEP[[ord("["), ord("{")]] = 1
_DEPTH_STEP[[ord("]"), ord("}")]] = -1


def json_too_deep(data, limit: int = MAX_NESTING) -> bool:
    """True when a JSON text nests arrays/objects more than ``limit`` levels deep.

    A text with no more than ``limit`` opening brackets is passed at once (two C-level counts); otherwise
    strings are blanked and the running depth is summed in blocks, so the check costs a few bytes of
    memory per byte of the message, not a frame of Python's stack per level.
    """
    data = bytes(data)
    if data.count(b"[") + data.count(b"{") <= limit:
        return False
    text = _JSON_STRING.sub(b'""', data)
    depth = 0
    for i in range(0, len(text), STEP):
        steps = _DEPTH_STEP[np.frombuffer(text, dtype=np.uint8, count=min(STEP, len(text) - i), offset=i)]
        run = depth + np.cumsum(steps, dtype=np.int64)
        if run.max(initial=depth) > limit:
            return True
        depth = int(run[-1])
    return False
