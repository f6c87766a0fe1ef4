"""Write sensor streams as the log formats engineers bring: CSV, MCAP, candump -L, BLF (and ASC).

The synthesiser calls :func:`write_streams` with physically simulated streams (per-signal rates,
quantised, with dropouts); each format keeps every sample at its own time, so the same drive written in
every format ingests back to the same canonical table (CAN adds its DBC scaling as quantisation: our
DBC's steps are no coarser than the sensors', see ``calib/data/can/README.md``).

- CSV: ``time [s]`` plus one column per channel with a human header (``speed [km/h]``,
  ``coolant_temp [degC]``...), empty cells where a channel has no sample at that time; ``#`` comment
  lines on top carry the metadata, the first one says SYNTHETIC when the log is synthetic.
- MCAP: JSON messages on ``/vehicle/speed``, ``/hv_battery``, ``/engine``, ``/hvac``, ``/environment``,
  ``/vehicle/grade`` (the layout of :data:`calib.ingest.mcaplog.DEFAULT_TOPIC_MAP`), ``log_time`` in ns,
  a metadata record ``iptm`` with ``synthetic``.
- CAN: frames per DBC message at the union of its signals' sample times; a signal without a sample at
  that time is sent as "not available" (all-ones raw), which the reader drops.
"""
from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np

from calib.drivelog import CHANNELS, LogMeta
from calib.errors import IptmError
from calib.fileio import atomic_path
from calib.ingest.common import HUMAN_NAME
from calib.units import convert

#: Units the CSV writer uses (a human logger's choice, not SI).
CSV_UNITS = {
    "speed_mps": "km/h", "bat_current_A": "A", "bat_voltage_V": "V", "soc": "%", "bat_temp_degC": "degC",
    "engine_speed_rpm": "rpm", "engine_torque_Nm": "N*m", "fuel_rate_g_per_s": "g/s",
    "engine_power_W": "kW", "bat_power_W": "kW",
    "coolant_temp_degC": "degC", "bay_temp_degC": "degC", "ambient_temp_degC": "degC",
    "cabin_temp_degC": "degC", "heater_power_W": "W", "vent_temp_degC": "degC",
    "blower_flow_kg_per_s": "kg/s", "hvac_setpoint_degC": "degC", "grade_rad": "rad",
}

WRITE_FORMATS = ("csv", "mcap", "candump", "blf", "asc")


def _start_epoch(meta: LogMeta) -> float:
    if meta.start_time:
        try:
            d = _dt.datetime.fromisoformat(str(meta.start_time))
            if d.tzinfo is None:
                d = d.replace(tzinfo=_dt.timezone.utc)
            return d.timestamp()
        except ValueError:
            pass
    return 0.0


def _clean(streams: dict) -> dict:
    out = {}
    for ch, s in streams.items():
        if ch not in CHANNELS:
            raise IptmError(f"write_streams: {ch!r} is not a canonical channel")
        s = s[np.isfinite(s.to_numpy(dtype=float))]
        if len(s):
            out[ch] = s.sort_index()
    if not out:
        raise IptmError("write_streams: no samples to write")
    return out


def write_streams(streams: dict, meta: LogMeta, path, fmt: str, *, dbc=None) -> Path:
    """Write ``streams`` (channel -> Series indexed by time_s, canonical units) as a log file.

    Parameters
    ----------
    streams : dict
        Canonical streams.
    meta : LogMeta
        ``synthetic``, ``vehicle_id``, ``start_time`` and ``notes`` are written where the format allows.
    path : str or Path
        Output file (written atomically).
    fmt : {"csv", "mcap", "candump", "blf", "asc"}
    dbc : str or Path, optional
        CAN formats: DBC to encode with (default our Prius DBC).

    Returns
    -------
    Path
    """
    streams = _clean(streams)
    path = Path(path)
    if fmt == "csv":
        _write_csv(streams, meta, path)
    elif fmt == "mcap":
        _write_mcap(streams, meta, path)
    elif fmt in ("candump", "blf", "asc"):
        frames = can_frames(streams, dbc=dbc, synthetic=meta.synthetic)
        header = ["SYNTHETIC drive log: simulated by iptm, not measured on a vehicle"] if meta.synthetic else []
        write_can_frames(frames, path, fmt, start_epoch=_start_epoch(meta), header=header)
    else:
        raise IptmError(f"write_streams: unknown format {fmt!r} (one of {', '.join(WRITE_FORMATS)})")
    return path


# ---------------------------------------------------------------- CSV

def _write_csv(streams, meta: LogMeta, path: Path) -> None:
    t_all = np.unique(np.concatenate([s.index.to_numpy(float) for s in streams.values()]))
    cols = {}
    for ch in CHANNELS:
        if ch not in streams:
            continue
        s = streams[ch]
        v = np.full(len(t_all), np.nan)
        idx = np.searchsorted(t_all, s.index.to_numpy(float))
        v[idx] = convert(s.to_numpy(float), CHANNELS[ch][0], CSV_UNITS[ch])
        cols[f"{HUMAN_NAME[ch]} [{CSV_UNITS[ch]}]"] = v
    head = []
    if meta.synthetic:
        head.append("# SYNTHETIC drive log: simulated by iptm, not measured on a vehicle")
    else:
        head.append("# drive log")
    head.append(f"# synthetic: {str(bool(meta.synthetic)).lower()}")
    if meta.vehicle_id:
        head.append(f"# vehicle_id: {meta.vehicle_id}")
    if meta.start_time:
        head.append(f"# start_time: {meta.start_time}")
    for n in meta.notes:
        head.append(f"# note: {str(n).replace(chr(10), ' ')}")
    names = list(cols)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        fh.write("\n".join(head) + "\n")
        fh.write(",".join(["time [s]"] + names) + "\n")
        mats = np.column_stack([t_all] + [cols[n] for n in names])
        # repr-precision numbers (%.17g would be exact; %.12g keeps files readable and is far below
        # any sensor quantisation); empty cell = no sample.
        for row in mats:
            fh.write(",".join("" if not np.isfinite(x) else f"{x:.12g}" for x in row) + "\n")


# ---------------------------------------------------------------- MCAP

def mcap_layout():
    """channel -> (topic, field, unit) from the default topic map (so reader and writer agree)."""
    from calib.ingest.common import split_spec
    from calib.ingest.mcaplog import DEFAULT_TOPIC_MAP

    out = {}
    for topic, fields in DEFAULT_TOPIC_MAP.items():
        for field, target in fields.items():
            ch, unit = split_spec(target)
            out[ch] = (topic, field, unit)
    return out


def _write_mcap(streams, meta: LogMeta, path: Path) -> None:
    from mcap.writer import CompressionType, Writer

    layout = mcap_layout()
    t0 = _start_epoch(meta)
    by_topic: dict[str, list[str]] = {}
    for ch in streams:
        by_topic.setdefault(layout[ch][0], []).append(ch)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)  # zstd: real loggers compress
        w.start(profile="", library="iptm")
        schema = json.dumps({"type": "object", "additionalProperties": {"type": "number"}}).encode()
        sid = w.register_schema(name="iptm.Sample", encoding="jsonschema", data=schema)
        events = []  # (t_ns, channel_id, json bytes)
        for topic, chans in by_topic.items():
            cid = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            t_all = np.unique(np.concatenate([streams[c].index.to_numpy(float) for c in chans]))
            per = {}
            for c in chans:
                s = streams[c]
                v = np.full(len(t_all), np.nan)
                v[np.searchsorted(t_all, s.index.to_numpy(float))] = convert(s.to_numpy(float), CHANNELS[c][0], layout[c][2])
                per[layout[c][1]] = v
            t_ns = np.round((t_all + t0) * 1e9).astype(np.int64)
            for k in range(len(t_all)):
                msg = {f: float(v[k]) for f, v in per.items() if np.isfinite(v[k])}
                events.append((int(t_ns[k]), cid, json.dumps(msg).encode()))
        events.sort(key=lambda e: (e[0], e[1]))
        for seq, (tn, cid, data) in enumerate(events):
            w.add_message(channel_id=cid, log_time=tn, data=data, publish_time=tn, sequence=seq)
        w.add_metadata(name="iptm", data={
            "synthetic": str(bool(meta.synthetic)).lower(),
            "vehicle_id": meta.vehicle_id or "",
            "start_time": meta.start_time or "",
            "notes": " | ".join(map(str, meta.notes)),
            "label": "SYNTHETIC drive log: simulated, not measured" if meta.synthetic else "drive log",
        })
        w.finish()


# ---------------------------------------------------------------- CAN

def _encode_signal(raw_target: np.ndarray, values: np.ndarray, sig) -> None:
    """OR the raw bits of ``sig`` for ``values`` (NaN -> "not available") into uint64 words (in place).

    The words are big-endian (Motorola) or little-endian (Intel) images of the 8 data bytes, matching
    the signal's byte order; see :func:`calib.ingest.canlog.extract_signal` for the inverse.
    """
    L = sig.length
    if sig.is_signed:
        lo, hi = -(1 << (L - 1)) + 1, (1 << (L - 1)) - 1  # most negative raw is reserved: not available
        sna = -(1 << (L - 1))
    else:
        lo, hi = 0, (1 << L) - 2  # all ones is reserved: not available
        sna = (1 << L) - 1
    ok = np.isfinite(values)
    raw = np.full(len(values), sna, dtype=np.int64)
    raw[ok] = np.clip(np.round((values[ok] - float(sig.offset)) / float(sig.scale)), lo, hi).astype(np.int64)
    raw_u = (raw & ((1 << L) - 1)).astype(np.uint64)
    if sig.byte_order == "little_endian":
        shift = sig.start
    else:
        byte, bit = divmod(sig.start, 8)
        shift = (7 - byte) * 8 + bit - (L - 1)
    raw_target |= raw_u << np.uint64(shift)


def can_frames(streams: dict, dbc=None, signal_map: dict | None = None, synthetic: bool = False) -> dict:
    """Encode streams into CAN frames with our DBC (cantools signal definitions).

    One frame per DBC message at each time any of its mapped signals has a sample. With ``synthetic``
    (and a DBC that has the iptm-defined ``IPTM_LOG_INFO`` message) a 1 Hz frame says SYNTHETIC = 1, so
    the label survives in formats without comments (BLF).

    Returns
    -------
    dict
        ``{"t": float seconds from start, "id": int, "data": uint8 (n, 8), "dlc": uint8}``, time-sorted.
    """
    from calib.ingest.canlog import PRIUS_DBC, load_dbc, resolve_signal_map

    dbc = Path(dbc) if dbc is not None else PRIUS_DBC
    db = load_dbc(dbc)
    smap = resolve_signal_map(db, dbc, signal_map)
    by_msg: dict[str, list[tuple[str, str, str]]] = {}
    for (m, s), (ch, unit) in smap.items():
        if ch in streams:
            by_msg.setdefault(m, []).append((s, ch, unit))
    missing = [ch for ch in streams if ch not in {c for v in by_msg.values() for _, c, _ in v}]
    if missing:
        raise IptmError(f"write_streams: DBC {dbc.name} has no signal for channel(s) {', '.join(missing)}")
    ts, ids, datas, dlcs = [], [], [], []
    for mname, sigs in by_msg.items():
        msg = db.get_message_by_name(mname)
        if msg.length > 8 or msg.is_multiplexed():
            raise IptmError(f"write_streams: DBC message {mname} is multiplexed or longer than 8 bytes")
        t_all = np.unique(np.concatenate([streams[ch].index.to_numpy(float) for _, ch, _ in sigs]))
        word = np.zeros(len(t_all), dtype=np.uint64)
        byte_order = None
        for sname, ch, unit in sigs:
            sig = msg.get_signal_by_name(sname)
            if byte_order is not None and sig.byte_order != byte_order:
                raise IptmError(f"write_streams: message {mname} mixes byte orders")
            byte_order = sig.byte_order
            s = streams[ch]
            v = np.full(len(t_all), np.nan)
            v[np.searchsorted(t_all, s.index.to_numpy(float))] = convert(s.to_numpy(float), CHANNELS[ch][0], unit or sig.unit)
            _encode_signal(word, v, sig)
        # Unmapped signals of the message are sent as "not available" too.
        for sig in msg.signals:
            if sig.name not in {s for s, _, _ in sigs} and sig.byte_order == byte_order:
                _encode_signal(word, np.full(len(t_all), np.nan), sig)
        dt = ">u8" if byte_order == "big_endian" else "<u8"
        data = word.astype(dt).view(np.uint8).reshape(-1, 8)
        ts.append(t_all)
        ids.append(np.full(len(t_all), msg.frame_id, dtype=np.int64))
        datas.append(data)
        dlcs.append(np.full(len(t_all), msg.length, dtype=np.uint8))
    if synthetic and "IPTM_LOG_INFO" in {m.name for m in db.messages}:
        msg = db.get_message_by_name("IPTM_LOG_INFO")
        t_end = max(float(s.index[-1]) for s in streams.values())
        t_info = np.arange(0.0, t_end + 1e-9, 1.0)
        word = np.zeros(len(t_info), dtype=np.uint64)
        _encode_signal(word, np.ones(len(t_info)), msg.get_signal_by_name("SYNTHETIC"))
        ts.append(t_info)
        ids.append(np.full(len(t_info), msg.frame_id, dtype=np.int64))
        datas.append(word.astype(">u8").view(np.uint8).reshape(-1, 8))
        dlcs.append(np.full(len(t_info), msg.length, dtype=np.uint8))
    t = np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    return {"t": t[order], "id": np.concatenate(ids)[order], "data": np.concatenate(datas)[order],
            "dlc": np.concatenate(dlcs)[order]}


def write_can_frames(frames: dict, path, fmt: str, *, start_epoch: float = 0.0, channel: str = "can0",
                     chunk: int = 200_000, header: list[str] | None = None) -> Path:
    """Write frames from :func:`can_frames` as candump -L text, BLF or ASC (atomically, in chunks).

    ``header`` lines become ``#`` comments at the top of a candump file (our reader skips them and
    reads SYNTHETIC from the first); BLF and ASC carry the label in the IPTM_LOG_INFO frames only.
    """
    path = Path(path)
    t = np.asarray(frames["t"], dtype=float) + start_epoch
    ids, data, dlc = frames["id"], frames["data"], frames["dlc"]
    if fmt == "candump":
        with atomic_path(path) as tmp, open(tmp, "w") as fh:
            for line in header or []:
                fh.write(f"# {line}\n")
            for a in range(0, len(t), chunk):
                b = min(a + chunk, len(t))
                hexes = [bytes(data[k, : dlc[k]]).hex().upper() for k in range(a, b)]
                fh.write("".join(
                    f"({t[k]:.6f}) {channel} {ids[k]:03X}#{hexes[k - a]}\n" if ids[k] <= 0x7FF
                    else f"({t[k]:.6f}) {channel} {ids[k]:08X}#{hexes[k - a]}\n"
                    for k in range(a, b)))
        return path
    if fmt in ("blf", "asc"):
        import can

        with atomic_path(path) as tmp:
            writer = can.BLFWriter(str(tmp)) if fmt == "blf" else can.ASCWriter(str(tmp))
            try:
                for k in range(len(t)):
                    writer.on_message_received(can.Message(
                        timestamp=float(t[k]), arbitration_id=int(ids[k]), is_extended_id=bool(ids[k] > 0x7FF),
                        data=bytes(data[k, : dlc[k]]), dlc=int(dlc[k]), channel=0))
            finally:
                writer.stop()
        return path
    raise IptmError(f"write_can_frames: unknown CAN format {fmt!r} (candump, blf, asc)")
