"""CAN dumps (candump -L, .asc, .blf, .trc) decoded against a DBC with cantools.

Memory stays bounded on long logs: frames are streamed; only frames whose ID is in the DBC *and* carries
a signal we want are kept, as 8-byte payloads and float timestamps in growing arrays (16 bytes a frame);
signals are then extracted per message with numpy bit operations derived from cantools' signal
definitions. No per-frame Python dicts, no DataFrame of all frames. Multiplexed, float or longer-than-8-byte
messages fall back to cantools' per-frame decoder.

Signal -> channel map: keys ``"MESSAGE.SIGNAL"`` (or ``"SIGNAL"`` when unique in the DBC), values
``"channel"`` or ``"channel [unit]"`` (the unit overrides the DBC's). :data:`DEFAULT_SIGNAL_MAP` covers
our Prius DBC (``calib/data/can/prius_iptm.dbc``) and opendbc's ``toyota_2017.dbc`` (SPEED, ENGINE_RPM).

Identity: a frame is a DBC message's only when its frame type (standard 11-bit / extended 29-bit) is the
message's, and the DBC is decoded on one bus (candump interface, ASC/BLF/TRC channel): the one with most of
its messages unless ``bus=`` names another. Frames of other buses and 29-bit look-alikes of 11-bit IDs are
counted and named in ``LogMeta.notes``, never merged. OBD-II service 01 responses (:mod:`calib.ingest.obd`)
are read besides the DBC's messages.

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
from calib.ingest import obd as _obd
from calib.ingest.common import (
    check_nonempty,
    fuel_from_maf,
    check_unit,
    make_series,
    parse_target,
    sniff_text,
    sniff_text_lenient,
    split_spec,
    to_channel_unit,
)
from calib.ingest.damage import Damage, quiet_libraries
from calib.ingest.dbc import PRIUS_DBC, _bytes_needed, _signal_is_vectorisable, extract_signal, load_dbc  # noqa: F401
from calib.units import GASOLINE_DENSITY_KG_PER_L, convert

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

#: The four wheel speeds (opendbc toyota_2017 WHEEL_SPEEDS, 0xAA). When a log carries all four, vehicle
#: speed is their mean and the dashboard signal mapped to ``speed_mps`` is only the fallback: Toyota's
#: dashboard SPEED reads about 2 % high, as speedometers are allowed to. Other DBCs: map signals to
#: ``wheel_speed_fl``/``_fr``/``_rl``/``_rr`` (optionally with a unit) in the signal map.
WHEEL_TARGETS = ("wheel_speed_fl", "wheel_speed_fr", "wheel_speed_rl", "wheel_speed_rr")
DEFAULT_WHEEL_MAP: dict[str, str] = {
    "WHEEL_SPEEDS.WHEEL_SPEED_FL": "wheel_speed_fl",
    "WHEEL_SPEEDS.WHEEL_SPEED_FR": "wheel_speed_fr",
    "WHEEL_SPEEDS.WHEEL_SPEED_RL": "wheel_speed_rl",
    "WHEEL_SPEEDS.WHEEL_SPEED_RR": "wheel_speed_rr",
}

CAN_FORMATS = ("candump", "asc", "blf", "trc")
#: iptm-defined log-information message (SYNTHETIC flag), see calib/data/can/README.md.
LOG_INFO_ID = 0x6FF
#: A timestamp stepping back by more than this is an error; smaller steps are sorted (bus/driver jitter).
MAX_BACKSTEP_S = 1.0


def resolve_signal_map(db, dbc_path, signal_map: dict | None) -> dict[tuple[str, str], tuple[str, str | None]]:
    """``{(message, signal): (channel, unit or None)}`` for the signals of ``db`` we decode.

    Default entries whose message/signal is absent from the DBC are skipped; user entries must exist.
    """
    names = {(m.name, s.name) for m in db.messages for s in m.signals}
    by_signal: dict[str, list[tuple[str, str]]] = {}
    for m, s in names:
        by_signal.setdefault(s, []).append((m, s))
    out = {}
    for key, target in {**DEFAULT_SIGNAL_MAP, **DEFAULT_WHEEL_MAP}.items():
        m, _, s = key.partition(".")
        if (m, s) in names:
            out[(m, s)] = _parse_can_target(target, dbc_path, f"default map {key}")
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
        out[pair] = _parse_can_target(target, dbc_path, f"signal map {key}")
    return out


def _parse_can_target(target, path, where):
    """``parse_target`` plus the wheel-speed pseudo-channels (checked as speeds)."""
    name, unit = split_spec(str(target)) if not isinstance(target, (dict, list, tuple)) else (None, None)
    if name is not None and name.strip().lower() in WHEEL_TARGETS:
        if unit is not None:
            check_unit(unit, "speed_mps", path, where)
        return name.strip().lower(), unit
    return parse_target(target, path, where)


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


#: Frame kinds (:meth:`FrameCollector.kind`): not kept, a DBC message, an OBD-II response, an ID whose value
#: is a DBC message's but of the other frame type (standard/extended), an OBD-II request.
OTHER, DBC_FRAME, OBD_RESPONSE, TYPE_MISMATCH, OBD_REQUEST = 0, 1, _obd.RESPONSE, 3, _obd.REQUEST


class FrameCollector:
    """Keep the frames a DBC message or an OBD-II response needs, per bus; hand damaged ones to ``damage``.

    A frame's identity is (bus, frame type, ID): ``acc`` and ``long`` are keyed ``(bus, extended, id)``.
    ``dbc_ids`` are ``(id, extended)`` pairs. With ``bus`` given, frames of other buses are only counted
    (``elsewhere``), except the log-information message, which labels the whole log.
    """

    def __init__(self, dbc_ids, damage: Damage | None = None, bus: str | None = None, obd: bool = True):
        self.dbc_ids = set(dbc_ids)
        self._dbc_values = {i for i, _ in self.dbc_ids}
        self.obd = obd
        self.bus = bus
        self._kinds: dict[tuple[int, bool], int] = {}
        self.acc: dict[tuple, _Acc] = {}
        self.long: dict[tuple, list] = {}  # frames longer than 8 bytes (CAN FD), kept whole
        self.mismatch: dict[tuple, int] = {}  # (bus, extended, id) -> frames of the wrong frame type
        self.elsewhere: dict[tuple, int] = {}  # (bus, kind) -> frames not kept because bus= names another
        self.requests: dict[str, int] = {}  # bus -> OBD-II requests
        self.t_first = math.inf
        self.t_prev = -math.inf
        self.n_frames = 0
        self.n_backsteps = 0
        self.max_backstep = 0.0
        self.synthetic_comment = False
        self.damage = damage if damage is not None else Damage("", strict=True)
        # The last accepted frame, so that a garbled timestamp that jumped forward can be taken back.
        self._t_before_last = -math.inf
        self._last_stored = None
        self._last_stored_long = False
        self._last_where = ""

    def kind(self, can_id: int, extended: bool) -> int:
        """What a frame of this ID and type is to this log (cached)."""
        k = self._kinds.get((can_id, extended))
        if k is None:
            if (can_id, extended) in self.dbc_ids:
                k = DBC_FRAME
            elif self.obd and _obd.classify(can_id, extended):
                k = _obd.classify(can_id, extended)
            elif can_id in self._dbc_values:
                k = TYPE_MISMATCH
            else:
                k = OTHER
            self._kinds[(can_id, extended)] = k
        return k

    def _unstore_last(self):
        key = self._last_stored
        if key is None:
            return
        if self._last_stored_long:
            self.long[key].pop()
        else:
            acc = self.acc[key]
            acc.t.pop()
            del acc.data[-8:]
            acc.dlc.pop()
            acc.pos.pop()
        self._last_stored = None

    def time(self, t: float, path, where: str) -> bool:
        """Account a frame time (every frame, wanted or not): start of log and ordering checks.

        Returns False when the frame is damaged (recorded in ``damage``) and must be skipped.
        """
        if self.t_prev <= t < math.inf:  # the usual case, kept short: it runs once per frame
            self.n_frames += 1
            if t < self.t_first:
                self.t_first = t
            self._last_stored = None
            self._last_where = where
            self._t_before_last = self.t_prev
            self.t_prev = t
            if self.damage._open_span is not None:
                self.damage.good(t)
            return True
        if not math.isfinite(t):
            self.damage.bad(LogFormatError(path, "timestamp is not a finite number", where), self.t_prev)
            return False
        if t < self.t_prev:
            back = self.t_prev - t
            if back > MAX_BACKSTEP_S:
                err = LogFormatError(path, f"timestamp goes back by {back:.3f} s", where,
                                     "frames must be in time order (small jitter is sorted)")
                if self.damage.strict:
                    raise err
                prev_jump = self.t_prev - self._t_before_last
                if (self.n_frames > 1 and prev_jump > MAX_BACKSTEP_S
                        and t >= self._t_before_last - MAX_BACKSTEP_S):
                    # The previous frame's time jumped forward and this one fits the time before it:
                    # the previous timestamp was the garbled one.
                    self._unstore_last()
                    self.n_frames -= 1
                    self.damage.bad(LogFormatError(path, f"timestamp jumps forward by {prev_jump:.3f} s",
                                                   self._last_where), self._t_before_last)
                    self.t_prev = self._t_before_last
                else:
                    self.damage.bad(err, self.t_prev)
                    return False
            else:
                self.n_backsteps += 1
                self.max_backstep = max(self.max_backstep, back)
        self.n_frames += 1
        if t < self.t_first:
            self.t_first = t
        self._last_stored = None
        self._last_where = where
        if t >= self.t_prev:
            self._t_before_last = self.t_prev
            self.t_prev = t
        if self.damage._open_span is not None:
            self.damage.good(t)
        return True

    def finish(self, path):
        """End of the log: a last frame whose time jumped far forward has no later frame to expose it."""
        jump = self.t_prev - self._t_before_last
        if self.damage.strict or self.n_frames < 3 or not jump > MAX_BACKSTEP_S or not self.damage:
            return
        # Only in a log already known to be damaged: a clean log may well end after a pause.
        self._unstore_last()
        self.n_frames -= 1
        self.damage.bad(LogFormatError(path, f"timestamp jumps forward by {jump:.3f} s", self._last_where),
                        self._t_before_last)
        self.t_prev = self._t_before_last

    def frame(self, t: float, bus: str, can_id: int, extended: bool, kind: int, data: bytes, pos: int):
        """Keep (or count) one frame of a non-zero ``kind`` whose time :meth:`time` accepted."""
        if kind == TYPE_MISMATCH:
            key = (bus, extended, can_id)
            self.mismatch[key] = self.mismatch.get(key, 0) + 1
            return
        if kind == OBD_REQUEST:
            self.requests[bus] = self.requests.get(bus, 0) + 1
            return
        if self.bus is not None and bus != self.bus and not (kind == DBC_FRAME and can_id == LOG_INFO_ID):
            self.elsewhere[(bus, kind)] = self.elsewhere.get((bus, kind), 0) + 1
            return
        key = (bus, extended, can_id)
        if len(data) > 8:
            self.long.setdefault(key, []).append((t, bytes(data), pos))
            self._last_stored, self._last_stored_long = key, True
            return
        acc = self.acc.get(key)
        if acc is None:
            acc = self.acc[key] = _Acc()
        acc.add(t, data, pos)
        self._last_stored, self._last_stored_long = key, False


def _parse_candump(path, col: FrameCollector, ids_cache: dict):
    """Stream a ``candump -L`` log: ``(timestamp) iface ID#DATA`` per line; bad lines go to ``col.damage``."""
    dmg = col.damage
    if dmg.strict:
        sniff_text(path, "candump")
    else:
        sniff_text_lenient(path, "candump")
    kind = col.kind

    def bad(problem, lineno, hint=None):
        dmg.bad(LogFormatError(path, problem, f"line {lineno}", hint), col.t_prev)

    # Bytes that are not UTF-8 become lone surrogates, which fail the timestamp/ID/data parse of their
    # own line: the line is named (and skipped unless strict).
    with open(path, "r", encoding="utf-8", errors="surrogateescape") as fh:
        lineno = 0
        try:
            for lineno, line in enumerate(fh, 1):
                if not line or line.isspace():
                    continue
                if line[0] == "#":
                    if "SYNTHETIC" in line.upper():
                        col.synthetic_comment = True
                    continue
                if line[-1] != "\n":
                    bad("line cut short (no line end)", lineno)
                    continue
                parts = line.split()
                if len(parts) < 3 or parts[0][0] != "(" or parts[0][-1] != ")":
                    bad(f"not a candump -L line: {_show(line.strip())}", lineno, "expected '(timestamp) iface ID#DATA'")
                    continue
                try:
                    t = float(parts[0][1:-1])
                except ValueError:
                    bad(f"bad timestamp {_show(parts[0])}", lineno)
                    continue
                idstr, sep, payload = parts[2].partition("#")
                ident = ids_cache.get(idstr)
                if ident is None:
                    if not sep or not idstr or len(idstr) > 8:
                        bad(f"bad frame {_show(parts[2])}", lineno)
                        continue
                    try:
                        can_id = int(idstr, 16)
                    except ValueError:
                        bad(f"bad CAN ID {_show(idstr)}", lineno)
                        continue
                    # candump writes standard IDs with 3 hex digits and extended (29-bit) ones with 8.
                    ext = len(idstr) > 3
                    ident = ids_cache[idstr] = (can_id, ext, kind(can_id, ext))
                if not ident[2]:
                    col.time(t, path, f"line {lineno}")
                    continue
                if payload[:1] == "R":
                    col.time(t, path, f"line {lineno}")
                    continue  # remote frame: no data
                if payload[:1] == "#":
                    payload = payload[2:]  # CAN FD: '##<flags><data>'
                try:
                    data = bytes.fromhex(payload)
                except ValueError:
                    bad(f"bad frame data {_show(payload)}", lineno)
                    continue
                if col.time(t, path, f"line {lineno}"):
                    col.frame(t, parts[1], ident[0], ident[1], ident[2], data, lineno)
        except UnicodeDecodeError:
            raise LogFormatError(path, "binary data in a candump text log", f"after line {lineno}") from None


def _show(text: str) -> str:
    return repr(text[:60].encode("utf-8", "replace").decode("utf-8", "replace"))


def _parse_python_can(path, fmt: str, col: FrameCollector):
    """Stream .asc/.blf/.trc through python-can's record parsing; damaged records go to ``col.damage``."""
    from calib.ingest.canreaders import READERS, Bad  # python-can is imported only for these formats

    dmg = col.damage
    if fmt in ("asc", "trc"):
        if dmg.strict:
            sniff_text(path, fmt.upper())
        else:
            sniff_text_lenient(path, fmt.upper())
    i = 0
    reader = None
    try:
        with quiet_libraries() as chatter:
            try:
                reader = READERS[fmt](path)
            except LogFormatError:
                raise
            except Exception as exc:  # noqa: BLE001 - python-can raises struct/ValueError/... on a bad header
                text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
                raise LogFormatError(path, f"corrupt {fmt.upper()} file header: {text}") from None
            header_size = getattr(reader, "file_size", 0) if fmt == "blf" else 0
            actual = Path(path).stat().st_size
            if fmt == "blf" and dmg.strict and header_size and actual < header_size:
                raise LogFormatError(path, f"truncated BLF file: {actual} of {header_size} bytes")
            with reader:
                for item in reader:
                    if type(item) is Bad:
                        if item.truncated:
                            a = item.byte_range[0]
                            dmg.truncated(a, max(actual, header_size) if a < actual else None, col.t_prev,
                                          item.err.problem)
                        else:
                            dmg.bad(item.err, col.t_prev, byte_range=item.byte_range)
                        continue
                    i += 1
                    if item.is_error_frame:
                        continue
                    pos = reader._lines.n if fmt != "blf" else i
                    where = f"line {pos}" if fmt != "blf" else f"message {i}"
                    if not col.time(float(item.timestamp), path, where):
                        continue
                    if item.is_remote_frame:
                        continue
                    can_id, ext = int(item.arbitration_id), bool(item.is_extended_id)
                    k = col.kind(can_id, ext)
                    if k:
                        col.frame(float(item.timestamp), _bus_name(fmt, item.channel), can_id, ext, k,
                                  bytes(item.data), pos)
            if fmt == "blf" and header_size and actual < header_size and not reader.hit_truncation:
                dmg.truncated(actual, header_size, col.t_prev, f"file is {actual} of the {header_size} bytes its header gives")
        for text in chatter:
            dmg.bad(LogFormatError(path, f"{text[:80].replace(':', ' -')} (reported by python-can)", "python-can"))
    except LogFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - python-can readers raise struct/zlib/ValueError/... on corrupt files
        text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
        err = LogFormatError(path, f"corrupt or truncated {fmt.upper()} file: {text}", f"after message {i}")
        if dmg.strict or col.n_frames == 0:
            raise err from None
        dmg.bad(err, col.t_prev)  # the reader cannot go on: the rest of the file is lost


def _bus_name(fmt: str, channel) -> str:
    """A python-can message's bus as its file writes it: ASC and BLF count channels from 1 (python-can
    from 0), TRC as written."""
    if channel is None:
        return "1"  # a file format without channels: one bus
    if isinstance(channel, int) and fmt in ("asc", "blf"):
        return str(channel + 1)
    return str(channel)


def decode_can_signals(path, *, fmt: str, dbc=None, signals=None, signal_map=None, strict: bool = False,
                       bus=None):
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
    strict : bool
        Raise at the first damaged line/record instead of skipping it (see :mod:`calib.ingest.damage`).
    bus : str, optional
        The bus to decode the DBC on (candump interface ``can0``; ASC/BLF/TRC channel number as the file
        writes it, from 1). Default: the bus that carries most frames of the DBC's messages.

    Returns
    -------
    result : dict
        ``{"signals": {(message, signal): (t, values)}, "t0": first frame time, "n_frames": int,
        "n_backsteps": int, "max_backstep": float, "map": resolved map, "db": cantools db,
        "damage": dict (empty for an intact log), "bus": the bus decoded, "dbc_frames_per_bus": dict,
        "obd": calib.ingest.obd.ObdDecoded or None, "obd_bus": str or None, "notes": list}``;
        ``t`` is seconds from the first frame of the log. A frame is a DBC message's only when its bus
        is the one decoded and its frame type (standard/extended) is the message's.

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
        msgs[(msg.frame_id, bool(msg.is_extended_frame))] = msg

    bus = None if bus is None else str(bus)
    dmg = Damage(path, strict=strict, unit="line" if fmt in ("candump", "asc", "trc") else "record")
    col = FrameCollector(msgs, dmg, bus=bus)
    if fmt == "candump":
        _parse_candump(path, col, {})
    elif fmt in ("asc", "blf", "trc"):
        _parse_python_can(path, fmt, col)
    else:
        raise LogFormatError(path, f"not a CAN log format: {fmt}")
    col.finish(path)
    if col.n_frames == 0:
        extra = f" ({dmg.n} damaged {dmg.unit}(s) skipped, first at {dmg.where[0]})" if dmg.n else ""
        raise LogFormatError(path, "no CAN frames in the file" + extra)

    notes: list[str] = []
    dbc_n, obd_n = _frames_per_bus(col)
    if bus is not None and bus not in dbc_n and bus not in obd_n:
        seen = _fmt_bus_counts({b: dbc_n.get(b, 0) + obd_n.get(b, 0) for b in set(dbc_n) | set(obd_n)})
        raise LogFormatError(path, f"no frame of DBC {dbc_path.name} and no OBD-II response on bus {bus!r}",
                             hint=f"buses with such frames: {seen}" if seen else "check the bus name")
    if not dbc_n and not obd_n:
        ids = ", ".join(_id_text(i, e) for i, e in sorted(msgs) if i != LOG_INFO_ID)
        wrong = sum(col.mismatch.values())
        extra = (f"; {wrong:,} frame(s) carry one of these ID values with the other frame type "
                 "(standard 11-bit vs extended 29-bit), which is not the same message") if wrong else ""
        raise LogFormatError(path, f"no frame matches the DBC {dbc_path.name}: none of its decoded messages "
                                   f"({ids}) is on this bus, and no OBD-II response either{extra}",
                             hint="pass the DBC for this vehicle with --dbc")
    chosen = bus if bus is not None else _busiest(dbc_n)
    if chosen is not None and chosen in dbc_n:
        tied = sorted(b for b, n in dbc_n.items() if n == dbc_n[chosen] and b != chosen)
        how = "chosen with --bus" if bus is not None else (
            "the only bus with its messages" if len(dbc_n) == 1 else
            f"as many as bus {', '.join(tied)}: the first by name; say which with --bus" if tied else
            "the bus with most of its messages")
        notes.append(f"DBC {dbc_path.name} decoded on bus {chosen} ({dbc_n[chosen]:,} frames, {how})")
    else:
        notes.append(f"no frame matches the DBC {dbc_path.name}" + (f" on bus {chosen}" if chosen else "")
                     + ": only OBD-II responses decoded")
    for b, n in sorted(dbc_n.items()):
        if b != chosen:
            notes.append(f"bus {b}: {n:,} frames with DBC IDs not decoded; pass --bus {b} to read that bus")
    for (b, ext, cid), n in sorted(col.mismatch.items()):
        other = msgs.get((cid, not ext))
        notes.append(f"bus {b}: {n:,} {_frame_type(ext)} frames with ID {_id_text(cid, ext)} not decoded: the DBC's "
                     f"{other.name if other else 'message'} with that ID value is a {_frame_type(not ext)} frame")

    out = {}
    for (can_id, ext), msg in msgs.items():
        pairs = [p for p in wanted_pairs if p[0] == msg.name]
        # The log-information message labels the whole log: taken from any bus.
        keys = [k for k in col.acc if k[1:] == (ext, can_id) and (k[0] == chosen or can_id == LOG_INFO_ID)]
        long_keys = [k for k in col.long if k[1:] == (ext, can_id) and (k[0] == chosen or can_id == LOG_INFO_ID)]
        rows = []
        for key in keys:
            acc = col.acc[key]
            with np.errstate(invalid="ignore", over="ignore"):  # a non-finite time is counted later
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
                        where = (f"line {pos[k]}" if fmt in ("candump", "asc", "trc") else f"message {pos[k]}")
                        err = LogFormatError(path, f"frame {_id_text(can_id, ext)} has {int(dlc[k])} data bytes but "
                                                   f"DBC message {msg.name} needs {need} for {sname}", where,
                                             "is this the right DBC for the log?")
                        if 2 * len(short) > len(dlc):
                            raise err  # most frames too short: the DBC does not fit, not damage
                        if sname == pairs[0][1]:
                            dmg.bad(err, None, count=len(short))
                        ok = dlc >= need
                        t, data, dlc, pos = t[ok], data[ok], dlc[ok], pos[ok]
                    ts.append(t)
                    vs.append(extract_signal(data, sig))
                else:
                    tt, vv = _decode_slow(path, fmt, msg, sname, t, data, dlc, pos, dmg)
                    ts.append(tt)
                    vs.append(vv)
            for key in long_keys:
                for t, data, pos in col.long[key]:
                    tt, vv = _decode_slow_one(path, fmt, msg, sname, t - col.t_first, data, pos, dmg)
                    ts.append(tt)
                    vs.append(vv)
            if ts:
                out[(msg.name, sname)] = (np.concatenate(ts), np.concatenate(vs))

    obd, obd_bus = None, None
    if obd_n:
        obd_bus = bus if bus is not None else (chosen if chosen in obd_n else _busiest(obd_n))
        frames = {}
        for (b, ext, can_id), acc in col.acc.items():
            if b == obd_bus and col.kind(can_id, ext) == OBD_RESPONSE:
                frames[(ext, can_id)] = (np.frombuffer(acc.t, dtype=float) - col.t_first,
                                         np.frombuffer(bytes(acc.data), dtype=np.uint8).reshape(-1, 8),
                                         np.frombuffer(acc.dlc, dtype=np.uint8))
        if frames:
            obd = _obd.decode_obd(frames)
            notes.append(f"OBD-II responses decoded on bus {obd_bus}: {obd.n_responses:,} response frames"
                         + (f", {col.requests[obd_bus]:,} requests (no data)" if col.requests.get(obd_bus) else ""))
        for b, n in sorted(obd_n.items()):
            if b != obd_bus:
                notes.append(f"bus {b}: {n:,} OBD-II response frames not decoded; pass --bus {b} to read that bus")
    return {"signals": out, "t0": col.t_first, "synthetic_comment": col.synthetic_comment, "n_frames": col.n_frames,
            "n_backsteps": col.n_backsteps, "max_backstep": col.max_backstep, "map": smap, "db": db,
            "dbc_path": dbc_path, "damage": dmg.finish(col.t_first, col.t_prev), "bus": chosen,
            "dbc_frames_per_bus": dbc_n, "obd": obd, "obd_bus": obd_bus, "notes": notes}


def _frames_per_bus(col: FrameCollector) -> tuple[dict, dict]:
    """Frames of DBC messages (the log-information message aside) and OBD-II responses, per bus."""
    dbc_n: dict[str, int] = {}
    obd_n: dict[str, int] = {}
    sizes = [(k, len(a.t)) for k, a in col.acc.items()] + [(k, len(v)) for k, v in col.long.items()]
    for (b, ext, can_id), n in sizes:
        kind = col.kind(can_id, ext)
        if kind == DBC_FRAME and can_id != LOG_INFO_ID:
            dbc_n[b] = dbc_n.get(b, 0) + n
        elif kind == OBD_RESPONSE:
            obd_n[b] = obd_n.get(b, 0) + n
    for (b, kind), n in col.elsewhere.items():
        target = dbc_n if kind == DBC_FRAME else obd_n
        target[b] = target.get(b, 0) + n
    return dbc_n, obd_n


def _busiest(counts: dict) -> str | None:
    """The bus with most frames (ties: the first name in order)."""
    return min(counts, key=lambda b: (-counts[b], b)) if counts else None


def _fmt_bus_counts(counts: dict) -> str:
    return ", ".join(f"{b} ({n:,} frames)" for b, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def _id_text(can_id: int, extended: bool) -> str:
    return f"0x{can_id:08X}" if extended else f"0x{can_id:03X}"


def _frame_type(extended: bool) -> str:
    return "extended (29-bit)" if extended else "standard (11-bit)"


def _decode_slow(path, fmt, msg, sname, t, data, dlc, pos, dmg=None):
    vals = np.empty(len(t))
    for k in range(len(t)):
        vals[k] = _decode_slow_one(path, fmt, msg, sname, 0.0, bytes(data[k, : int(dlc[k])]), int(pos[k]), dmg)[1][0]
    return t, vals


def _decode_slow_one(path, fmt, msg, sname, t, payload, pos, dmg=None):
    try:
        v = msg.decode(payload, decode_choices=False, scaling=True).get(sname, np.nan)
    except Exception as exc:  # noqa: BLE001 - cantools raises DecodeError/ValueError/IndexError on mismatch
        where = f"line {pos}" if fmt in ("candump", "asc", "trc") else f"message {pos}"
        err = LogFormatError(path, f"frame 0x{msg.frame_id:X} does not decode as DBC message {msg.name}: {exc}", where)
        if dmg is None:
            raise err from None
        dmg.bad(err, None)
        return np.array([t]), np.array([np.nan])
    return np.array([t]), np.array([float(v)])


def wheel_mean_speed(wheels: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """Mean of the four wheel speeds ``{target: (t, v m/s, ...)}``: (t, v), or None unless all four are there.

    The wheels' own times when they share them (one message carries all four, as on Toyota); otherwise
    the other three are interpolated onto the first one's times. A time with any wheel missing is dropped.
    """
    if set(wheels) != set(WHEEL_TARGETS) or any(len(wheels[w][0]) == 0 for w in WHEEL_TARGETS):
        return None
    t = np.asarray(wheels[WHEEL_TARGETS[0]][0], dtype=float)
    vals = []
    for w in WHEEL_TARGETS:
        tw, vw = np.asarray(wheels[w][0], dtype=float), np.asarray(wheels[w][1], dtype=float)
        if len(tw) == len(t) and np.array_equal(tw, t):
            vals.append(vw)
        else:
            ok = np.isfinite(vw)
            if ok.sum() < 2:
                return None
            o = np.argsort(tw[ok], kind="stable")
            vi = np.interp(t, tw[ok][o], vw[ok][o], left=np.nan, right=np.nan)
            vals.append(vi)
    v = np.mean(vals, axis=0)
    ok = np.isfinite(v)
    if not ok.any():
        return None
    return t[ok], v[ok]


def _speed_from_wheels(wheels: dict, parts: dict, meta) -> None:
    """Vehicle speed from the four wheel speeds when the log has them, else the dashboard signal."""
    mean = wheel_mean_speed(wheels)
    if mean is None:
        if wheels:
            meta.notes.append(f"speed: only {len(wheels)} of 4 wheel speeds in the log; dashboard signal used")
        if "speed_mps" in meta.channel_sources:
            meta.notes.append(f"speed from the dashboard signal {meta.channel_sources['speed_mps']}")
        return
    dash = meta.channel_sources.get("speed_mps")
    parts["speed_mps"] = [(mean[0], mean[1], None)]
    meta.channel_sources["speed_mps"] = "mean of " + ", ".join(wheels[w][2] for w in WHEEL_TARGETS)
    meta.original_units["speed_mps"] = wheels[WHEEL_TARGETS[0]][3]
    meta.notes.append("speed from the mean of the four wheel speeds"
                      + (f" (dashboard {dash} is the fallback, not used)" if dash else ""))


def read_can_streams(path, *, fmt: str, dbc=None, signal_map=None, strict: bool = False, bus=None):
    """Read a CAN log into canonical streams (see :func:`decode_can_signals`).

    The DBC is decoded on one bus (``bus``, else the one with most of its messages); OBD-II service 01
    responses (:mod:`calib.ingest.obd`) add the channels the DBC does not give. ``meta.channel_sources``
    names the bus (``"can0:SPEED.SPEED"``); ``meta.notes`` says which bus was read and what other buses,
    frame-type collisions and OBD-II responses were left out.

    Returns
    -------
    (Streams, LogMeta)
        ``meta.damage`` says what a damaged log lost (empty when intact).
    """
    res = decode_can_signals(path, fmt=fmt, dbc=dbc, signal_map=signal_map, strict=strict, bus=bus)
    dbc_path = res["dbc_path"]
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format=fmt)
    meta.damage = res["damage"]
    meta.notes.append(f"decoded with DBC {dbc_path.name}")
    meta.notes.extend(res["notes"])
    if res["n_backsteps"]:
        meta.notes.append(f"{res['n_backsteps']} frame(s) out of time order by up to "
                          f"{res['max_backstep'] * 1e3:.1f} ms were sorted")
    t0 = res["t0"]
    if t0 > 1e9:  # epoch seconds (candump -L on a live bus); a monotonic clock is not a date
        import datetime as _dt

        try:
            meta.start_time = _dt.datetime.fromtimestamp(t0, tz=_dt.timezone.utc).isoformat()
        except (OverflowError, ValueError, OSError):  # beyond year 9999 or the platform's time_t: not a date
            meta.notes.append(f"warning: the first time stamp {t0:.6g} s is not a date; no start time recorded")
    info = res["signals"].get(("IPTM_LOG_INFO", "SYNTHETIC"))
    if res["synthetic_comment"] or (info is not None and np.any(info[1] == 1)):
        meta.synthetic = True
    chosen = res["bus"]
    parts: dict[str, list] = {}
    wheels: dict[str, tuple] = {}
    for (m, s), (ch, unit) in res["map"].items():
        if (m, s) not in res["signals"]:
            continue
        t, v = res["signals"][(m, s)]
        sig = res["db"].get_message_by_name(m).get_signal_by_name(s)
        src_unit = unit or sig.unit
        if not src_unit:
            raise LogFormatError(dbc_path, f"signal {m}.{s} has no unit", hint="give one in the signal map: 'channel [unit]'")
        # NaN from an integer signal is its "not available" value: no sample, not a bad reading.
        absent = np.isnan(v) if not sig.is_float else None
        if ch in WHEEL_TARGETS:
            wheels[ch] = (t, to_channel_unit(v, src_unit, "speed_mps", dbc_path, f"signal {m}.{s}"),
                          f"{chosen}:{m}.{s}", src_unit)
            continue
        v = to_channel_unit(v, src_unit, ch, dbc_path, f"signal {m}.{s}")
        parts.setdefault(ch, []).append((t, v, absent))
        meta.channel_sources.setdefault(ch, f"{chosen}:{m}.{s}")
        meta.original_units.setdefault(ch, src_unit)
    _speed_from_wheels(wheels, parts, meta)
    streams = {}
    extra = _obd_parts(res, parts, meta) if res["obd"] is not None else {}
    for ch, chunks in parts.items():
        absent = None
        if any(c[2] is not None for c in chunks):
            absent = np.concatenate([c[2] if c[2] is not None else np.zeros(len(c[0]), bool) for c in chunks])
        s = make_series(np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]), ch,
                        meta=meta, absent=absent)
        if len(s):
            streams[ch] = s
    for ch, s in extra.items():
        if len(s):
            streams[ch] = s
    return streams, meta


def _obd_parts(res, parts: dict, meta) -> dict:
    """Add the OBD-II channels the DBC did not give to ``parts``; the fuel estimate from MAF is returned
    as a finished stream (it is built and labelled by :func:`calib.ingest.common.fuel_from_maf`)."""
    obd, bus = res["obd"], res["obd_bus"]
    meta.notes.extend(obd.notes)
    extra = {}
    for pid, (t, v, label) in sorted(obd.series.items()):
        _, ch, what = _obd.PIDS[pid]
        src = f"{bus}:{label}"
        unit = obd.units[pid]
        if pid == _obd.PID_FUEL_LEVEL:
            ok = np.isfinite(v)
            rng = f", {np.min(v[ok]):.0f}-{np.max(v[ok]):.0f} {unit}" if ok.any() else ""
            meta.notes.append(f"{src} ({what}): {len(v):,} samples{rng}; not a canonical channel, not used")
            continue
        if pid == _obd.PID_MAF:
            if "fuel_rate_g_per_s" in parts or _obd.PID_FUEL_RATE in obd.series:
                used = meta.channel_sources.get("fuel_rate_g_per_s") or f"{bus}:{obd.series[_obd.PID_FUEL_RATE][2]}"
                meta.notes.append(f"{src} ({what}): {len(v):,} samples not used: fuel comes from {used}")
            else:
                extra["fuel_rate_g_per_s"] = fuel_from_maf(t, convert(v, unit, "g/s"), meta, src)
            continue
        if ch in parts:
            meta.notes.append(f"{src} ({what}, {len(v):,} samples) not used: {ch} comes from "
                              f"{meta.channel_sources.get(ch, 'the DBC')}")
            continue
        parts[ch] = [(t, to_channel_unit(v, unit, ch, _obd.OBD2_DBC, label), None)]
        meta.channel_sources[ch] = src
        meta.original_units[ch] = unit
        if pid == _obd.PID_FUEL_RATE:
            meta.notes.append(f"fuel_rate_g_per_s from {src}: the engine ECU's own computed fuel rate (from its "
                              f"injection), not a flow-meter measurement; L/h converted at "
                              f"{GASOLINE_DENSITY_KG_PER_L} kg/L gasoline")
    return extra

