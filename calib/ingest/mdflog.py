"""MDF4 (.mf4) logs through asammdf (optional extra: ``pip install iptm[mdf]``).

Channels are matched by name like CSV headers (canonical names, human names, aliases) or through a
``column_map`` ``{mdf channel name: "channel [unit]"}``; the unit comes from the map, else from the MDF
channel's own unit, and a mapped channel with neither is an error.
"""
from __future__ import annotations

import gc
import struct
import sys
import tempfile
from pathlib import Path

import numpy as np

from calib.drivelog import LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.ingest.common import canonical_name, check_nonempty, make_series, parse_target, split_spec, to_channel_unit
from calib.ingest.damage import Damage, quiet_libraries


def _declared_size(path) -> int:
    """End of the farthest block the file's block headers reach (0 if none can be read)."""
    end = 0
    with open(path, "rb") as fh:
        data = fh.read()
    k = data.find(b"##", 64)
    while 0 <= k < len(data) - 16:
        if data[k + 2:k + 4].isalpha():
            length = struct.unpack_from("<Q", data, k + 8)[0]
            if length < 1 << 40:
                end = max(end, k + length)
        k = data.find(b"##", k + 1)
    return end


def _cut_data_copy(path, folder) -> tuple[Path, int] | None:
    """A copy of a cut MDF4 file that asammdf reads as an unfinalised one, or None if none can be made.

    A streaming logger writes the channel definitions (DG, CG, CN blocks) first and appends records to the
    last data block, so a file cut short still holds every definition and every complete record before the
    cut. The copy sets each data block that runs past the end to the length that is left (a group whose
    data block starts past the end gets none) and marks the file unfinalised with "update the cycle
    counters" and "update the last DT length", which asammdf applies as it opens it: it keeps the whole
    records and drops the partial last one. Returns (copy, number of groups cut). None when a definition
    block lies past the end (asammdf's own layout, definitions after the data), when the version is below
    4.10 (asammdf finalises only 4.10 and later) or when no data block was cut (another kind of damage).
    """
    data = bytearray(Path(path).read_bytes())
    size = len(data)
    if size < 88 or not data[8:12].startswith(b"4.") or data[8:12] < b"4.10":
        return None
    seen, todo, dgs = set(), [64], []
    while todo:
        a = todo.pop()
        if a in seen:
            continue
        seen.add(a)
        if a + 24 > size or data[a:a + 2] != b"##":
            return None  # a definition past the cut (or a bad link): no layout to read the data with
        length, n_links = struct.unpack_from("<QQ", data, a + 8)
        if a + 24 + 8 * n_links > size or n_links > 1 << 16:
            return None
        links = struct.unpack_from(f"<{n_links}Q", data, a + 24)
        kind = bytes(data[a:a + 4])
        if kind == b"##DG":
            dgs.append(a)
            links = links[:2] + links[3:]  # the data link is handled below, not followed
        if kind in (b"##DT", b"##DL", b"##DZ", b"##HL", b"##SD"):
            continue
        todo.extend(x for x in links if x)
    cut = 0
    for dg in dgs:
        dt = struct.unpack_from("<Q", data, dg + 24 + 16)[0]
        if not dt:
            continue
        if dt + 24 > size:
            struct.pack_into("<Q", data, dg + 24 + 16, 0)  # its data starts past the cut: none left
            cut += 1
            continue
        length = struct.unpack_from("<Q", data, dt + 8)[0]
        if dt + length <= size:
            continue
        if data[dt:dt + 4] != b"##DT":
            return None  # a cut list or compressed block: not followed
        struct.pack_into("<Q", data, dt + 8, size - dt)
        cut += 1
    if not cut:
        return None
    data[0:8] = b"UnFinMF "
    struct.pack_into("<H", data, 60, struct.unpack_from("<H", data, 60)[0] | 0x1 | 0x4)
    out = Path(folder) / Path(path).name
    out.write_bytes(bytes(data))
    return out, cut


def _quiet_asammdf_del(unraisable, _prev=None):
    """Drop the exception asammdf's ``__del__`` raises on a half-built object; pass any other on."""
    if str(getattr(unraisable.object, "__module__", "")).startswith("asammdf"):
        return
    (_prev or sys.__unraisablehook__)(unraisable)


def _open_mdf(MDF, path, **kw):
    """Open with asammdf; a corrupt file becomes a :class:`LogFormatError` (returned, not raised).

    asammdf leaves a half-initialised object behind when its constructor fails, and that object's
    ``__del__`` then raises AttributeError at collection time; that known asammdf bug is silenced here
    (only for asammdf objects, only while the failed object is being collected).
    """
    prev = sys.unraisablehook
    sys.unraisablehook = lambda u: _quiet_asammdf_del(u, prev)
    try:
        try:
            return MDF(str(path), **kw), None
        except Exception as exc:  # noqa: BLE001 - asammdf raises many types on a bad file
            text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
            err = LogFormatError(path, f"corrupt or unreadable MDF file: {text}")
        gc.collect()
        return None, err
    finally:
        sys.unraisablehook = prev


def _layout_error(mdf, name) -> str | None:
    """Why a channel's place in its record (or its group's time channel's) cannot be trusted, or None.

    asammdf's compiled record slicer reads wherever a channel's byte offset points: a damaged offset or bit
    count reads outside the record (a crash of the process, or garbage, not an exception), so such a
    channel is refused before it is read."""
    for gi, ci in mdf.channels_db.get(name, ()):
        try:
            grp = mdf.groups[gi]
            size = int(grp.channel_group.samples_byte_nr)
            for k, ch in enumerate(grp.channels):
                kind = int(getattr(ch, "channel_type", 0))
                if not (k == ci or kind == 2) or kind not in (0, 2):  # the channel and its master; fixed slots
                    continue
                end = int(ch.byte_offset) + (int(ch.bit_offset) + int(ch.bit_count) + 7) // 8
                if int(ch.bit_count) <= 0 or end > size:
                    what = "its time channel's" if k != ci else "its"
                    return (f"{what} bytes {int(ch.byte_offset)}..{end} lie outside the {size}-byte record "
                            f"(group {gi}, channel {k})")
        except (AttributeError, IndexError, TypeError, ValueError):
            continue  # not an MDF4 layout this check knows; asammdf's own checks apply
    return None


def read_mdf_streams(path, column_map: dict | None = None, strict: bool = False):
    """Read an MDF4 file into streams. See the module docstring.

    Raises
    ------
    LogFormatError
        asammdf missing, corrupt file, a matched channel without a unit, no known channel.
    """
    check_nonempty(path)
    try:
        from asammdf import MDF
    except ImportError:
        raise LogFormatError(path, "reading MDF4 needs asammdf", hint="pip install 'iptm[mdf]'") from None
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format="mf4")
    column_map = dict(column_map or {})
    with open(path, "rb") as fh:
        head = fh.read(64)
    if len(head) < 64 or not head.startswith(b"MDF "):
        raise LogFormatError(path, "not an MDF file (no 'MDF' identification block)")
    dmg = Damage(path, strict=strict, unit="block")
    with tempfile.TemporaryDirectory(prefix="iptm-mdf-") as tmp:
        return _read_mdf(MDF, path, column_map, dmg, meta, tmp)


def _read_mdf(MDF, path, column_map, dmg, meta, tmp):
    size = Path(path).stat().st_size
    cut_groups = 0
    with quiet_libraries() as chatter:
        mdf, err = _open_mdf(MDF, path)
        if err is not None and size < _declared_size(path):
            copy = _cut_data_copy(path, tmp)
            if copy is None:
                # asammdf writes the channel definitions after the data: what is left of a cut file is
                # records with nothing saying which channel, type, scaling or unit they hold.
                raise LogFormatError(path, f"{err.problem}; the file is cut short and its channel definitions "
                                           "(DG/CG/CN blocks) lie after the cut, so its records cannot be "
                                           "decoded") from None
            if dmg.strict:
                dmg.truncated(size, None, None, "file ends inside its data (an unfinalised MDF4 file)")
            mdf, err = _open_mdf(MDF, copy[0], temporary_folder=tmp)
            cut_groups = copy[1]
    if err is not None:
        raise err
    parts = {}
    t_first = np.inf
    chatter_ctx = quiet_libraries()
    chatter2 = chatter_ctx.__enter__()
    try:
        names = list(mdf.channels_db)
        for name in names:
            base, unit_in_name = split_spec(name)
            if name in column_map:
                ch, unit = parse_target(column_map[name], path, f"column map entry {name!r}")
            else:
                ch, unit = canonical_name(base), unit_in_name
                if ch is None:
                    continue
            why = _layout_error(mdf, name)
            if why is not None:
                dmg.bad(LogFormatError(path, f"channel outside its record, skipped: {why}", f"MDF channel {name!r}"))
                continue
            sig = mdf.get(name)
            unit = unit or (sig.unit or None)
            if not unit:
                raise LogFormatError(path, f"MDF channel {name!r} has no unit", hint="give one in a column map")
            t = np.asarray(sig.timestamps, dtype=float)
            v = np.asarray(sig.samples, dtype=float)
            if len(t):
                t_first = min(t_first, float(t[0]))
            parts[ch] = (t, to_channel_unit(v, unit, ch, path, f"channel {name!r}"), name, unit)
    except LogFormatError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise LogFormatError(path, f"cannot read MDF channels: {str(exc)[:160]}") from None
    finally:
        mdf.close()
        chatter_ctx.__exit__(None, None, None)
    for text in list(chatter) + list(chatter2):
        dmg.bad(LogFormatError(path, f"{text[:80].replace(':', ' -')} (reported by asammdf)", "asammdf"))
    if not parts:
        raise LogFormatError(path, "no MDF channel is a known channel", hint="pass a column map")
    t_last = max((float(t[-1]) for t, *_ in parts.values() if len(t)), default=None)
    if cut_groups:
        dmg.truncated(size, None, t_last, f"file ends inside the data of {cut_groups} channel group(s), read "
                                          "as an unfinalised MDF4 file (whole records kept)")
    meta.damage = dmg.finish(t_first if np.isfinite(t_first) else 0.0, t_last if cut_groups else None)
    streams = {}
    for ch, (t, v, name, unit) in parts.items():
        with np.errstate(invalid="ignore", over="ignore"):  # a non-finite time is counted by make_series
            rel = t - t_first
        s = make_series(rel, v, ch, meta)
        if len(s):
            streams[ch] = s
        meta.channel_sources[ch] = name
        meta.original_units[ch] = unit
    return streams, meta
