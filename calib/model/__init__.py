"""The vehicle model: equations, parameter sets, drive cycles, simulation, the stock controller, fuel maps.

:mod:`calib.model.equations` holds every equation once (numba scalar functions); everything else,
the simulator, the fitters and the DP kernels in :mod:`optimize`, calls those functions.
"""
from calib.model.equations import (CAT, IDLE, INFEASIBLE_REASONS, OFF, ON, OUTPUTS, battery, battery_ocv_r, cabin_rate,
                        coolant_flows, engine_speed, evaluate, f_cold, fuel_map, fuel_rate, heater_limit,
                        power_split, radiator, step, traction_power)
from calib.model.params import ENTRY_FIELDS, Parameter, ParameterSet, default_parameters
from calib.model.cycles import Cycle, available_cycles, load_cycle
from calib.model.rulebased import RuleBasedController, RuleParams
from calib.model.simulate import SimResult, credit_per_gram, fuel_equivalents_g, sim_from_arrays, sim_to_arrays, simulate
from calib.model.continuation import (CONTINUATION_CYCLE, continuation_corrected, continuation_credit_per_gram,
                                      continuation_run, continuation_value)
from calib.model.fuelmap import FuelMap, apply_fuel_map, optimal_operating_line, read_fuel_map
from calib.model.epa import bag_table, epa_comparison, hot_cycle_bags, tune_fuel_scale
from calib.model import ftp
from calib.model.ftp import COLD_FTP, WARM_FTP, FtpResult, ftp_comparison, run_ftp, weighted_fuel_per_distance

__all__ = [
    "OFF", "IDLE", "ON", "CAT", "OUTPUTS", "INFEASIBLE_REASONS",
    "traction_power", "power_split", "battery_ocv_r", "battery", "f_cold", "engine_speed", "fuel_map",
    "fuel_rate", "heater_limit", "radiator", "coolant_flows", "cabin_rate", "step", "evaluate",
    "Parameter", "ParameterSet", "default_parameters", "ENTRY_FIELDS",
    "Cycle", "available_cycles", "load_cycle",
    "RuleBasedController", "RuleParams",
    "SimResult", "simulate", "fuel_equivalents_g", "credit_per_gram", "sim_to_arrays", "sim_from_arrays",
    "CONTINUATION_CYCLE", "continuation_run", "continuation_value", "continuation_corrected",
    "continuation_credit_per_gram",
    "FuelMap", "read_fuel_map", "optimal_operating_line", "apply_fuel_map",
    "epa_comparison", "tune_fuel_scale", "bag_table", "hot_cycle_bags",
    "WARM_FTP", "COLD_FTP", "FtpResult", "run_ftp", "ftp_comparison", "weighted_fuel_per_distance",
    "ftp",  # the module: its bag constants, and the blower ramp the EPA benchmark varies
]
