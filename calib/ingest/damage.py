"""Reading damaged logs: what was skipped, reported once, or an error under ``strict``.

A logger that loses power mid-write, a pulled card, one garbled line: the readers keep every record they
can still trust and hand each piece they cannot to a :class:`Damage`. Under ``strict`` the first piece is
raised as the :class:`~calib.errors.LogFormatError` it describes (the reader's behaviour before recovery
existed); otherwise it is counted, with where it was (line numbers, message numbers, byte ranges) and the
stretch of log time it leaves without data, and :func:`warn_damage` reports it all in one
:class:`~calib.errors.LogDamageWarning`. The same summary is stored in ``LogMeta.damage``.

Library chatter (python-can's and asammdf's log records, warnings from mcap/pandas) is caught by
:func:`quiet_libraries` and turned into damage entries instead of being printed.
"""
from __future__ import annotations

import contextlib
import logging
import math
import warnings

from calib.errors import LogDamageWarning, LogFormatError

#: How many individual places are listed in the summary (all are counted).
MAX_LISTED = 8


class Damage:
    """Collects the damaged parts of one log while it is read.

    Parameters
    ----------
    path : str or Path
        The log (for messages).
    strict : bool
        Raise the first damage instead of recording it.
    unit : str
        What one damaged piece is ("line", "message", "frame", "chunk").
    """

    def __init__(self, path, strict: bool = False, unit: str = "line"):
        self.path = str(path)
        self.strict = strict
        self.unit = unit
        self.n = 0
        self.where: list[str] = []
        self.problems: dict[str, int] = {}
        self.spans: list[list[float]] = []  # [t_start, t_end] in the file's clock; end may be inf
        self.bytes_lost: list[tuple[int, int]] = []
        self.truncated_at: int | None = None
        self.file_size: int | None = None
        self._open_span: float | None = None

    def __bool__(self) -> bool:
        return self.n > 0 or self.truncated_at is not None

    def bad(self, err: LogFormatError, t_last_good: float | None = None, count: int = 1,
            byte_range: tuple[int, int] | None = None, t_span: tuple[float, float] | None = None) -> None:
        """Record one damaged piece (raise it under ``strict``).

        ``t_last_good`` opens a time span closed by the next :meth:`good` time; ``t_span`` gives a
        known span directly (a chunk's own start and end times).
        """
        if self.strict:
            raise err
        self.n += count
        if len(self.where) < MAX_LISTED:
            self.where.append(err.where or "?")
        key = err.problem.split(":")[0][:100]
        self.problems[key] = self.problems.get(key, 0) + count
        if byte_range is not None:
            self.bytes_lost.append((int(byte_range[0]), int(byte_range[1])))
        if t_span is not None:
            self.spans.append([float(t_span[0]), float(t_span[1])])
        elif self._open_span is None and t_last_good is not None:
            self._open_span = t_last_good

    def good(self, t: float) -> None:
        """A trusted record at time ``t``: closes an open span of lost data."""
        if self._open_span is not None:
            self.spans.append([self._open_span, float(t)])
            self._open_span = None

    def truncated(self, at_byte: int, size: int | None = None, t_last_good: float | None = None,
                  problem: str = "file ends in the middle of a record") -> None:
        """The file stops early (or cannot be followed past ``at_byte``)."""
        err = LogFormatError(self.path, f"corrupt or truncated file: {problem}", f"byte {at_byte}")
        if self.strict:
            raise err
        self.truncated_at = int(at_byte)
        self.file_size = size
        key = problem.split(":")[0][:100]
        self.problems[key] = self.problems.get(key, 0) + 1
        if len(self.where) < MAX_LISTED:
            self.where.append(f"from byte {at_byte}")
        if size is not None and size > at_byte:
            self.bytes_lost.append((int(at_byte), int(size)))
        if self._open_span is None:
            self._open_span = t_last_good if t_last_good is not None else -math.inf

    def finish(self, t0: float, t_end: float | None = None) -> dict:
        """Close open spans and return the summary (``{}`` when nothing was damaged).

        ``t0`` is the log's first record time (spans are reported from it); ``t_end`` its last.
        """
        if self._open_span is not None:
            self.spans.append([self._open_span, math.inf])
            self._open_span = None
        if not self:
            return {}
        spans = []
        for a, b in self.spans:
            a = max(a - t0, 0.0) if math.isfinite(a) else 0.0
            b = max(b - t0, a) if math.isfinite(b) else None  # a jittered next sample may sort earlier
            if spans and b is not None and spans[-1][1] is not None and a <= spans[-1][1]:
                spans[-1][1] = max(spans[-1][1], b)
            else:
                spans.append([a, b])
        out = {
            "recovered": True,
            "unit": self.unit,
            "pieces_lost": self.n,
            "where": list(self.where),
            "problems": dict(self.problems),
            "spans_s": spans,
            "bytes_lost": [list(r) for r in self.bytes_lost[:MAX_LISTED]],
            "bytes_lost_total": int(sum(b - a for a, b in self.bytes_lost)),
            "truncated_at_byte": self.truncated_at,
            "file_size": self.file_size,
            "last_time_s": None if t_end is None else float(t_end - t0),
        }
        out["summary"] = summarize(out)
        return out


def _span_text(spans) -> str:
    parts = []
    for a, b in spans[:MAX_LISTED]:
        parts.append(f"everything after {a:.1f} s" if b is None else f"{a:.1f}-{b:.1f} s")
    more = f" and {len(spans) - MAX_LISTED} more" if len(spans) > MAX_LISTED else ""
    return ", ".join(parts) + more


def summarize(d: dict) -> str:
    """One line saying what a damaged log lost (from :meth:`Damage.finish`'s dict)."""
    bits = []
    n = d.get("pieces_lost", 0)
    if n:
        unit = d.get("unit", "piece")
        where = ", ".join(d.get("where", [])[: MAX_LISTED])
        more = "..." if n > len(d.get("where", [])) else ""
        bits.append(f"{n} damaged {unit}{'s' if n != 1 else ''} skipped ({where}{more})")
    if d.get("truncated_at_byte") is not None:
        size = d.get("file_size")
        bits.append(f"unreadable from byte {d['truncated_at_byte']}" + (f" of {size}" if size else ""))
    if d.get("bytes_lost_total"):
        bits.append(f"{d['bytes_lost_total']} bytes lost")
    probs = d.get("problems", {})
    if probs:
        bits.append("problems: " + "; ".join(f"{k} x{v}" for k, v in list(probs.items())[:4]))
    spans = d.get("spans_s", [])
    if spans:
        bits.append("time without data: " + _span_text(spans))
    if d.get("last_time_s") is not None:
        bits.append(f"data kept up to {d['last_time_s']:.1f} s")
    return "recovered a damaged log: " + "; ".join(bits)


def warn_damage(path, damage: dict, stacklevel: int = 3) -> None:
    """Issue the one :class:`LogDamageWarning` for a log (nothing when ``damage`` is empty)."""
    if damage:
        warnings.warn(LogDamageWarning(f"{path}: {damage['summary']} (pass strict=True / --strict to refuse "
                                       "damaged logs)"), stacklevel=stacklevel)


class _ListHandler(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list[str] = []

    def emit(self, record):  # noqa: D401 - logging API
        try:
            self.records.append(record.getMessage())
        except Exception:  # noqa: BLE001 - a malformed log record from a library must not escape
            self.records.append(str(record.msg))


@contextlib.contextmanager
def quiet_libraries(loggers=("can", "asammdf", "mcap", "canmatrix", "cantools")):
    """Catch what the readers' libraries log or warn while a file is read.

    Yields a list that receives the captured messages (log records at WARNING and above, and warnings),
    so the caller can report them as damage instead of letting them reach the console.
    """
    captured: list[str] = []
    handler = _ListHandler()
    handler.setLevel(logging.WARNING)
    saved = []
    for name in loggers:
        lg = logging.getLogger(name)
        saved.append((lg, lg.propagate, lg.handlers[:]))
        lg.handlers = [handler]  # asammdf installs its own console handler: replace, not add
        lg.propagate = False
    ours = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield captured
        for w in caught:
            if issubclass(w.category, LogDamageWarning):
                ours.append(w)
            elif issubclass(w.category, ResourceWarning):
                # the garbage collector's report on some earlier object's unclosed handle, emitted whenever
                # collection happens to run: it says nothing about the file being read
                continue
            else:
                captured.append(f"{w.category.__name__}: {w.message}")
    finally:
        for lg, prop, handlers in saved:
            lg.handlers = handlers
            lg.propagate = prop
        captured.extend(handler.records)
    for w in ours:  # the project's own warnings pass through
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
