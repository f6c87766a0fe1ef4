"""MCAP logs with JSON-encoded messages (the ``mcap`` package).

Timestamps are the messages' ``log_time`` (ns). The topic/field -> channel map is configuration:
``{topic: {field: "channel [unit]"}}`` (a dotted field reaches into nested objects). The default,
:data:`DEFAULT_TOPIC_MAP`, is the layout :mod:`calib.ingest.writers` produces; pass ``topic_map`` to read other
layouts (its topics replace the default's topics of the same name; other default topics stay).
Messages slightly out of log-time order are sorted and counted in ``meta.notes``.
"""
from __future__ import annotations

import json
import math

import numpy as np

from calib.drivelog import LogMeta, file_sha256
from calib.errors import LogFormatError
from calib.ingest.common import check_nonempty, make_series, parse_target, to_channel_unit

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


def _resolve_map(path, topic_map):
    tmap = {k: dict(v) for k, v in DEFAULT_TOPIC_MAP.items()}
    for topic, fields in (topic_map or {}).items():
        if not isinstance(fields, dict):
            raise LogFormatError(path, f"topic map entry {topic!r} must be a table field -> 'channel [unit]'")
        tmap[topic] = dict(fields)
    out = {}
    for topic, fields in tmap.items():
        out[topic] = {}
        for field, target in fields.items():
            ch, unit = parse_target(target, path, f"topic map {topic} {field}")
            if unit is None:
                raise LogFormatError(path, f"topic map {topic} {field}: no unit", hint="write 'channel [unit]'")
            out[topic][field] = (ch, unit)
    return out


def _get(obj, dotted: str):
    for part in dotted.split("."):
        if not isinstance(obj, dict) or part not in obj:
            return None
        obj = obj[part]
    return obj


def read_mcap_streams(path, topic_map: dict | None = None):
    """Read an MCAP log of JSON messages into streams.

    Parameters
    ----------
    path : str or Path
    topic_map : dict, optional
        ``{topic: {field: "channel [unit]"}}``, merged over :data:`DEFAULT_TOPIC_MAP`.

    Returns
    -------
    (Streams, LogMeta)

    Raises
    ------
    LogFormatError
        Empty, truncated or corrupt file; a mapped field that is not a number; no mapped topic.
    """
    from mcap.reader import make_reader

    check_nonempty(path)
    tmap = _resolve_map(path, topic_map)
    meta = LogMeta(source=str(path), sha256=file_sha256(path), format="mcap")
    parts: dict[str, tuple[list, list]] = {}
    t_first, t_prev = math.inf, -math.inf
    n_back, max_back, n_msgs = 0, 0.0, 0
    topics_seen = set()
    i = 0
    try:
        with open(path, "rb") as fh:
            reader = make_reader(fh, validate_crcs=True)
            for i, (_schema, channel, message) in enumerate(reader.iter_messages(log_time_order=False), 1):
                n_msgs += 1
                t = message.log_time * 1e-9
                t_first = min(t_first, t)
                if t < t_prev:
                    back = t_prev - t
                    if back > MAX_BACKSTEP_S:
                        raise LogFormatError(path, f"log time goes back by {back:.3f} s", f"message {i} on {channel.topic}")
                    n_back += 1
                    max_back = max(max_back, back)
                else:
                    t_prev = t
                topics_seen.add(channel.topic)
                fields = tmap.get(channel.topic)
                if not fields:
                    continue
                if channel.message_encoding != "json":
                    raise LogFormatError(path, f"topic {channel.topic} is {channel.message_encoding!r}-encoded, "
                                               "only JSON is supported", f"message {i}")
                try:
                    obj = json.loads(message.data)
                except (ValueError, UnicodeDecodeError):
                    raise LogFormatError(path, "message is not valid JSON", f"message {i} on {channel.topic}") from None
                for field, (ch, _unit) in fields.items():
                    v = _get(obj, field)
                    if v is None:
                        continue
                    if isinstance(v, bool) or not isinstance(v, (int, float)):
                        raise LogFormatError(path, f"field {field!r} is not a number: {str(v)[:40]!r}",
                                             f"message {i} on {channel.topic}")
                    tl, vl = parts.setdefault(f"{channel.topic}\x00{field}", ([], []))
                    tl.append(t)
                    vl.append(float(v))
            for md in reader.iter_metadata():
                if md.name in ("iptm", "drive_log"):
                    d = dict(md.metadata)
                    meta.synthetic = d.get("synthetic", "").lower() in ("true", "1", "yes")
                    meta.vehicle_id = d.get("vehicle_id", "")
                    meta.start_time = d.get("start_time") or None
    except LogFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - the mcap reader raises struct/EndOfFile/CRC/zstd/... errors
        text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
        raise LogFormatError(path, f"corrupt or truncated MCAP file: {text}", f"after message {i}") from None
    if n_msgs == 0:
        raise LogFormatError(path, "MCAP file holds no messages")
    mapped = [tp for tp in topics_seen if tp in tmap]
    if not mapped:
        raise LogFormatError(path, f"no topic matches the topic map (topics in file: {', '.join(sorted(topics_seen))[:200]})",
                             hint="pass a topic map (--map) naming topic, field, channel and unit")
    if n_back:
        meta.notes.append(f"{n_back} message(s) out of log-time order by up to {max_back * 1e3:.1f} ms were sorted")
    streams = {}
    for key, (tl, vl) in parts.items():
        topic, field = key.split("\x00")
        ch, unit = tmap[topic][field]
        v = to_channel_unit(np.asarray(vl), unit, ch, path, f"topic {topic} field {field}")
        t = np.asarray(tl) - t_first
        if ch in streams:
            raise LogFormatError(path, f"two fields map to channel {ch}", f"topic {topic} field {field}")
        s = make_series(t, v, ch)
        if len(s):
            streams[ch] = s
        meta.channel_sources[ch] = f"{topic}.{field}"
        meta.original_units[ch] = unit
    return streams, meta
