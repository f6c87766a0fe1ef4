"""DBC files: loading with cantools (errors name the file) and the vectorised signal extraction shared by the CAN
reader (:mod:`calib.ingest.canlog`) and the OBD-II decoder (:mod:`calib.ingest.obd`)."""
from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np

from calib.errors import LogFormatError

#: Our Prius DBC, shipped with the package.
PRIUS_DBC = Path(str(resources.files("calib") / "data" / "can" / "prius_iptm.dbc"))


#: Largest DBC file read, bytes, and longest line: a vehicle's whole DBC is a few MB with lines of a few kB;
#: cantools' parser needs about 200 bytes of memory per byte of a line, so a hostile 4-MB line cost 800 MB.
MAX_DBC_BYTES = 64 << 20
MAX_DBC_LINE = 1 << 16


def _check_dbc_size(dbc: Path) -> None:
    size = dbc.stat().st_size
    if size > MAX_DBC_BYTES:
        raise LogFormatError(dbc, f"DBC file of {size:,} bytes (at most {MAX_DBC_BYTES:,} are read)",
                             hint="is this a DBC? split it or keep the messages you need")
    with open(dbc, "rb") as fh:
        for no, line in enumerate(fh, 1):
            if len(line) > MAX_DBC_LINE:
                raise LogFormatError(dbc, f"line {no:,} is {len(line):,} characters long (at most {MAX_DBC_LINE:,} "
                                          "in a DBC)", f"line {no}", hint="correct the DBC")


def load_dbc(dbc, path_for_errors=None):
    """Load a DBC with cantools; errors name the DBC file."""
    import cantools

    dbc = Path(dbc) if dbc is not None else PRIUS_DBC
    if not dbc.exists():
        raise LogFormatError(dbc, "DBC file not found")
    if dbc.is_file():
        _check_dbc_size(dbc)
    try:
        db = cantools.database.load_file(str(dbc), database_format="dbc", strict=False)
    except Exception as exc:  # noqa: BLE001 - cantools raises many parser types; all mean "bad DBC"
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise LogFormatError(dbc, f"cannot parse DBC: {msg[:200]}") from None
    for m in db.messages:  # a scale or offset no float holds would overflow in the decoding
        for sg in m.signals:
            for what in ("scale", "offset", "minimum", "maximum"):
                v = getattr(sg, what)
                try:
                    ok = v is None or math.isfinite(float(v))
                except (OverflowError, TypeError, ValueError):
                    ok = False
                if not ok:
                    raise LogFormatError(dbc, f"signal {m.name}.{sg.name}: {what} {str(v)[:24]!r} is not a finite "
                                              "number", hint="correct the DBC")
    return db


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
        with np.errstate(over="ignore", invalid="ignore"):  # an absurd scale gives inf, dropped by range
            phys = r * float(sig.scale) + float(sig.offset)
        if sig.minimum is not None:
            sna &= phys < float(sig.minimum)
        else:
            sna[:] = False
    else:
        sna = raw == mask
        with np.errstate(over="ignore", invalid="ignore"):  # an absurd scale gives inf, dropped by range
            phys = raw.astype(np.float64) * float(sig.scale) + float(sig.offset)
        if sig.maximum is not None:
            sna &= phys > float(sig.maximum)
        else:
            sna[:] = False
    return np.where(sna, np.nan, phys)
