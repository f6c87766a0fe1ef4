"""Fuel economy in the units engineers read: grams over a distance as L/100 km and US mpg.

Stated once here; the simulator's summary, the case-study table, the report and the dashboard call it.
"""
from __future__ import annotations

import math

#: Gasoline density (kg/L), as used for every litre figure of the workbench.
GASOLINE_KG_PER_L = 0.74
#: 1 mpg (US) in km/L.
KM_PER_L_PER_MPG = 0.4251


def litres(fuel_g: float) -> float:
    """Volume of ``fuel_g`` grams of gasoline in litres."""
    return float(fuel_g) / 1e3 / GASOLINE_KG_PER_L


def l_per_100km(fuel_g: float, distance_km: float) -> float:
    """Consumption in L/100 km (NaN without distance)."""
    return litres(fuel_g) / distance_km * 100.0 if distance_km > 0 else math.nan


def mpg(fuel_g: float, distance_km: float) -> float:
    """Economy in US miles per gallon (inf when no fuel was burnt, NaN without distance)."""
    if not distance_km > 0:
        return math.nan
    if fuel_g <= 0:
        return math.inf
    return distance_km / litres(fuel_g) / KM_PER_L_PER_MPG


def economy(fuel_g: float, distance_km: float) -> dict:
    """``{"L_per_100km": ..., "mpg": ...}`` for ``fuel_g`` grams over ``distance_km``."""
    return {"L_per_100km": l_per_100km(fuel_g, distance_km), "mpg": mpg(fuel_g, distance_km)}


def format_economy(fuel_g: float, distance_km: float) -> str:
    """``"4.22 L/100 km, 55.7 mpg"`` (or ``"-"`` without distance)."""
    e = economy(fuel_g, distance_km)
    if not math.isfinite(e["L_per_100km"]):
        return "-"
    return f"{e['L_per_100km']:.2f} L/100 km, {e['mpg']:.1f} mpg"


def log_fuel_distance(log) -> tuple[float, float]:
    """Fuel burnt (g) and distance driven (km) over a drive log, integrating its fuel-rate and speed
    channels on the log's time base (NaN for a channel the log lacks; gaps count as nothing)."""
    import numpy as np

    d = log.data
    t = d.index.to_numpy(float)
    if len(t) < 2:
        return math.nan, math.nan
    dt = np.diff(t)

    def integral(col):
        if col not in d.columns or not d[col].notna().any():
            return math.nan
        v = d[col].to_numpy(float)
        return float(np.nansum(0.5 * (v[1:] + v[:-1]) * dt))

    fuel = integral("fuel_rate_g_per_s")
    dist = integral("speed_mps")
    return fuel, dist / 1e3 if dist == dist else math.nan
