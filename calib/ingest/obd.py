"""OBD-II service 01 (current data) responses in CAN logs, decoded with cantools.

An OBD tool on the diagnostic connector asks (functional request 0x7DF, or 0x7E0-0x7E7 to one ECU) and
each ECU answers on its response ID (0x7E8-0x7EF; with 29-bit IDs 0x18DAF1xx) in an ISO 15765-2 (ISO-TP)
frame. A service 01 answer for one PID fits a single frame: byte 0 = PCI (0x0N, N bytes follow),
byte 1 = 0x41, byte 2 = PID, then the PID's data bytes A, B, ... The layout and SAE J1979 scalings are
in ``calib/data/can/obd2_mode01.dbc`` (a DBC multiplexed on the PID, read by cantools); the values are
extracted from whole arrays with the same bit arithmetic as the DBC fast path
(:func:`calib.ingest.canlog.extract_signal`).

Requests carry no data and are only counted. Multi-frame (ISO-TP first/consecutive frame) responses,
negative responses, answers to other services and PIDs outside the DBC are counted and named in the
notes, never decoded silently. A response holding several PIDs (a request may ask for up to six) is
split while every PID in it has a known length.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

#: The OBD-II service 01 DBC shipped with the package (iptm-written, MIT).
OBD2_DBC = Path(str(resources.files("calib") / "data" / "can" / "obd2_mode01.dbc"))
RESPONSE_MESSAGE = "OBD2_MODE01_RESPONSE"

#: Decoded PIDs: PID -> (DBC signal, canonical channel or None, what it is). MAF and fuel level have no
#: channel of their own: MAF feeds the labelled fuel estimate, the fuel level is only reported.
PIDS: dict[int, tuple[str, str | None, str]] = {
    0x05: ("COOLANT_TEMP", "coolant_temp_degC", "engine coolant temperature"),
    0x0C: ("ENGINE_RPM", "engine_speed_rpm", "engine speed"),
    0x0D: ("VEHICLE_SPEED", "speed_mps", "vehicle speed"),
    0x10: ("MAF", None, "mass air flow"),
    0x2F: ("FUEL_LEVEL", None, "fuel tank level"),
    0x46: ("AMBIENT_TEMP", "ambient_temp_degC", "ambient air temperature"),
    0x5B: ("HYBRID_BATTERY_REMAINING", "soc", "hybrid battery pack remaining charge"),
    0x5E: ("ENGINE_FUEL_RATE", "fuel_rate_g_per_s", "engine fuel rate computed by the engine ECU"),
}
PID_MAF = 0x10
PID_FUEL_LEVEL = 0x2F
PID_FUEL_RATE = 0x5E
#: "PIDs supported" bitmap PIDs (4 data bytes each): they say what an ECU can answer, not a measurement.
SUPPORTED_PIDS = (0x00, 0x20, 0x40, 0x60, 0x80, 0xA0, 0xC0, 0xE0)

# Frame kinds as classified by :func:`classify` (values shared with calib.ingest.canlog).
RESPONSE = 2
REQUEST = 4


def classify(can_id: int, extended: bool) -> int:
    """:data:`RESPONSE` for an OBD-II response ID, :data:`REQUEST` for a request ID, else 0."""
    if not extended:
        if 0x7E8 <= can_id <= 0x7EF:
            return RESPONSE
        if can_id == 0x7DF or 0x7E0 <= can_id <= 0x7E7:
            return REQUEST
        return 0
    if can_id & 0x1FFFFF00 == 0x18DAF100:  # ISO 15765-4 normal fixed addressing: to the tester (F1)
        return RESPONSE
    if can_id == 0x18DB33F1 or can_id & 0x1FFF00FF == 0x18DA00F1:  # functional, or from the tester
        return REQUEST
    return 0


def ecu_name(can_id: int, extended: bool) -> str:
    """A response ID as people write it: ``0x7E8`` or ``0x18DAF110``."""
    return f"0x{can_id:08X}" if extended else f"0x{can_id:03X}"


@dataclass
class ObdDecoded:
    """OBD-II values of one bus.

    ``series``: PID -> (t, values in the DBC signal's unit, source label); ``units``: PID -> that unit;
    ``notes``: what was not decoded and why; ``n_responses``: response frames read; ``n_decoded``:
    PID values decoded (all PIDs, used or not).
    """

    series: dict = field(default_factory=dict)
    units: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    n_responses: int = 0
    n_decoded: int = 0


def load_obd_dbc():
    """The OBD-II service 01 message of :data:`OBD2_DBC` (cantools)."""
    from calib.ingest.dbc import load_dbc

    return load_dbc(OBD2_DBC).get_message_by_name(RESPONSE_MESSAGE)


def _signal_bytes(sig) -> int:
    """Data bytes (after byte 2, the PID) a big-endian signal of the service 01 layout needs."""
    byte, bit = divmod(sig.start, 8)
    lsb = (7 - byte) * 8 + bit - (sig.length - 1)
    return (7 - lsb // 8) + 1 - 3


def _pid_layout(msg) -> tuple[dict[int, list], np.ndarray]:
    """PID -> its signals, and a 256-entry table of data lengths (-1: unknown PID)."""
    by_pid: dict[int, list] = {}
    for sig in msg.signals:
        for pid in sig.multiplexer_ids or ():
            by_pid.setdefault(int(pid), []).append(sig)
    length = np.full(256, -1, dtype=np.int64)
    for pid, sigs in by_pid.items():
        length[pid] = max(_signal_bytes(s) for s in sigs)
    length[list(SUPPORTED_PIDS)] = 4
    return by_pid, length


def _ecu(key) -> str:
    extended, can_id = key
    return ecu_name(can_id, extended)


def _fmt_counts(counts: dict, name) -> str:
    return ", ".join(f"{name(k)} ({v:,})" for k, v in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def decode_obd(frames: dict) -> ObdDecoded:
    """Decode service 01 responses.

    Parameters
    ----------
    frames : dict
        ``{(extended, can_id): (t, data, dlc)}`` for the response IDs of one bus: times (s), payloads
        (uint8, shape (n, 8), zero-padded) and data lengths.

    Returns
    -------
    ObdDecoded
        For each decoded PID the values of the ECU that answered it most often (the others are named in
        the notes, not merged: two ECUs may answer the same PID from different sensors).
    """
    from calib.ingest.dbc import extract_signal

    msg = load_obd_dbc()
    by_pid, length = _pid_layout(msg)
    out = ObdDecoded()
    ts, rows, ecus = [], [], []
    n_multi = n_first = n_neg = n_short = n_bad = 0
    other_service: dict[int, int] = {}
    unknown: dict[int, int] = {}
    supported = 0
    ecu_keys = sorted(frames)
    for e, key in enumerate(ecu_keys):
        t, data, dlc = frames[key]
        t = np.asarray(t, dtype=float)
        data = np.asarray(data, dtype=np.uint8).reshape(-1, 8)
        dlc = np.asarray(dlc, dtype=np.int64)
        out.n_responses += len(t)
        pci = data[:, 0].astype(np.int64)
        ftype, n_pci = pci >> 4, pci & 0x0F
        multi = (ftype == 1) | (ftype == 2)
        n_multi += int(multi.sum())
        n_first += int((ftype == 1).sum())
        single = (ftype == 0) & (n_pci >= 1) & (n_pci <= np.minimum(dlc, 8) - 1)
        n_bad += int((~multi & ~single & (ftype != 3)).sum())  # flow control (3) carries no data
        svc = data[:, 1]
        neg = single & (svc == 0x7F) & (data[:, 2] == 0x01)
        n_neg += int(neg.sum())
        pos = single & (svc == 0x41) & (n_pci >= 2)
        n_short += int((single & (svc == 0x41) & (n_pci < 2)).sum())
        for s in np.unique(svc[single & (svc != 0x41) & ~neg]):
            other_service[int(s)] = other_service.get(int(s), 0) + int((single & (svc == s)).sum())
        pid = data[:, 2].astype(np.int64)
        need = length[pid]
        exact = pos & (need >= 0) & (n_pci == 2 + need)
        ts.append(t[exact])
        rows.append(data[exact])
        ecus.append(np.full(int(exact.sum()), e))
        unk = pos & (need < 0)
        for p in np.unique(pid[unk]):
            unknown[int(p)] = unknown.get(int(p), 0) + int((unk & (pid == p)).sum())
        n_short += int((pos & (need >= 0) & (n_pci < 2 + need)).sum())
        # Several PIDs in one response: split into one normalised row per PID while lengths are known.
        for k in np.flatnonzero(pos & (need >= 0) & (n_pci > 2 + need)):
            payload = bytes(data[k, 2:1 + n_pci[k]])
            i = 0
            while i < len(payload):
                p, n = payload[i], int(length[payload[i]])
                if n < 0 or i + 1 + n > len(payload):
                    unknown[p] = unknown.get(p, 0) + 1
                    break
                row = np.zeros((1, 8), dtype=np.uint8)
                row[0, :3 + n] = [2 + n, 0x41, p, *payload[i + 1:i + 1 + n]]
                ts.append(t[k:k + 1])
                rows.append(row)
                ecus.append(np.array([e]))
                i += 1 + n
    t = np.concatenate(ts) if ts else np.empty(0)
    data = np.concatenate(rows) if rows else np.empty((0, 8), dtype=np.uint8)
    ecu = np.concatenate(ecus) if ecus else np.empty(0, dtype=np.int64)
    pid = data[:, 2].astype(np.int64)
    for p in SUPPORTED_PIDS:
        supported += int((pid == p).sum())
    for p in sorted(set(by_pid) & set(PIDS)):
        sel = pid == p
        if not sel.any():
            continue
        per_ecu = {int(x): int((ecu[sel] == x).sum()) for x in np.unique(ecu[sel])}
        best = min(per_ecu, key=lambda x: (-per_ecu[x], x))
        rows_p = sel & (ecu == best)
        name = PIDS[p][0]
        sig = msg.get_signal_by_name(name)
        src = _ecu(ecu_keys[best])
        out.series[p] = (t[rows_p], extract_signal(data[rows_p], sig), f"OBD-II PID 0x{p:02X} {name} ({src})")
        out.units[p] = sig.unit
        out.n_decoded += int(sel.sum())
        others = {_ecu(ecu_keys[x]): n for x, n in per_ecu.items() if x != best}
        if others:
            out.notes.append(f"OBD-II PID 0x{p:02X} {name}: the answers of {src} ({per_ecu[best]:,}) are used; "
                             f"also answered by {_fmt_counts(others, str)}, not merged")
    if supported:
        out.notes.append(f"OBD-II: {supported:,} 'PIDs supported' responses (no measurement)")
    if unknown:
        out.notes.append("OBD-II PIDs not decoded (not in obd2_mode01.dbc): "
                         + _fmt_counts(unknown, lambda p: f"0x{p:02X}") + " responses")
    if n_multi:
        out.notes.append(f"OBD-II: {n_multi:,} multi-frame (ISO-TP) response frames ({n_first:,} responses) "
                         "skipped: only single-frame responses are decoded")
    if n_neg:
        out.notes.append(f"OBD-II: {n_neg:,} negative responses to service 01 (PID not supported or ECU busy)")
    if other_service:
        out.notes.append("OBD-II: responses to other services not decoded: "
                         + _fmt_counts(other_service, lambda s: f"0x{s:02X}"))
    if n_short:
        out.notes.append(f"OBD-II: {n_short:,} service 01 responses shorter than their PID's data, skipped")
    if n_bad:
        out.notes.append(f"OBD-II: {n_bad:,} frames on response IDs that are not ISO-TP frames, skipped")
    return out
