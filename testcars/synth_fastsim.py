"""A virtual test car that is not our model: NREL's FASTSim 3 thermal Hyundai Sonata Hybrid.

FASTSim 3 (PyPI ``fastsim`` 3.1.0, Apache-2.0, "Copyright 2020 Alliance for Energy Innovation, LLC") ships
``2021_Hyundai_Sonata_Hybrid_Blue_thrml.yaml``: a parallel hybrid with a lumped engine thermal model
(thermostat, radiator, temperature-dependent efficiency), an engine-heated lumped cabin under a PID
climate control, and a lumped battery thermal model, calibrated by NREL on Argonne dynamometer tests
down to -7 degC. Its equations, controller, efficiency curve and heat paths are FASTSim's, not ours, so
calibrating our model on its output tests the fitter against structure it does not share.

:func:`run_fastsim` drives the car over one of our cycles with ambient air temperature in the cycle's
``temp_amb_air_kelvin`` and initial engine, cabin and battery temperatures in the vehicle's ``state``
entries; :func:`synthesise_fastsim` turns the result into logger streams (per-channel rate, noise,
quantisation, dropouts) of what FASTSim models: speed, engine brake power, battery terminal power, fuel
rate, engine (coolant) temperature, cabin temperature, heat drawn by the cabin heater, ambient, SOC and
battery temperature. FASTSim models powers, not engine speed and torque or battery current and voltage,
so those channels are absent. Every log is labelled SYNTHETIC (file name, metadata, header).

Quirks of the car as FASTSim 3.1.0 models it (see docs/test_cars.md for how a fit should treat them):

- the radiator acts only while the car is stopped (its heat transfer uses the stopped-car coefficient);
  on a highway the engine warms to ~120 degC and drops tens of kelvin within seconds of a stop;
- the engine, when on, runs almost always at one power (~14.8 kW, its most efficient point), so the
  logs hardly span the fuel map;
- the heater can move ~15 kW into the cabin within seconds of a cold start (the climate controller's
  limit), far above what a real heater core passes from a cold engine.

The optional dependency is imported lazily; :func:`fastsim_available` tells whether it is installed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.synth import Sensor, sample_signals

K0 = 273.15
#: Lower heating value NREL used to turn measured fuel into fuel power when calibrating this car (J/g).
LHV_J_PER_G = 43205.45
VEHICLE_RESOURCE = "2021_Hyundai_Sonata_Hybrid_Blue_thrml.yaml"
VEHICLE_ID = "SYNTHETIC-FASTSIM3-SONATA-HEV-2021"
FASTSIM_VERSION = "3.1.0"

#: Logger model for the FASTSim channels (a dynamometer-cell/CAN logger at 1 Hz).
FASTSIM_SENSORS: dict[str, Sensor] = {
    "speed_mps": Sensor(1.0, 0.03, 0.1 / 3.6, False),
    "engine_power_W": Sensor(1.0, 100.0, 100.0, True),
    "bat_power_W": Sensor(1.0, 50.0, 10.0, True),
    "fuel_rate_g_per_s": Sensor(1.0, 0.005, 0.001, True),
    "coolant_temp_degC": Sensor(1.0, 0.15, 1.0, False),
    "cabin_temp_degC": Sensor(1.0, 0.1, 0.5, False),
    "heater_power_W": Sensor(1.0, 20.0, 1.0, True),
    "ambient_temp_degC": Sensor(1.0, 0.1, 0.5, False),
    "soc": Sensor(1.0, 0.0, 0.005, False),
    "bat_temp_degC": Sensor(1.0, 0.0, 1.0, False),
}


@dataclass
class FastsimScenario:
    """One FASTSim drive: cycle (our cycle names, ``+`` joins), ambient and initial temperatures (degC).

    FASTSim starts the battery at the middle of its SOC window (0.625) whatever the vehicle's state says.
    """

    name: str
    cycle: str
    T_amb: float
    T_eng0: float
    T_cab0: float
    T_bat0: float
    description: str = ""
    duration_s: float | None = None  # cut the cycle (short samples)


#: The Sonata drives: two cold-soaked calibration drives at -7 degC, a warm restart at -7 degC and a
#: 22 degC drive held out for validation, and single UDDS runs for the cold/warm fuel ratio.
SONATA = [
    FastsimScenario("sonata_cold_udds_hwfet", "udds+hwfet", -7.0, -7.0, -7.0, -7.0,
                    "cold soak at -7 degC, UDDS + HWFET (36 min)"),
    FastsimScenario("sonata_cold_nycc_us06_udds", "nycc+us06+udds", -7.0, -7.0, -7.0, -7.0,
                    "cold soak at -7 degC, NYCC + US06 + UDDS (42 min)"),
    FastsimScenario("sonata_warm_restart", "artemis_urban+udds", -7.0, 70.0, 12.0, -3.0,
                    "restart at -7 degC after a 20-min stop: engine 70 degC, cabin 12 degC; ARTEMIS Urban + UDDS"),
    FastsimScenario("sonata_mild_udds_hwfet", "udds+hwfet", 22.0, 22.0, 22.0, 22.0,
                    "soak at 22 degC, UDDS + HWFET"),
]
#: Cold-soaked and 22 degC UDDS: FASTSim's cold/warm fuel-per-km ratio.
UDDS_COLD = FastsimScenario("sonata_udds_cold", "udds", -7.0, -7.0, -7.0, -7.0, "cold soak at -7 degC, UDDS")
UDDS_WARM = FastsimScenario("sonata_udds_22", "udds", 22.0, 22.0, 22.0, 22.0, "soak at 22 degC, UDDS")
#: The short sample committed under tests/data/fastsim (first 5 min of a cold-soaked UDDS, seed 0).
SAMPLE = FastsimScenario("sonata_cold_udds_300s", "udds", -7.0, -7.0, -7.0, -7.0,
                         "cold soak at -7 degC, first 300 s of UDDS", duration_s=300.0)


def fastsim_available() -> bool:
    """Whether the optional ``fastsim`` package (the ``fastsim`` extra) can be imported."""
    try:
        import fastsim  # noqa: F401
    except ImportError:
        return False
    return True


def _fastsim():
    from calib.errors import IptmError

    try:
        import fastsim
    except ImportError:
        raise IptmError("the FASTSim test car needs the optional package fastsim: "
                        "pip install 'iptm[fastsim]' (fastsim==3.1.0)") from None
    return fastsim


def _vehicle(fsim, sc: FastsimScenario):
    vd = fsim.Vehicle.from_resource(VEHICLE_RESOURCE).to_dict()
    hev = vd["pt_type"]["HEV"]
    cab = vd["cabin"]["LumpedCabin"]["state"]
    cab["temperature_kelvin"] = cab["temp_prev_kelvin"] = sc.T_cab0 + K0
    bat = hev["res"]["thrml"]["RESLumpedThermal"]["state"]
    bat["temperature_kelvin"] = bat["temp_prev_kelvin"] = sc.T_bat0 + K0
    hev["fc"]["thrml"]["FuelConverterThermal"]["state"]["temperature_kelvin"] = sc.T_eng0 + K0
    # a logged drive is not repeated until its SOC balances (FASTSim's default for HEVs)
    hev["sim_params"]["balance_soc"] = False
    veh = fsim.Vehicle.from_dict(vd)
    veh.set_save_interval(1)
    return veh


def _cycle(fsim, sc: FastsimScenario):
    from calib.model.cycles import load_cycle

    cyc = load_cycle(sc.cycle)
    if sc.duration_s is not None:
        keep = cyc.t <= sc.duration_s
        cyc = type(cyc)(cyc.name, cyc.t[keep], cyc.v[keep], None if cyc.grade is None else cyc.grade[keep])
    if abs(cyc.Ts - 1.0) > 1e-9:
        from calib.errors import ScenarioError

        raise ScenarioError(f"FASTSim scenario {sc.name}: cycle {sc.cycle} has step {cyc.Ts} s; need 1 s")
    n = len(cyc.t)
    zeros = [0.0] * n
    d = {"init_elev_meters": 0.0, "time_seconds": [float(x) for x in cyc.t],
         "speed_meters_per_second": [float(x) for x in cyc.v], "dist_meters": [], "grade": zeros,
         "elev_meters": [], "pwr_max_chrg_watts": zeros, "temp_amb_air_kelvin": [sc.T_amb + K0] * n,
         "pwr_solar_load_watts": zeros, "grade_interp": 0.0, "elev_interp": 0.0}
    return fsim.Cycle.from_dict(d)


def pack_energy_J() -> float:
    """The Sonata pack's energy capacity as FASTSim models it (``energy_capacity_joules`` of the resource)."""
    vd = _fastsim().Vehicle.from_resource(VEHICLE_RESOURCE).to_dict()
    return float(vd["pt_type"]["HEV"]["res"]["energy_capacity_joules"])


def run_fastsim(sc: FastsimScenario) -> dict:
    """Drive the Sonata over a scenario; returns the true signals at FASTSim's 1 s steps (SI, degC).

    Keys: ``t``, ``speed_mps``, ``engine_power_W`` (brake power incl. any engine-driven auxiliaries),
    ``bat_power_W`` (terminal, + = discharge), ``fuel_rate_g_per_s`` (fuel power / LHV 43.205 kJ/g),
    ``coolant_temp_degC`` (FASTSim's lumped engine temperature), ``cabin_temp_degC``, ``heater_power_W``
    (heat moved from the engine into the cabin), ``ambient_temp_degC``, ``soc``, ``bat_temp_degC``,
    ``engine_on``, ``tstat_open_frac``; plus ``fuel_g`` and ``distance_km``.
    """
    fsim = _fastsim()
    veh = _vehicle(fsim, sc)
    sd = fsim.SimDrive(veh, _cycle(fsim, sc))
    d = sd.to_dict()
    # A cold engine is power-limited: FASTSim then falls a few hundredths of a mph behind the trace, which
    # its default setting treats as an error; accept misses within its own tolerances (5 % of distance).
    d["sim_params"]["trace_miss_opts"] = "AllowChecked"
    sd = fsim.SimDrive.from_dict(d)
    sd.run()
    df = sd.to_dataframe()
    H = "veh.pt_type.HEV."
    fct = H + "fc.thrml.FuelConverterThermal.history."
    g = lambda c: df[c].to_numpy(dtype=float)  # noqa: E731
    out = {
        "t": g("veh.history.time_seconds"),
        "speed_mps": g("veh.history.speed_ach_meters_per_second"),
        "engine_power_W": g(H + "fc.history.pwr_prop_watts") + g(H + "fc.history.pwr_aux_watts"),
        "bat_power_W": g(H + "res.history.pwr_out_electrical_watts"),
        "fuel_rate_g_per_s": g(H + "fc.history.pwr_fuel_watts") / LHV_J_PER_G,
        "coolant_temp_degC": g(fct + "temperature_kelvin") - K0,
        "cabin_temp_degC": g("veh.cabin.LumpedCabin.history.temperature_kelvin") - K0,
        "heater_power_W": g("veh.hvac.LumpedCabin.history.pwr_thrml_fc_to_cabin_watts"),
        "ambient_temp_degC": g("cyc.temp_amb_air_kelvin") - K0,
        "soc": g(H + "res.history.soc"),
        "bat_temp_degC": g(H + "res.thrml.RESLumpedThermal.history.temperature_kelvin") - K0,
        "engine_on": df[H + "fc.history.fc_on"].to_numpy(dtype=bool),
        "tstat_open_frac": g(fct + "tstat_open_frac"),
    }
    out["fuel_g"] = float(np.sum(out["fuel_rate_g_per_s"][1:] * np.diff(out["t"])))
    out["distance_km"] = float(np.sum(out["speed_mps"][1:] * np.diff(out["t"])) / 1e3)
    return out


#: Channels written to the logs, with how they vary over a step: 'state' (interpolated) or 'flow'
#: (FASTSim's value at step i is the mean over (t[i-1], t[i]]).
LOGGED = {"speed_mps": "state", "engine_power_W": "flow", "bat_power_W": "flow", "fuel_rate_g_per_s": "flow",
          "coolant_temp_degC": "state", "cabin_temp_degC": "state", "heater_power_W": "flow",
          "ambient_temp_degC": "state", "soc": "state", "bat_temp_degC": "state"}


def synthesise_fastsim(sc: FastsimScenario, seed: int = 0, drop_channels=()):
    """Run FASTSim on ``sc`` and sample its signals like a logger.

    Returns
    -------
    true : dict
        :func:`run_fastsim`'s output.
    streams : dict of pandas.Series
        Canonical streams (SI), noisy and quantised, with short dropouts.
    meta : LogMeta
        ``synthetic=True``; notes name FASTSim, its licence and the scenario.
    """
    from calib.drivelog import CHANNELS, LogMeta

    true = run_fastsim(sc)
    t = true["t"]
    sig = {}
    for ch, kind in LOGGED.items():
        if ch in drop_channels:
            continue
        v = true[ch]
        sig[ch] = (kind, v[1:] if kind == "flow" else v)
    rng = np.random.default_rng(seed)
    streams = sample_signals(t, sig, FASTSIM_SENSORS, rng,
                             nonneg=("speed_mps", "engine_power_W", "fuel_rate_g_per_s", "heater_power_W"))
    meta = LogMeta(source=f"SYNTHETIC_fastsim_{sc.name}", format="synthetic", vehicle_id=VEHICLE_ID,
                   synthetic=True, channel_sources={c: "FASTSim 3" for c in streams},
                   original_units={c: CHANNELS[c][0] for c in streams},
                   notes=[f"SYNTHETIC log: simulated with NREL FASTSim {FASTSIM_VERSION} (Apache-2.0, Copyright 2020 "
                          f"Alliance for Energy Innovation, LLC), vehicle {VEHICLE_RESOURCE}; not measured on a car",
                          f"scenario {sc.name}: {sc.description}; ambient {sc.T_amb:g} degC; initial engine "
                          f"{sc.T_eng0:g} degC, cabin {sc.T_cab0:g} degC, battery {sc.T_bat0:g} degC; "
                          f"seed {seed}",
                          f"true totals: fuel {true['fuel_g']:.1f} g over {true['distance_km']:.2f} km"])
    return true, streams, meta


def write_fastsim_log(sc: FastsimScenario, path, seed: int = 0):
    """Write one scenario's logger CSV to ``path``; returns the true signals."""
    from calib.ingest.writers import write_streams

    true, streams, meta = synthesise_fastsim(sc, seed=seed)
    write_streams(streams, meta, path, "csv")
    return true


def udds_cold_warm_ratio() -> dict:
    """FASTSim's fuel per km on a cold-soaked -7 degC UDDS over that on a 22 degC UDDS."""
    c, w = run_fastsim(UDDS_COLD), run_fastsim(UDDS_WARM)
    fc, fw = c["fuel_g"] / c["distance_km"], w["fuel_g"] / w["distance_km"]
    return {"cold_g_per_km": fc, "warm_g_per_km": fw, "ratio": fc / fw,
            "soc_change_cold": float(c["soc"][-1] - c["soc"][0]), "soc_change_warm": float(w["soc"][-1] - w["soc"][0])}


def write_fastsim_logs(out_dir, scenarios=None, seed: int = 0, progress=print) -> dict:
    """Write each scenario as ``SYNTHETIC_fastsim_<name>.csv`` plus ``SYNTHETIC_fastsim_truth.json``.

    The JSON holds, per log, the true totals and the scenario, and FASTSim's cold/warm UDDS ratio.
    """
    from pathlib import Path

    from calib.fileio import write_json

    out = Path(out_dir)
    scenarios = list(scenarios or SONATA)
    info = {"note": "SYNTHETIC: true totals of the FASTSim 3 logs next to this file", "simulator":
            f"NREL FASTSim {FASTSIM_VERSION} (Apache-2.0)", "vehicle": VEHICLE_RESOURCE, "logs": {}}
    for i, sc in enumerate(scenarios):
        path = out / f"SYNTHETIC_fastsim_{sc.name}.csv"
        true = write_fastsim_log(sc, path, seed=seed + i)
        info["logs"][sc.name] = {"file": str(path), "fuel_g": true["fuel_g"], "distance_km": true["distance_km"],
                                 "duration_s": float(true["t"][-1]), "scenario": sc.__dict__}
        progress(f"SYNTHETIC (FASTSim) {sc.name}: {true['t'][-1]:.0f} s, {true['fuel_g']:.0f} g fuel -> {path}")
    info["udds_cold_warm"] = udds_cold_warm_ratio()
    truth = out / "SYNTHETIC_fastsim_truth.json"
    write_json(truth, info)
    progress(f"true totals: {truth}")
    return info


__all__ = ["FastsimScenario", "SONATA", "SAMPLE", "write_fastsim_log", "UDDS_COLD", "UDDS_WARM", "FASTSIM_SENSORS", "fastsim_available",
           "run_fastsim", "synthesise_fastsim", "udds_cold_warm_ratio", "write_fastsim_logs"]
