"""Plausible multi-rate sensor streams for ingestion tests and the ingestion benchmark.

Not a vehicle model (that is :mod:`calib.synth`): smooth, bounded traces at realistic per-signal rates,
quantised like the sensors (SOC 0.5 %, temperatures 1 degC...) and with a dropout, so readers, writers
and resampling can be checked format against format. Everything it makes is labelled synthetic.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from calib.drivelog import LogMeta

#: Default sample rates, Hz (CAN-like: fast powertrain signals, slow thermal ones).
DEFAULT_RATES = {
    "speed_mps": 10.0, "bat_current_A": 10.0, "bat_voltage_V": 10.0, "soc": 1.0, "bat_temp_degC": 1.0,
    "engine_speed_rpm": 10.0, "engine_torque_Nm": 10.0, "fuel_rate_g_per_s": 10.0,
    "coolant_temp_degC": 1.0, "bay_temp_degC": 1.0, "ambient_temp_degC": 1.0, "cabin_temp_degC": 1.0,
    "heater_power_W": 1.0, "vent_temp_degC": 1.0, "blower_flow_kg_per_s": 1.0, "hvac_setpoint_degC": 1.0,
    "grade_rad": 1.0,
}

#: Quantisation steps (canonical units), no finer than real loggers/CAN give.
QUANTUM = {
    "speed_mps": 0.01 / 3.6, "bat_current_A": 0.1, "bat_voltage_V": 1.0, "soc": 0.005, "bat_temp_degC": 1.0,
    "engine_speed_rpm": 0.78125, "engine_torque_Nm": 0.1, "fuel_rate_g_per_s": 0.001,
    "coolant_temp_degC": 1.0, "bay_temp_degC": 1.0, "ambient_temp_degC": 1.0, "cabin_temp_degC": 1.0,
    "heater_power_W": 1.0, "vent_temp_degC": 1.0, "blower_flow_kg_per_s": 0.0001, "hvac_setpoint_degC": 0.5,
    "grade_rad": 0.0001,
}


def _q(x, step):
    return np.round(np.asarray(x) / step) * step


def fabricate_streams(duration_s: float = 120.0, seed: int = 0, rates: dict | None = None,
                      dropout: tuple[float, float] | None = (40.0, 52.0),
                      channels=None) -> tuple[dict, LogMeta]:
    """Make multi-rate, quantised streams of a winter stop-and-go drive.

    Parameters
    ----------
    duration_s : float
        Length of the drive.
    seed : int
        Random seed (noise and phases).
    rates : dict, optional
        Channel -> Hz, over :data:`DEFAULT_RATES`.
    dropout : (start, end) or None
        The coolant temperature and SOC have no samples in this window (a logger dropout longer than
        the default 5 s gap limit).
    channels : iterable, optional
        Subset of channels to make (default all in :data:`DEFAULT_RATES`).

    Returns
    -------
    (Streams, LogMeta)
        ``meta.synthetic`` is True.
    """
    rng = np.random.default_rng(seed)
    r = dict(DEFAULT_RATES)
    r.update(rates or {})
    chans = list(channels) if channels is not None else list(DEFAULT_RATES)
    ph = rng.uniform(0, 2 * np.pi, 4)

    def speed(t):
        return np.clip(12 + 10 * np.sin(2 * np.pi * t / 90 + ph[0]) + 3 * np.sin(2 * np.pi * t / 17 + ph[1]), 0, None)

    def current(t):
        return 40 * np.sin(2 * np.pi * t / 30 + ph[2]) + 5 * np.sin(2 * np.pi * t / 7)

    fns = {
        "speed_mps": speed,
        "bat_current_A": current,
        "bat_voltage_V": lambda t: 220.8 - 0.26 * current(t),
        "soc": lambda t: 0.55 + 0.05 * np.sin(2 * np.pi * t / 300 + ph[3]),
        "bat_temp_degC": lambda t: -5 + 3 * t / max(duration_s, 1),
        "engine_speed_rpm": lambda t: np.where(np.sin(2 * np.pi * t / 60) > -0.3, 1200 + 800 * np.abs(np.sin(2 * np.pi * t / 45)), 0.0),
        "engine_torque_Nm": lambda t: 60 + 40 * np.sin(2 * np.pi * t / 45),
        "fuel_rate_g_per_s": lambda t: 0.6 + 0.5 * np.abs(np.sin(2 * np.pi * t / 45)),
        "coolant_temp_degC": lambda t: -10 + 95 * (1 - np.exp(-t / 400)),
        "bay_temp_degC": lambda t: -8 + 30 * (1 - np.exp(-t / 600)),
        "ambient_temp_degC": lambda t: -10 + 0.5 * np.sin(2 * np.pi * t / 500),
        "cabin_temp_degC": lambda t: -8 + 28 * (1 - np.exp(-t / 500)),
        "heater_power_W": lambda t: 3000 + 1500 * np.sin(2 * np.pi * t / 200),
        "vent_temp_degC": lambda t: -5 + 45 * (1 - np.exp(-t / 300)),
        "blower_flow_kg_per_s": lambda t: 0.08 + 0.02 * np.sin(2 * np.pi * t / 100),
        "hvac_setpoint_degC": lambda t: np.full_like(t, 21.0),
        "grade_rad": lambda t: 0.02 * np.sin(2 * np.pi * t / 150),
    }
    streams = {}
    for ch in chans:
        hz = r[ch]
        # Each sensor has its own clock phase, as on a real bus.
        t = np.arange(0.0, duration_s, 1.0 / hz) + (rng.uniform(0, 1.0 / hz) if ch != "speed_mps" else 0.0)
        t = t[t <= duration_s]
        v = fns[ch](t) + rng.normal(0, QUANTUM[ch] * 0.3, len(t))
        v = _q(v, QUANTUM[ch])
        if ch in ("speed_mps", "engine_speed_rpm", "fuel_rate_g_per_s", "heater_power_W", "blower_flow_kg_per_s"):
            v = np.clip(v, 0.0, None)  # these sensors cannot read below zero
        if dropout is not None and ch in ("coolant_temp_degC", "soc"):
            keep = (t < dropout[0]) | (t >= dropout[1])
            t, v = t[keep], v[keep]
        streams[ch] = pd.Series(np.round(v, 12), index=pd.Index(np.round(t, 6), name="time_s"), name=ch)
    meta = LogMeta(source="fabricated", format="streams", vehicle_id="prius-test", synthetic=True,
                   start_time="2026-01-15T07:30:00+00:00", notes=["fabricated test streams, not a vehicle model"])
    return streams, meta
