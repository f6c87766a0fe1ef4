"""CAN dumps (candump -L, .asc, .blf, .trc) decoded against a DBC with cantools.

Memory stays bounded on long logs: frames are streamed; only frames whose ID is in the DBC *and* carries
a signal we want are kept, as 8-byte payloads and float timestamps in growing arrays (16 bytes a frame);
signals are then extracted per message with numpy bit operations derived from cantools' signal
definitions. No per-frame Python dicts, no DataFrame of all frames. Multiplexed, float or longer-than-8-byte
messages fall back to cantools' per-frame decoder.

Signal -> channel map: keys ``"MESSAGE.SIGNAL"`` (or ``"SIGNAL"`` when unique in the DBC), values
``"channel"`` or ``"channel [unit]"`` (the unit overrides the DBC's). :data:`DEFAULT_SIGNAL_MAP` covers
our Prius DBC (``calib/data/can/prius_iptm.dbc``) and opendbc's ``toyota_2017.dbc`` (SPEED, ENGINE_RPM).

"Signal not available": an all-ones raw value (unsigned) or the most negative raw value (signed) that
decodes outside the signal's declared [min|max] range is dropped, not kept as a number.
"""
from __future__ import annotations

import math
from array import array
from importlib import resources
from pathlib import Path

import numpy as np

from calib.drivelog import LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.ingest.common import check_nonempty, make_series, parse_target, sniff_text, to_channel_unit

#: Our Prius DBC, shipped with the package.
PRIUS_DBC = Path(str(resources.files("calib") / "data" / "can" / "prius_iptm.dbc"))
#: opendbc's Toyota 2017 DBC (MIT), shipped with the package.
TOYOTA_2017_DBC = Path(str(resources.files("calib") / "data" / "can" / "toyota_2017.dbc"))

#: Default ``MESSAGE.SIGNAL -> channel`` map (units from the DBC).
DEFAULT_SIGNAL_MAP: dict[str, str] = {
    # prius_iptm.dbc
    "HV_BATTERY.BAT_CURRENT": "bat_current_A",
    "HV_BATTERY.BAT_VOLTAGE": "bat_voltage_V",
    "SPEED.SPEED": "speed_mps",  # also opendbc toyota_2017 SPEED (0xB4)
    "ENGINE_RPM.RPM": "engine_speed_rpm",  # also opendbc toyota_2017 ENGINE_RPM (0x1C4)
    "BATTERY_STATE.SOC": "soc",
    "BATTERY_STATE.BAT_TEMP": "bat_temp_degC",
    "ENGINE_COOLANT.COOLANT_TEMP": "coolant_temp_degC",
    "IPTM_FUEL_ENGINE.FUEL_RATE": "fuel_rate_g_per_s",
    "IPTM_FUEL_ENGINE.ENGINE_TORQUE": "engine_torque_Nm",
    "IPTM_CLIMATE.AMBIENT_TEMP": "ambient_temp_degC",
    "IPTM_CLIMATE.CABIN_TEMP": "cabin_temp_degC",
    "IPTM_CLIMATE.VENT_TEMP": "vent_temp_degC",
    "IPTM_CLIMATE.HVAC_SETPOINT": "hvac_setpoint_degC",
    "IPTM_CLIMATE.BAY_TEMP": "bay_temp_degC",
    "IPTM_HEATER.HEATER_POWER": "heater_power_W",
    "IPTM_HEATER.BLOWER_FLOW": "blower_flow_kg_per_s",
    "IPTM_HEATER.ROAD_GRADE": "grade_rad",
}

CAN_FORMATS = ("candump", "asc", "blf", "trc")
#: iptm-defined log-information message (SYNTHETIC flag), see calib/data/can/README.md.
LOG_INFO_ID = 0x6FF
#: A timestamp stepping back by more than this is an error; smaller steps are sorted (bus/driver jitter).
MAX_BACKSTEP_S = 1.0


def load_dbc(dbc, path_for_errors=None):
    """Load a DBC with cantools; errors name the DBC file."""
    import cantools

    dbc = Path(dbc) if dbc is not None else PRIUS_DBC
    if not dbc.exists():
        raise LogFormatError(dbc, "DBC file not found")
    try:
        return cantools.database.load_file(str(dbc), database_format="dbc", strict=False)
    except Exception as exc:  # noqa: BLE001 - cantools raises many parser types; all mean "bad DBC"
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise LogFormatError(dbc, f"cannot parse DBC: {msg[:200]}") from None


def resolve_signal_map(db, dbc_path, signal_map: dict | None) -> dict[tuple[str, str], tuple[str, str | None]]:
    """``{(message, signal): (channel, unit or None)}`` for the signals of ``db`` we decode.

    Default entries whose message/signal is absent from the DBC are skipped; user entries must exist.
    """
    names = {(m.name, s.name) for m in db.messages for s in m.signals}
    by_signal: dict[str, list[tuple[str, str]]] = {}
    for m, s in names:
        by_signal.setdefault(s, []).append((m, s))
    out = {}
    for key, target in DEFAULT_SIGNAL_MAP.items():
        m, _, s = key.partition(".")
        if (m, s) in names:
            out[(m, s)] = parse_target(target, dbc_path, f"default map {key}")
    for key, target in (signal_map or {}).items():
        if "." in key:
            m, _, s = key.partition(".")
            if (m, s) not in names:
                raise LogFormatError(dbc_path, f"signal map names {key!r}, which is not in the DBC")
            pair = (m, s)
        else:
            cands = by_signal.get(key, [])
            if len(cands) != 1:
                raise LogFormatError(dbc_path, f"signal map key {key!r} is {'ambiguous' if cands else 'not in the DBC'}",
                                     hint="write MESSAGE.SIGNAL")
            pair = cands[0]
        out[pair] = parse_target(target, dbc_path, f"signal map {key}")
    return out


class _Acc:
    """Per-ID growing arrays of timestamps, 8-byte payloads, lengths and source positions."""

    __slots__ = ("t", "data", "dlc", "pos")

    def __init__(self):
        self.t = array("d")
        self.data = bytearray()
        self.dlc = array("B")
        self.pos = array("q")

    def add(self, t: float, data: bytes, pos: int):
        self.t.append(t)
        n = len(data)
        self.dlc.append(min(n, 255))
        self.data += data[:8] if n >= 8 else data + bytes(8 - n)
        self.pos.append(pos)


class FrameCollector:
    """Keep the frames whose ID the DBC decodes into a wanted signal."""

    def __init__(self, wanted_ids):
        self.wanted = set(wanted_ids)
        self.acc: dict[int, _Acc] = {}
        self.long: dict[int, list] = {}  # frames longer than 8 bytes (CAN FD), kept whole
        self.t_first = math.inf
        self.t_prev = -math.inf
        self.n_frames = 0
        self.n_backsteps = 0
        self.max_backstep = 0.0
        self.synthetic_comment = False

    def time(self, t: float, path, where: str):
        """Account a frame time (every frame, wanted or not): start of log and ordering checks."""
        if not math.isfinite(t):
            raise LogFormatError(path, "timestamp is not a finite number", where)
        self.n_frames += 1
        if t < self.t_first:
            self.t_first = t
        if t < self.t_prev:
            back = self.t_prev - t
            if back > MAX_BACKSTEP_S:
                raise LogFormatError(path, f"timestamp goes back by {back:.3f} s", where,
                                     "frames must be in time order (small jitter is sorted)")
            self.n_backsteps += 1
            self.max_backstep = max(self.max_backstep, back)
        else:
            self.t_prev = t

    def frame(self, t: float, can_id: int, data: bytes, pos: int):
        if can_id not in self.wanted:
            return
        if len(data) > 8:
            self.long.setdefault(can_id, []).append((t, bytes(data), pos))
            return
        acc = self.acc.get(can_id)
        if acc is None:
            acc = self.acc[can_id] = _Acc()
        acc.add(t, data, pos)


def _parse_candump(path, col: FrameCollector, ids_cache: dict):
    """Stream a ``candump -L`` log: ``(timestamp) iface ID#DATA`` per line."""
    sniff_text(path, "candump")
    wanted = col.wanted
    with open(path, "r", encoding="utf-8", errors="strict") as fh:
        lineno = 0
        try:
            for lineno, line in enumerate(fh, 1):
                if not line or line.isspace():
                    continue
                if line[0] == "#":
                    if "SYNTHETIC" in line.upper():
                        col.synthetic_comment = True
                    continue
                parts = line.split()
                if len(parts) < 3 or parts[0][0] != "(" or parts[0][-1] != ")":
                    raise LogFormatError(path, f"not a candump -L line: {line.strip()[:60]!r}", f"line {lineno}",
                                         "expected '(timestamp) iface ID#DATA'")
                try:
                    t = float(parts[0][1:-1])
                except ValueError:
                    raise LogFormatError(path, f"bad timestamp {parts[0][:40]!r}", f"line {lineno}") from None
                col.time(t, path, f"line {lineno}")
                idstr, sep, payload = parts[2].partition("#")
                can_id = ids_cache.get(idstr)
                if can_id is None:
                    if not sep or not idstr or len(idstr) > 8:
                        raise LogFormatError(path, f"bad frame {parts[2][:40]!r}", f"line {lineno}")
                    try:
                        can_id = int(idstr, 16)
                    except ValueError:
                        raise LogFormatError(path, f"bad CAN ID {idstr[:20]!r}", f"line {lineno}") from None
                    ids_cache[idstr] = can_id
                if can_id not in wanted:
                    continue
                if payload[:1] == "R":
                    continue  # remote frame: no data
                if payload[:1] == "#":
                    payload = payload[2:]  # CAN FD: '##<flags><data>'
                try:
                    data = bytes.fromhex(payload)
                except ValueError:
                    raise LogFormatError(path, f"bad frame data {payload[:40]!r}", f"line {lineno}") from None
                col.frame(t, can_id, data, lineno)
        except UnicodeDecodeError:
            raise LogFormatError(path, "binary data in a candump text log", f"after line {lineno}") from None


def _parse_python_can(path, fmt: str, col: FrameCollector):
    """Stream .asc/.blf/.trc through python-can's readers; any reader failure is a format error."""
    import can

    reader_cls = {"asc": can.ASCReader, "blf": can.BLFReader, "trc": can.TRCReader}[fmt]
    if fmt in ("asc", "trc"):
        sniff_text(path, fmt.upper())
    i = 0
    try:
        with reader_cls(str(path)) as reader:
            if fmt == "blf":
                # python-can stops quietly at a truncated container: check the header's own size.
                actual = Path(path).stat().st_size
                if reader.file_size and actual < reader.file_size:
                    raise LogFormatError(path, f"truncated BLF file: {actual} of {reader.file_size} bytes")
            for i, msg in enumerate(reader, 1):
                if msg.is_error_frame:
                    continue
                col.time(float(msg.timestamp), path, f"message {i}")
                if msg.is_remote_frame:
                    continue
                col.frame(float(msg.timestamp), int(msg.arbitration_id), bytes(msg.data), i)
    except LogFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - python-can readers raise struct/zlib/ValueError/... on corrupt files
        text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
        raise LogFormatError(path, f"corrupt or truncated {fmt.upper()} file: {text}", f"after message {i}") from None


def _signal_is_vectorisable(msg, sig) -> bool:
    if msg.is_multiplexed() or sig.is_float or msg.length > 8:
        return False
    if sig.byte_order == "little_endian":
        return sig.start + sig.length <= 64
    byte, bit = divmod(sig.start, 8)
    return (7 - byte) * 8 + bit - (sig.length - 1) >= 0


def _bytes_needed(sig) -> int:
    if sig.byte_order == "little_endian":
        return (sig.start + sig.length - 1) // 8 + 1
    byte, bit = divmod(sig.start, 8)
    lsb = (7 - byte) * 8 + bit - (sig.length - 1)
    return 7 - lsb // 8 + 1


def extract_signal(data: np.ndarray, sig) -> np.ndarray:
    """Physical values of ``sig`` from payloads ``data`` (uint8, shape (n, 8)); NaN where not available.

    Implements the DBC bit layout (Intel and Motorola "sawtooth" numbering) on whole arrays.
    """
    n = data.shape[0]
    if n == 0:
        return np.empty(0)
    mask = np.uint64((1 << sig.length) - 1) if sig.length < 64 else np.uint64(0xFFFFFFFFFFFFFFFF)
    if sig.byte_order == "little_endian":
        word = data.view("<u8").reshape(n)
        raw = (word >> np.uint64(sig.start)) & mask
    else:
        word = data.view(">u8").reshape(n)
        byte, bit = divmod(sig.start, 8)
        lsb = (7 - byte) * 8 + bit - (sig.length - 1)
        raw = (word >> np.uint64(lsb)) & mask
    if sig.is_signed:
        r = raw.astype(np.int64)
        half = 1 << (sig.length - 1)
        r = np.where(r >= half, r - (1 << sig.length), r)
        sna = r == -half
        phys = r * float(sig.scale) + float(sig.offset)
        if sig.minimum is not None:
            sna &= phys < float(sig.minimum)
        else:
            sna[:] = False
    else:
        sna = raw == mask
        phys = raw.astype(np.float64) * float(sig.scale) + float(sig.offset)
        if sig.maximum is not None:
            sna &= phys > float(sig.maximum)
        else:
            sna[:] = False
    return np.where(sna, np.nan, phys)


def decode_can_signals(path, *, fmt: str, dbc=None, signals=None, signal_map=None):
    """Decode DBC signals from a CAN log into arrays.

    Parameters
    ----------
    path : str or Path
        The log.
    fmt : {"candump", "asc", "blf", "trc"}
    dbc : str or Path, optional
        DBC file; default our Prius DBC.
    signals : list of str, optional
        ``"MESSAGE.SIGNAL"`` names to decode (physical values in DBC units). Default: the signals of the
        channel map.
    signal_map : dict, optional
        Extra/overriding ``MESSAGE.SIGNAL -> channel`` entries (used when ``signals`` is None).

    Returns
    -------
    result : dict
        ``{"signals": {(message, signal): (t, values)}, "t0": first frame time, "n_frames": int,
        "n_backsteps": int, "max_backstep": float, "map": resolved map, "db": cantools db}``;
        ``t`` is seconds from the first frame of the log.

    Raises
    ------
    LogFormatError
        Malformed/corrupt log, DBC not matching the frames (no frame of a decoded message, or frames
        too short for their signals).
    """
    check_nonempty(path)
    dbc_path = Path(dbc) if dbc is not None else PRIUS_DBC
    db = load_dbc(dbc_path)
    if signals is None:
        smap = resolve_signal_map(db, dbc_path, signal_map)
        if not smap:
            raise LogFormatError(dbc_path, "no signal of this DBC maps to a canonical channel",
                                 hint="pass a signal map (MESSAGE.SIGNAL = 'channel')")
        wanted_pairs = list(smap)
        if ("IPTM_LOG_INFO", "SYNTHETIC") in {(m.name, sg.name) for m in db.messages for sg in m.signals}:
            wanted_pairs.append(("IPTM_LOG_INFO", "SYNTHETIC"))
    else:
        smap = {}
        wanted_pairs = []
        for name in signals:
            m, _, s = name.partition(".")
            try:
                db.get_message_by_name(m).get_signal_by_name(s)
            except KeyError:
                raise LogFormatError(dbc_path, f"signal {name!r} is not in the DBC") from None
            wanted_pairs.append((m, s))
    msgs = {}
    for m, _ in wanted_pairs:
        msg = db.get_message_by_name(m)
        msgs[msg.frame_id] = msg

    col = FrameCollector(msgs)
    if fmt == "candump":
        _parse_candump(path, col, {})
    elif fmt in ("asc", "blf", "trc"):
        _parse_python_can(path, fmt, col)
    else:
        raise LogFormatError(path, f"not a CAN log format: {fmt}")
    if col.n_frames == 0:
        raise LogFormatError(path, "no CAN frames in the file")
    if not (set(col.acc) | set(col.long)) - {LOG_INFO_ID}:
        ids = ", ".join(f"0x{i:X}" for i in sorted(msgs))
        raise LogFormatError(path, f"no frame matches the DBC {dbc_path.name}: none of its decoded messages "
                                   f"({ids}) is on this bus", hint="pass the DBC for this vehicle with --dbc")

    out = {}
    for can_id, msg in msgs.items():
        pairs = [p for p in wanted_pairs if p[0] == msg.name]
        acc = col.acc.get(can_id)
        rows = []
        if acc is not None:
            t = np.frombuffer(acc.t, dtype=float) - col.t_first
            data = np.frombuffer(bytes(acc.data), dtype=np.uint8).reshape(-1, 8)
            dlc = np.frombuffer(acc.dlc, dtype=np.uint8)
            pos = np.frombuffer(acc.pos, dtype=np.int64)
            rows.append((t, data, dlc, pos))
        for _, sname in pairs:
            sig = msg.get_signal_by_name(sname)
            ts, vs = [], []
            for t, data, dlc, pos in rows:
                if _signal_is_vectorisable(msg, sig):
                    need = _bytes_needed(sig)
                    short = np.flatnonzero(dlc < need)
                    if len(short):
                        k = int(short[0])
                        where = (f"line {pos[k]}" if fmt == "candump" else f"message {pos[k]}")
                        raise LogFormatError(path, f"frame 0x{can_id:X} has {int(dlc[k])} data bytes but DBC message "
                                                   f"{msg.name} needs {need} for {sname}", where,
                                             "is this the right DBC for the log?")
                    ts.append(t)
                    vs.append(extract_signal(data, sig))
                else:
                    tt, vv = _decode_slow(path, fmt, msg, sname, t, data, dlc, pos)
                    ts.append(tt)
                    vs.append(vv)
            for t, data, pos in col.long.get(can_id, []):
                tt, vv = _decode_slow_one(path, fmt, msg, sname, t - col.t_first, data, pos)
                ts.append(tt)
                vs.append(vv)
            if ts:
                out[(msg.name, sname)] = (np.concatenate(ts), np.concatenate(vs))
    return {"signals": out, "t0": col.t_first, "synthetic_comment": col.synthetic_comment, "n_frames": col.n_frames, "n_backsteps": col.n_backsteps,
            "max_backstep": col.max_backstep, "map": smap, "db": db, "dbc_path": dbc_path}


def _decode_slow(path, fmt, msg, sname, t, data, dlc, pos):
    vals = np.empty(len(t))
    for k in range(len(t)):
        vals[k] = _decode_slow_one(path, fmt, msg, sname, 0.0, bytes(data[k, : int(dlc[k])]), int(pos[k]))[1][0]
    return t, vals


def _decode_slow_one(path, fmt, msg, sname, t, payload, pos):
    try:
        v = msg.decode(payload, decode_choices=False, scaling=True).get(sname, np.nan)
    except Exception as exc:  # noqa: BLE001 - cantools raises DecodeError/ValueError/IndexError on mismatch
        where = f"line {pos}" if fmt == "candump" else f"message {pos}"
        raise LogFormatError(path, f"frame 0x{msg.frame_id:X} does not decode as DBC message {msg.name}: {exc}",
                             where) from None
    return np.array([t]), np.array([float(v)])


def read_can_streams(path, *, fmt: str, dbc=None, signal_map=None):
    """Read a CAN log into canonical streams (see :func:`decode_can_signals`).

    Returns
    -------
    (Streams, LogMeta)
    """
    res = decode_can_signals(path, fmt=fmt, dbc=dbc, signal_map=signal_map)
    dbc_path = res["dbc_path"]
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format=fmt)
    meta.notes.append(f"decoded with DBC {dbc_path.name}")
    if res["n_backsteps"]:
        meta.notes.append(f"{res['n_backsteps']} frame(s) out of time order by up to "
                          f"{res['max_backstep'] * 1e3:.1f} ms were sorted")
    t0 = res["t0"]
    if t0 > 1e9:  # epoch seconds (candump -L on a live bus); a monotonic clock is not a date
        import datetime as _dt

        meta.start_time = _dt.datetime.fromtimestamp(t0, tz=_dt.timezone.utc).isoformat()
    info = res["signals"].get(("IPTM_LOG_INFO", "SYNTHETIC"))
    if res["synthetic_comment"] or (info is not None and np.any(info[1] == 1)):
        meta.synthetic = True
    parts: dict[str, list] = {}
    for (m, s), (ch, unit) in res["map"].items():
        if (m, s) not in res["signals"]:
            continue
        t, v = res["signals"][(m, s)]
        sig = res["db"].get_message_by_name(m).get_signal_by_name(s)
        src_unit = unit or sig.unit
        if not src_unit:
            raise LogFormatError(dbc_path, f"signal {m}.{s} has no unit", hint="give one in the signal map: 'channel [unit]'")
        v = to_channel_unit(v, src_unit, ch, dbc_path, f"signal {m}.{s}")
        parts.setdefault(ch, []).append((t, v))
        meta.channel_sources.setdefault(ch, f"{m}.{s}")
        meta.original_units.setdefault(ch, src_unit)
    streams = {}
    for ch, chunks in parts.items():
        s = make_series(np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]), ch)
        if len(s):
            streams[ch] = s
    return streams, meta
