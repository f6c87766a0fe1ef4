"""MDF4 (.mf4) logs through asammdf (optional extra: ``pip install iptm[mdf]``).

Channels are matched by name like CSV headers (canonical names, human names, aliases) or through a
``column_map`` ``{mdf channel name: "channel [unit]"}``; the unit comes from the map, else from the MDF
channel's own unit, and a mapped channel with neither is an error.
"""
from __future__ import annotations

import gc
import struct
import sys
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


def _quiet_asammdf_del(unraisable, _prev=None):
    """Drop the exception asammdf's ``__del__`` raises on a half-built object; pass any other on."""
    if str(getattr(unraisable.object, "__module__", "")).startswith("asammdf"):
        return
    (_prev or sys.__unraisablehook__)(unraisable)


def _open_mdf(MDF, path):
    """Open with asammdf; a corrupt file becomes a :class:`LogFormatError` (returned, not raised).

    asammdf leaves a half-initialised object behind when its constructor fails, and that object's
    ``__del__`` then raises AttributeError at collection time; that known asammdf bug is silenced here
    (only for asammdf objects, only while the failed object is being collected).
    """
    prev = sys.unraisablehook
    sys.unraisablehook = lambda u: _quiet_asammdf_del(u, prev)
    try:
        try:
            return MDF(str(path)), None
        except Exception as exc:  # noqa: BLE001 - asammdf raises many types on a bad file
            text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
            err = LogFormatError(path, f"corrupt or unreadable MDF file: {text}")
        gc.collect()
        return None, err
    finally:
        sys.unraisablehook = prev


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
    with quiet_libraries() as chatter:
        mdf, err = _open_mdf(MDF, path)
    if err is not None:
        if mdf is None and Path(path).stat().st_size < _declared_size(path):
            # asammdf writes the channel definitions after the data: a cut file has no layout left.
            raise LogFormatError(path, f"{err.problem}; the file is cut short and keeps its channel "
                                       "definitions after the data, so nothing can be recovered") from None
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
    meta.damage = dmg.finish(0.0)
    streams = {}
    for ch, (t, v, name, unit) in parts.items():
        s = make_series(t - t_first, v, ch)
        if len(s):
            streams[ch] = s
        meta.channel_sources[ch] = name
        meta.original_units[ch] = unit
    return streams, meta
