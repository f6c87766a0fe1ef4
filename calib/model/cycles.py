"""Drive cycles: speed traces on a uniform time base.

Bundled cycles (``calib/data/cycles``, see its README for sources and licences): ``artemis_urban``
(default winter stand-in for the paper's Ann Arbor cycle), ``nycc``, ``manhattan``, ``udds``, ``hwfet``,
``us06``. Any CSV with ``time_s`` and a speed column (``speed_kph``, ``speed_mps`` or a header with a unit)
works, and so does a :class:`calib.drivelog.DriveLog` with ``speed_mps``.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from calib.errors import IptmError, MissingChannelsError

CYCLE_DIR = resources.files("calib") / "data" / "cycles"


@dataclass
class Cycle:
    """A speed trace: ``t`` (s, uniform step ``Ts``) and ``v`` (m/s)."""

    name: str
    t: np.ndarray
    v: np.ndarray
    grade: np.ndarray | None = None

    @property
    def Ts(self) -> float:
        """Time step in s (the cycle's sample spacing)."""
        return float(self.t[1] - self.t[0])

    @property
    def n_steps(self) -> int:
        """Number of model steps (samples minus one)."""
        return len(self.v) - 1

    @property
    def distance_m(self) -> float:
        """Distance driven over the cycle, in m."""
        return float(np.sum(0.5 * (self.v[1:] + self.v[:-1])) * self.Ts)

    def describe(self) -> dict:
        """One line: name, duration, distance and mean speed."""
        return {"name": self.name, "duration_s": float(self.t[-1] - self.t[0]),
                "distance_km": self.distance_m / 1e3,
                "mean_speed_kph": self.distance_m / max(self.t[-1] - self.t[0], 1e-9) * 3.6,
                "standstill_frac": float(np.mean(self.v < 0.1))}


def available_cycles() -> list[str]:
    """Names of the bundled drive cycles (``calib/data/cycles``)."""
    return sorted(p.name[:-4] for p in CYCLE_DIR.iterdir() if p.name.endswith(".csv"))


def _resample(name, t, v, Ts):
    if len(t) < 2:
        raise IptmError(f"cycle {name}: needs at least two samples")
    if np.any(np.diff(t) <= 0):
        raise IptmError(f"cycle {name}: time must be strictly increasing")
    if np.any(~np.isfinite(v)) or np.any(v < -0.01):
        raise IptmError(f"cycle {name}: speed has NaN or negative values")
    tt = np.arange(0.0, t[-1] - t[0] + 1e-9, Ts)
    return Cycle(name, tt, np.clip(np.interp(tt + t[0], t, v), 0.0, None))


def load_cycle(spec, Ts: float = 1.0) -> Cycle:
    """Load a cycle by bundled name, CSV path, or from a DriveLog's speed channel."""
    from calib.drivelog import DriveLog

    if isinstance(spec, Cycle):
        return spec
    if isinstance(spec, DriveLog):
        if not spec.has("speed_mps"):
            raise MissingChannelsError(["speed_mps"], "extract a drive cycle", spec.meta.source)
        s = spec.data["speed_mps"].interpolate(limit_direction="both")
        return _resample(f"{spec.name} (from log)", s.index.to_numpy(float), s.to_numpy(float), Ts)
    name = str(spec)
    if "+" in name and not Path(name).is_file():
        # "udds+hwfet": cycles driven back to back
        parts = [load_cycle(n.strip(), Ts) for n in name.split("+")]
        v = np.concatenate([parts[0].v] + [c.v[1:] for c in parts[1:]])
        return Cycle(name, np.arange(v.size) * Ts, v)
    path = Path(name)
    if not path.suffix and (CYCLE_DIR / f"{name}.csv").is_file():
        path = Path(str(CYCLE_DIR / f"{name}.csv"))
    if not path.is_file():
        raise IptmError(f"cycle {name!r} not found: give a file or one of {', '.join(available_cycles())}")
    try:
        df = pd.read_csv(path, comment="#")
    except Exception as exc:  # pandas raises many types for unreadable text
        why = " ".join(str(exc).split())[:200]  # pandas' messages span lines
        raise IptmError(f"{path}: not a readable cycle CSV ({why}); a cycle CSV has a time_s column and a "
                        "speed_kph (or speed_mps) column") from None
    cols = {c.strip().lower(): c for c in df.columns}
    if "time_s" not in cols:
        raise IptmError(f"{path}: a cycle CSV needs a time_s column (has {str(list(df.columns))[:200]})")
    t = df[cols["time_s"]].to_numpy(float)
    if "speed_kph" in cols:
        v = df[cols["speed_kph"]].to_numpy(float) / 3.6
    elif "speed_mps" in cols:
        v = df[cols["speed_mps"]].to_numpy(float)
    else:
        raise IptmError(f"{path}: a cycle CSV needs speed_kph or speed_mps (has {list(df.columns)})")
    return _resample(path.stem, t, v, Ts)
