"""Log ingestion: CSV, MCAP, CAN dumps (candump -L, .asc, .blf, .trc) and MDF4 into one canonical log.

Public API
----------
read_streams(path, fmt=None, dbc=None, column_map=None, topic_map=None) -> (Streams, LogMeta)
to_drivelog(streams, meta, rate_hz=1.0, max_gap_s=5.0) -> DriveLog
read_log(path, ...) -> DriveLog
channel_report(log, streams=None) -> DataFrame ; format_report(report) -> str
write_canonical(log, path) ; read_canonical(path) -> DriveLog
load_map(path) -> dict  (column/topic/signal maps from TOML or JSON)
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import pandas as pd

from calib.drivelog import CHANNELS, DriveLog, LogMeta, file_sha256
from calib.errors import ChannelLossWarning, LogFormatError
from calib.fileio import atomic_path, write_json
from calib.ingest.canlog import (CAN_FORMATS, DEFAULT_SIGNAL_MAP, PRIUS_DBC, TOYOTA_2017_DBC, decode_can_signals,
                                 read_can_streams)
from calib.ingest.channels import (channel_losses, channel_report, display_report, format_report, log_warnings,
                                   loss_text)
from calib.ingest.csvlog import read_csv_streams, sniff_is_csv
from calib.ingest.damage import summarize as damage_summary
from calib.ingest.damage import warn_damage
from calib.ingest.mcaplog import DEFAULT_TOPIC_MAP, read_mcap_streams
from calib.ingest.mdflog import read_mdf_streams
from calib.ingest.resample import to_drivelog
from calib.ingest.common import HUMAN_NAME, describe_channels
from calib.ingest.drives import group_drives, same_drive, split_fit_validation
from calib.ingest.writers import can_frames, mcap_layout, write_can_frames, write_streams

FORMATS = ("csv", "mcap", "candump", "asc", "blf", "trc", "mf4")
_EXT = {".csv": "csv", ".txt": "csv", ".mcap": "mcap", ".log": "candump", ".candump": "candump",
        ".asc": "asc", ".blf": "blf", ".trc": "trc", ".mf4": "mf4", ".mdf": "mf4"}
_MAGIC = {b"\x89MCAP": "mcap", b"LOGG": "blf", b"MDF ": "mf4"}

__all__ = [
    "FORMATS", "DEFAULT_SIGNAL_MAP", "DEFAULT_TOPIC_MAP", "PRIUS_DBC", "TOYOTA_2017_DBC",
    "detect_format", "read_streams", "to_drivelog", "read_log", "channel_report", "display_report", "format_report",
    "write_canonical", "read_canonical", "load_map", "decode_can_signals", "damage_summary", "channel_losses",
    "loss_text", "log_warnings", "input_digest", "warn_damage", "describe_channels", "HUMAN_NAME",
    "group_drives", "same_drive", "split_fit_validation",
    "write_streams", "can_frames", "write_can_frames", "mcap_layout",
]


def input_digest(path, *, dbc=None, maps: dict | None = None) -> str:
    """SHA-256 over the contents of everything a read of ``path`` depends on: the log, the DBC (the shipped
    ones when none is given) and the column/topic/signal maps. Caches of ingested logs are keyed on it, so an
    edited DBC is never served from a copy decoded with the old one."""
    import hashlib

    from calib.drivelog import file_sha256

    h = hashlib.sha256(file_sha256(path).encode())
    for d in ([dbc] if dbc else [PRIUS_DBC, TOYOTA_2017_DBC]):
        h.update(file_sha256(d).encode() if Path(d).is_file() else f"missing:{d}".encode())
    h.update(json.dumps(maps or {}, sort_keys=True, default=str).encode())
    return h.hexdigest()


def detect_format(path) -> str:
    """Format of a log from its first bytes, else its extension.

    Raises
    ------
    LogFormatError
        Missing/empty file, or neither content nor extension tells.
    """
    p = Path(path)
    if not p.exists():
        raise LogFormatError(path, "no such file")
    if p.is_dir():
        raise LogFormatError(path, "is a folder, not a log file")
    with open(p, "rb") as fh:
        head = fh.read(64)
    if not head:
        raise LogFormatError(path, "empty file")
    for magic, fmt in _MAGIC.items():
        if head.startswith(magic):
            return fmt
    ext = p.suffix.lower()
    if ext in _EXT:
        return _EXT[ext]
    if head.lstrip().startswith(b"(") and b"#" in head:
        return "candump"
    if sniff_is_csv(p):
        return "csv"
    raise LogFormatError(path, f"cannot tell the log format from extension {ext or '(none)'!r} or content",
                         hint=f"pass the format explicitly: one of {', '.join(FORMATS)}")


def read_streams(path, *, fmt: str | None = None, dbc=None, column_map: dict | None = None,
                 topic_map: dict | None = None, signal_map: dict | None = None, strict: bool = False,
                 profile: str | None = None, vehicle=None, trip=None, bus: str | None = None):
    """Read a log file into raw canonical streams.

    Parameters
    ----------
    path : str or Path
        The log.
    fmt : str, optional
        One of :data:`FORMATS`; detected from content/extension when omitted.
    dbc : str or Path, optional
        DBC for CAN formats (default: our Prius DBC, ``calib/data/can/prius_iptm.dbc``).
    column_map : dict, optional
        CSV/MDF: ``{column: "channel [unit]"}``.
    topic_map : dict, optional
        MCAP: ``{topic: {field: "channel [unit]"}}``.
    signal_map : dict, optional
        CAN: ``{"MESSAGE.SIGNAL": "channel"}`` added over the default map.
    strict : bool
        Refuse a damaged log (the first garbled line/record, or a truncation, is a LogFormatError).
        By default a damaged log is read as far as it can be trusted, ``meta.damage`` says what was
        lost and one :class:`~calib.errors.LogDamageWarning` is issued.
    profile : {"d3", "ved", "torque", "carscanner"}, optional
        Read a test-data format (:mod:`calib.ingest.profiles`); detected from a CSV's header when omitted.
    vehicle, trip : optional
        VED: the vehicle and trip to read.
    bus : str, optional
        CAN formats: the bus to decode with the DBC (default: the bus with most frames the DBC knows).

    Returns
    -------
    (Streams, LogMeta)
        Streams in canonical units, time in seconds from the log's first record. ``meta.channel_counts``
        accounts every channel's samples; a channel that lost more than 1 % of them (non-finite or
        physically impossible values) is named in one :class:`~calib.errors.ChannelLossWarning`.

    Raises
    ------
    LogFormatError
        Any unreadable input (a file with nothing readable, or any damage under ``strict``); the message
        names the file and, where it applies, the line/message/channel.
    """
    streams, meta = _read_streams(path, fmt=fmt, dbc=dbc, column_map=column_map, topic_map=topic_map,
                                  signal_map=signal_map, strict=strict, profile=profile, vehicle=vehicle,
                                  trip=trip, bus=bus)
    if meta.damage:
        if not streams:
            raise LogFormatError(path, "nothing readable: " + meta.damage["summary"])
        warn_damage(path, meta.damage)
    lost = loss_text(meta)
    if lost:
        warnings.warn(ChannelLossWarning(f"{path}: {lost}"), stacklevel=2)
    return streams, meta


def _read_streams(path, *, fmt, dbc, column_map, topic_map, signal_map, strict, profile, vehicle, trip, bus):
    fmt = (fmt or detect_format(path)).lower().lstrip(".")
    if fmt == "log":
        fmt = "candump"
    if fmt == "csv":
        from calib.ingest.profiles import detect_profile, read_profile_streams

        profile = profile or detect_profile(path)
        if profile:
            return read_profile_streams(path, profile, column_map=column_map, vehicle=vehicle, trip=trip,
                                        strict=strict)
    elif bus is not None and fmt not in CAN_FORMATS:
        raise LogFormatError(path, f"--bus applies to CAN logs, not {fmt}")
    if profile and fmt != "csv":
        raise LogFormatError(path, f"profile {profile!r} applies to CSV/TSV text files, not {fmt}")
    if fmt == "csv":
        return read_csv_streams(path, column_map=column_map, strict=strict)
    if fmt == "mcap":
        return read_mcap_streams(path, topic_map=topic_map, strict=strict)
    if fmt in CAN_FORMATS:
        kw = {"bus": bus} if bus is not None else {}
        return read_can_streams(path, fmt=fmt, dbc=dbc, signal_map=signal_map, strict=strict, **kw)
    if fmt in ("mf4", "mdf"):
        return read_mdf_streams(path, column_map=column_map, strict=strict)
    raise LogFormatError(path, f"unknown log format {fmt!r}", hint=f"one of {', '.join(FORMATS)}")


def read_log(path, *, fmt: str | None = None, dbc=None, column_map: dict | None = None,
             topic_map: dict | None = None, signal_map: dict | None = None,
             rate_hz: float = 1.0, max_gap_s: float = 5.0, strict: bool = False, profile: str | None = None,
             vehicle=None, trip=None, bus: str | None = None) -> DriveLog:
    """:func:`read_streams` then :func:`to_drivelog` (``strict``: refuse a damaged log)."""
    streams, meta = read_streams(path, fmt=fmt, dbc=dbc, column_map=column_map, topic_map=topic_map,
                                 signal_map=signal_map, strict=strict, profile=profile, vehicle=vehicle, trip=trip,
                                 bus=bus)
    if not streams:
        raise LogFormatError(path, "no samples of any canonical channel in the log")
    return to_drivelog(streams, meta, rate_hz=rate_hz, max_gap_s=max_gap_s)


def _sidecar(path: Path) -> Path:
    return path.with_name(path.name + ".meta.json")


def write_canonical(log: DriveLog, path) -> Path:
    """Write the canonical table: Parquet (metadata inside, key ``iptm``) or CSV (+ ``<file>.meta.json``).

    Both files are written atomically. Returns the table's path.
    """
    path = Path(path)
    df = log.data.copy()
    df.index.name = "time_s"
    meta_json = json.dumps(log.meta.to_dict(), default=str)
    ext = path.suffix.lower()
    if ext == ".parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pandas(df.reset_index(), preserve_index=False)
        md = dict(table.schema.metadata or {})
        md[b"iptm"] = meta_json.encode()
        table = table.replace_schema_metadata(md)
        with atomic_path(path) as tmp:
            pq.write_table(table, tmp)
    elif ext == ".csv":
        # Two files cannot be renamed into place in one step: the sidecar names the SHA-256 of the table it
        # belongs to, and is written first, so a write killed between the two leaves a pair that
        # read_canonical refuses rather than new data with old provenance.
        from calib.drivelog import file_sha256

        with atomic_path(path) as tmp:
            with open(tmp, "w", newline="") as fh:
                if log.meta.synthetic:
                    fh.write("# SYNTHETIC drive log (canonical table)\n")
                df.to_csv(fh, float_format="%.10g")
            write_json(_sidecar(path), {**log.meta.to_dict(), "table_sha256": file_sha256(tmp)})
    else:
        raise LogFormatError(path, f"cannot write a canonical table as {ext or '(no extension)'}",
                             hint="use .parquet or .csv")
    return path


def read_canonical(path) -> DriveLog:
    """Read a table written by :func:`write_canonical`."""
    path = Path(path)
    if not path.exists():
        raise LogFormatError(path, "no such file")
    ext = path.suffix.lower()
    try:
        if ext == ".parquet":
            import pyarrow.parquet as pq

            table = pq.read_table(path)
            md = (table.schema.metadata or {}).get(b"iptm")
            if md is None:
                raise LogFormatError(path, "not an iptm canonical table (no 'iptm' metadata)")
            meta = LogMeta.from_dict(json.loads(md))
            df = table.to_pandas()
        elif ext == ".csv":
            side = _sidecar(path)
            if not side.exists():
                raise LogFormatError(path, f"metadata sidecar {side.name} is missing")
            side_d = json.loads(side.read_text())
            if side_d.get("table_sha256") not in (None, file_sha256(path)):
                raise LogFormatError(path, f"metadata sidecar {side.name} belongs to another version of the table "
                                           "(a write was interrupted)", hint="ingest the log again")
            meta = LogMeta.from_dict(side_d)
            df = pd.read_csv(path, comment="#")
        else:
            raise LogFormatError(path, f"not a canonical table extension {ext!r}", hint="use .parquet or .csv")
    except LogFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - pyarrow/pandas/json errors on a damaged file
        raise LogFormatError(path, f"cannot read canonical table: {str(exc).splitlines()[0][:160]}") from None
    if "time_s" not in df.columns:
        raise LogFormatError(path, "no time_s column")
    unknown = [c for c in df.columns if c != "time_s" and c not in CHANNELS]
    if unknown:
        raise LogFormatError(path, f"not canonical channels: {', '.join(unknown)}")
    df = df.set_index("time_s").astype(float)
    df.index = pd.Index(df.index.to_numpy(dtype=float), name="time_s")
    return DriveLog(data=df, meta=meta)


def load_map(path) -> dict:
    """Load a map file (TOML or JSON) with optional tables ``columns``, ``topics``, ``signals``.

    Example (TOML)::

        [columns]
        "Vehicle Speed" = "speed_mps [km/h]"
        [topics."/obd"]
        rpm = "engine_speed_rpm [rpm]"
        [signals]
        "MY_MSG.SOC" = "soc"

    Returns ``{"columns": {...}, "topics": {...}, "signals": {...}}``.
    """
    from calib.fileio import read_config

    p = Path(path)
    d = read_config(p, lambda msg: LogFormatError(path, msg.removeprefix(f"{p}: ")), "map file")
    extra = set(d) - {"columns", "topics", "signals"}
    if extra:
        raise LogFormatError(path, f"unknown map section(s): {', '.join(sorted(extra))}",
                             hint="use [columns], [topics.\"/topic\"], [signals]")
    for sec in ("columns", "topics", "signals"):
        if not isinstance(d.get(sec, {}), dict):
            raise LogFormatError(path, f"[{sec}] must be a table", hint="see `iptm ingest --help`")
    # every target checked here, so that a bad channel or unit names this file, not the log or the DBC
    for col, target in d.get("columns", {}).items():
        _check_map_target(target, path, f"[columns] {col!r}", time_ok=True)
    for topic, fields in d.get("topics", {}).items():
        if not isinstance(fields, dict):
            raise LogFormatError(path, f"[topics.{topic!r}] must be a table of field = \"channel [unit]\"")
        for field, target in fields.items():
            _check_map_target(target, path, f"[topics.{topic!r}] {field!r}")
    for key, target in d.get("signals", {}).items():
        _check_map_target(target, path, f"[signals] {key!r}", wheel_ok=True)
    return {"columns": dict(d.get("columns", {})), "topics": dict(d.get("topics", {})),
            "signals": dict(d.get("signals", {}))}


def _check_map_target(target, path, where: str, time_ok: bool = False, wheel_ok: bool = False) -> None:
    from calib.ingest.canlog import WHEEL_TARGETS
    from calib.ingest.common import TIME_NAMES, check_unit, parse_target, split_spec
    from calib.units import UnitError, parse_unit

    if not isinstance(target, (str, dict, list)):
        raise LogFormatError(path, f"map entry {where}: {str(target)[:40]!r} is not \"channel [unit]\"", where)
    name, unit = split_spec(target) if isinstance(target, str) else (None, None)
    if name is not None and ((time_ok and name.strip().lower() in TIME_NAMES)
                             or (wheel_ok and name.strip().lower() in WHEEL_TARGETS)):
        if unit is not None:
            try:
                parse_unit(unit)
            except UnitError as exc:
                raise LogFormatError(path, str(exc), where) from None
            if wheel_ok and name.strip().lower() in WHEEL_TARGETS:
                check_unit(unit, "speed_mps", path, where)
        return
    parse_target(target, path, where)



