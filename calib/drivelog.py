"""The canonical drive log: one table, SI units, with provenance.

Every reader (CSV, MCAP, CAN, MDF4) and the synthesiser end here. Raw readers first produce *streams*
(one irregularly sampled :class:`pandas.Series` per canonical channel, index = seconds from log start,
values in the canonical unit); :func:`calib.ingest.resample.to_drivelog` then puts them on a common time
base without inventing data across long gaps.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from calib.errors import MissingChannelsError

#: Canonical channels: name -> (pint unit string, description). Column names carry the unit.
CHANNELS: dict[str, tuple[str, str]] = {
    "speed_mps": ("m/s", "vehicle speed"),
    "bat_current_A": ("A", "HV battery current, + = discharge"),
    "bat_voltage_V": ("V", "HV battery terminal voltage"),
    "bat_power_W": ("W", "HV battery terminal power, + = discharge (where current and voltage are not logged)"),
    "soc": ("dimensionless", "battery state of charge, fraction 0..1"),
    "bat_temp_degC": ("degC", "battery temperature"),
    "engine_speed_rpm": ("rpm", "engine speed"),
    "engine_torque_Nm": ("N*m", "engine brake torque"),
    "engine_power_W": ("W", "engine brake power (where speed and torque are not logged)"),
    "fuel_rate_g_per_s": ("g/s", "fuel mass flow"),
    "coolant_temp_degC": ("degC", "engine coolant temperature"),
    "bay_temp_degC": ("degC", "engine-bay (compartment) temperature"),
    "ambient_temp_degC": ("degC", "ambient air temperature"),
    "cabin_temp_degC": ("degC", "cabin air temperature"),
    "heater_power_W": ("W", "heat drawn from coolant by the heater core"),
    "vent_temp_degC": ("degC", "vent (heater outlet) air temperature"),
    "blower_flow_kg_per_s": ("kg/s", "blower air mass flow"),
    "hvac_setpoint_degC": ("degC", "HVAC set point"),
    "grade_rad": ("rad", "road grade"),
}

#: Power channels and the channels they follow from when those are logged instead (P = omega tau, P = V I).
DERIVABLE: dict[str, tuple[str, ...]] = {
    "engine_power_W": ("engine_speed_rpm", "engine_torque_Nm"),
    "bat_power_W": ("bat_current_A", "bat_voltage_V"),
}

#: Physical range of each canonical channel, in its canonical unit: a sample outside it is not a reading of a
#: car on a road or a dyno (a garbled cell, a wrong unit, a sensor's error code), and is dropped where it enters
#: (``calib.ingest.common.make_series``) with a count in ``LogMeta.channel_counts``. Wide on purpose: they
#: catch the impossible, not the unusual. ``docs/logs.md`` gives the reason for each bound.
RANGES: dict[str, tuple[float, float]] = {
    "speed_mps": (-0.5, 90.0),  # standstill noise of a few cm/s; 324 km/h
    "bat_current_A": (-1000.0, 1000.0),
    "bat_voltage_V": (0.0, 1500.0),
    "bat_power_W": (-500e3, 500e3),
    "soc": (0.0, 1.0),
    "bat_temp_degC": (-60.0, 100.0),
    "engine_speed_rpm": (0.0, 12000.0),
    "engine_torque_Nm": (-500.0, 2000.0),
    "engine_power_W": (-200e3, 1e6),
    "fuel_rate_g_per_s": (-0.05, 100.0),  # a flow meter's zero offset; 100 g/s is a 1 MW engine
    "coolant_temp_degC": (-60.0, 150.0),
    "bay_temp_degC": (-60.0, 200.0),
    "ambient_temp_degC": (-60.0, 60.0),
    "cabin_temp_degC": (-60.0, 90.0),
    "heater_power_W": (-2e3, 50e3),
    "vent_temp_degC": (-60.0, 120.0),
    "blower_flow_kg_per_s": (0.0, 2.0),
    "hvac_setpoint_degC": (0.0, 40.0),
    "grade_rad": (-0.6, 0.6),  # 68 %
}

Streams = dict  # dict[str, pd.Series]: channel -> irregular samples (index: time_s)


def file_sha256(path) -> str:
    """SHA-256 of a file, read in chunks (logs can be large)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class LogMeta:
    """Where a log came from and what was done to it."""

    source: str
    sha256: str = ""
    format: str = ""
    vehicle_id: str = ""
    start_time: str | None = None
    synthetic: bool = False
    channel_sources: dict = field(default_factory=dict)  # channel -> original column/topic/signal
    original_units: dict = field(default_factory=dict)  # channel -> unit as found in the file
    notes: list = field(default_factory=list)
    # Empty for an intact file; for a damaged one read as far as possible: what was lost (see
    # calib.ingest.damage.Damage.to_dict), so every report built on the log can say it was recovered.
    damage: dict = field(default_factory=dict)
    # channel -> sample accounting where the channel entered (calib.ingest.common.make_series): ``read``,
    # ``nonfinite``, ``out_of_range`` (with ``range`` and the first times), ``merged`` (samples folded into a
    # mean with another at the same time), ``kept``.
    channel_counts: dict = field(default_factory=dict)
    # channel -> how it was estimated when the log does not measure it (fuel from MAF, say): such a channel
    # is never presented as measured.
    estimated: dict = field(default_factory=dict)
    # channel -> [[start, stop), ...] rows of the canonical table whose value was interpolated between samples
    # (no sample fell in the row's bin): fitters that must not treat a filled value as a reading skip them.
    interpolated_rows: dict = field(default_factory=dict)

    def lossy_channels(self, threshold: float = 0.01) -> list[str]:
        """Channels that lost more than ``threshold`` of the samples read (non-finite or impossible values)."""
        out = []
        for ch, c in (self.channel_counts or {}).items():
            lost = int(c.get("nonfinite", 0)) + int(c.get("out_of_range", 0))
            if lost > threshold * max(int(c.get("read", 0)), 1):
                out.append(ch)
        return out

    @property
    def recovered(self) -> bool:
        """True when the log was damaged and read only in part."""
        return bool(self.damage)

    def to_dict(self) -> dict:
        """The metadata as a JSON-able dict."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "LogMeta":
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})


@dataclass
class DriveLog:
    """A drive log on a uniform time base.

    Attributes
    ----------
    data : pandas.DataFrame
        Index ``time_s`` (seconds from the log's start, uniform step), one column per canonical channel
        present (see :data:`CHANNELS`), SI units; NaN where a long gap left no data.
    meta : LogMeta
        Provenance.
    """

    data: pd.DataFrame
    meta: LogMeta

    @property
    def name(self) -> str:
        """The source file name (or the label given when the log was built)."""
        return Path(self.meta.source).name

    @property
    def dt(self) -> float:
        """The sample spacing of the canonical table, in s."""
        t = self.data.index.to_numpy()
        return float(np.median(np.diff(t))) if len(t) > 1 else 1.0

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample, in s."""
        t = self.data.index.to_numpy()
        return float(t[-1] - t[0]) if len(t) else 0.0

    def channels(self) -> list[str]:
        """Canonical channels that have at least one valid (finite) sample."""
        return [c for c in self.data.columns
                if c in CHANNELS and np.isfinite(pd.to_numeric(self.data[c], errors="coerce").to_numpy(float)).any()]

    def has(self, *channels: str) -> bool:
        """Whether every named channel has at least one valid sample."""
        present = set(self.channels())
        return all(c in present for c in channels)

    def missing(self, channels) -> list[str]:
        """Which of the named channels have no valid sample."""
        present = set(self.channels())
        return [c for c in channels if c not in present]

    def require(self, channels, purpose: str) -> None:
        """Raise :class:`MissingChannelsError` naming what is missing for ``purpose``."""
        miss = self.missing(channels)
        if miss:
            raise MissingChannelsError(miss, purpose, self.meta.source)

    @property
    def sampled(self) -> dict:
        """``{channel: bool per row}`` for channels with interpolated rows: True where the row holds a logged
        sample (``LogMeta.interpolated_rows``). Channels not listed have a sample in every finite row."""
        out = {}
        for ch, runs in (self.meta.interpolated_rows or {}).items():
            if ch not in self.data.columns:
                continue
            m = np.isfinite(self.data[ch].to_numpy(float))
            for a, b in runs:
                m[int(a):int(b)] = False
            out[ch] = m
        return out

    @sampled.setter
    def sampled(self, masks: dict) -> None:
        """Record which rows hold a logged sample (``{channel: bool per row}``, e.g. for a table built by hand)."""
        runs = {}
        for ch, m in (masks or {}).items():
            filled = np.isfinite(self.data[ch].to_numpy(float)) & ~np.asarray(m, dtype=bool)
            edges = np.flatnonzero(np.diff(np.concatenate([[0], filled.astype(np.int8), [0]])))
            runs[ch] = edges.reshape(-1, 2).tolist()
        self.meta.interpolated_rows = runs

    def content_digest(self) -> str:
        """SHA-256 of the table itself (times, channels, values): the key of anything computed from the log,
        which the source file's hash alone is not (the same file read with another DBC or map differs)."""
        h = hashlib.sha256()
        h.update(",".join(map(str, self.data.columns)).encode())
        h.update(np.ascontiguousarray(self.data.index.to_numpy(float)).tobytes())
        h.update(np.ascontiguousarray(self.data.to_numpy(float)).tobytes())
        h.update(repr(sorted(self.meta.estimated.items())).encode())
        return h.hexdigest()

    def label(self) -> str:
        """The name, with ``[SYNTHETIC]`` for synthetic logs, ``[LOST SAMPLES]`` when a channel lost more than
        1 % of its samples, ``[ESTIMATED ...]`` naming estimated channels and ``[RECOVERED]`` for damaged
        logs."""
        label = f"{self.name} [SYNTHETIC]" if self.meta.synthetic else self.name
        if self.meta.lossy_channels():
            label += " [LOST SAMPLES]"
        if self.meta.estimated:
            label += " [ESTIMATED " + ", ".join(self.meta.estimated) + "]"
        return f"{label} [RECOVERED]" if self.meta.damage else label
