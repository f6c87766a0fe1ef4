"""Measured engine fuel maps: read a speed x torque map and derive the optimal operating line (OOL).

The model runs the engine on its OOL (docs/model.md s.2): for each engine power the speed that burns the
least fuel. A measured map is therefore reduced, once, to the tables the model uses: engine efficiency
``eta_ool`` and speed ``n_ool_rpm`` at power breakpoints ``P_e``. The map is a CSV in long form, one
operating point per row, with units in the header (converted with pint)::

    speed [rpm],torque [N*m],fuel [g/s]
    1000,10,0.21
    ...

Accepted header names: ``speed``/``engine_speed``/``n``; ``torque``/``engine_torque``/``tau``;
``fuel``/``fuel_rate``/``W_f``. Fuel may be in g/s, kg/h, L/h (gasoline density 0.74 kg/L) and so on.
Points need not lie on a rectangular grid: fuel is interpolated linearly over the triangulated points, and
nothing is extrapolated outside their convex hull (an operating point outside the measured region is not
eligible for the OOL).
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import IptmError
from calib.units import RPM

_ALIASES = {"speed": ("speed", "engine_speed", "n", "n_e", "rpm"),
            "torque": ("torque", "engine_torque", "tau", "trq"),
            "fuel": ("fuel", "fuel_rate", "w_f", "fuel_flow", "mdot_fuel")}
_CANON = {"speed": "rpm", "torque": "N*m", "fuel": "g/s"}


@dataclass
class FuelMap:
    """Scattered fuel-map points in canonical units and where they came from."""

    speed_rpm: np.ndarray
    torque_Nm: np.ndarray
    fuel_g_per_s: np.ndarray
    source: str
    sha256: str

    @property
    def power_W(self) -> np.ndarray:
        """Engine power of every map point, in W."""
        return self.speed_rpm * RPM * self.torque_Nm


def read_fuel_map(path) -> FuelMap:
    """Read a long-form fuel-map CSV (see module docstring); one clear error for anything wrong."""
    import pandas as pd

    from calib.units import convert

    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise IptmError(f"{path}: cannot read fuel map ({exc.strerror})") from None
    if not raw.strip():
        raise IptmError(f"{path}: the fuel map is empty")
    try:
        df = pd.read_csv(path, comment="#")
    except (ValueError, UnicodeDecodeError) as exc:
        raise IptmError(f"{path}: not a readable CSV fuel map ({exc})") from None
    cols = {}
    for col in df.columns:
        m = re.fullmatch(r"\s*([^\[]+?)\s*(?:\[(.*)\])?\s*", str(col))
        name, unit = m.group(1).strip().lower(), (m.group(2) or "").strip()
        for key, names in _ALIASES.items():
            if name in names:
                if not unit:
                    raise IptmError(f"{path}: column {col!r} has no unit; write it as '{key} [{_CANON[key]}]'")
                cols[key] = (col, unit)
    missing = [k for k in _ALIASES if k not in cols]
    if missing:
        raise IptmError(f"{path}: fuel map needs speed, torque and fuel columns; missing {', '.join(missing)} "
                        f"(found {list(df.columns)})")
    vals = {}
    for key, (col, unit) in cols.items():
        x = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise IptmError(f"{path}: line {bad[0] + 2}: column {col!r} is not a number")
        vals[key] = np.asarray(convert(x, unit, _CANON[key]), dtype=float)
    if np.any(vals["speed"] <= 0) or np.any(vals["fuel"] < 0):
        raise IptmError(f"{path}: speeds must be positive and fuel rates non-negative")
    if len(df) < 6:
        raise IptmError(f"{path}: a fuel map needs at least 6 operating points (has {len(df)})")
    return FuelMap(vals["speed"], vals["torque"], vals["fuel"], str(path), hashlib.sha256(raw).hexdigest())


def optimal_operating_line(fm: FuelMap, LHV_J_per_g: float, n_power: int = 40, n_speed: int = 200):
    """For each power, the map speed of least fuel.

    Returns
    -------
    P_W, n_rpm, eta : ndarray
        Power breakpoints (from 0 to the map's largest power), OOL speed and efficiency ``P / (W_f LHV)``.
        At P = 0 the speed is the map's lowest and the efficiency is taken from the first positive point.
    """
    from scipy.interpolate import LinearNDInterpolator

    pts = np.column_stack([fm.speed_rpm, fm.torque_Nm])
    f = LinearNDInterpolator(pts, fm.fuel_g_per_s)  # NaN outside the convex hull: never extrapolated
    speeds = np.linspace(fm.speed_rpm.min(), fm.speed_rpm.max(), n_speed)
    P_max = float(np.max(fm.power_W))
    P = np.linspace(0.0, P_max, n_power + 1)[1:]
    n_opt, eta = np.empty(P.size), np.empty(P.size)
    for i, p in enumerate(P):
        tau = p / (speeds * RPM)
        w = f(speeds, tau)
        w = np.where(np.isfinite(w) & (w > 0), w, np.inf)
        j = int(np.argmin(w))
        if not np.isfinite(w[j]):
            n_opt[i], eta[i] = np.nan, np.nan
            continue
        n_opt[i], eta[i] = speeds[j], p / (w[j] * LHV_J_per_g)
    ok = np.isfinite(eta)
    if ok.sum() < 3:
        raise IptmError(f"{fm.source}: the map covers too few powers to define an operating line")
    P, n_opt, eta = P[ok], n_opt[ok], eta[ok]
    return (np.concatenate([[0.0], P]), np.concatenate([[fm.speed_rpm.min()], n_opt]),
            np.concatenate([[eta[0]], eta]))


def apply_fuel_map(params, path):
    """A copy of ``params`` whose OOL tables come from the measured map at ``path``.

    ``fuel_scale`` is reset to 1 (the map is taken as measured) and ``P_e_max_W`` to the map's largest
    power; the provenance names the file and its hash.
    """
    fm = read_fuel_map(path)
    P, n, eta = optimal_operating_line(fm, float(params["LHV_J_per_g"]))
    eta = np.clip(eta, *params.param("eta_ool").bounds)
    n = np.clip(n, *params.param("n_ool_rpm").bounds)
    new = params.copy()
    src = f"measured fuel map {Path(path).name} (sha256 {fm.sha256[:12]}), OOL derived by calib.model.fuelmap"
    for name, vals in (("eta_ool", eta), ("n_ool_rpm", n)):
        p = new.param(name)
        p.x, p.value, p.source, p.status = [float(v) for v in P], [float(v) for v in vals], src, "prior"
    lo, hi = new.param("P_e_max_W").bounds
    new.param("P_e_max_W").value = float(np.clip(P[-1], lo, hi))
    new.param("P_e_max_W").source = src
    new.param("fuel_scale").value = 1.0
    new.param("fuel_scale").source = "1: the measured map is used as measured"
    new.validate()
    return new
