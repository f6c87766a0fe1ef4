"""calib: the physics of the workbench: the vehicle model, parameter sets, ingestion of drive logs,
calibration with uncertainty and validation.

A script needs only this front door (run from the repository root, whose ``logs/`` holds the bundled
SYNTHETIC logs; the test suite runs it as a doctest):

>>> import calib
>>> log = calib.read_log("logs/winter_cold_start.blf")
>>> result = calib.calibrate([log], validate=[calib.read_log("logs/winter_warm_restart.blf")], progress=False)
>>> sim = calib.simulate(result.params, "udds", T_amb=-7.0)
>>> print(f"UDDS at -7 degC: {sim.fuel_g:.0f} g of fuel")  # doctest: +ELLIPSIS
UDDS at -7 degC: ... g of fuel

Sub-packages: :mod:`calib.model` (equations, parameters, cycles, simulation, stock controller, fuel maps),
:mod:`calib.ingest` (readers, writers, resampling, channel report), :mod:`calib.fit` (identification
toolkit, subsystem fitters, driver, validation), :mod:`calib.synth` (SYNTHETIC logs with a known truth).
Test cars that are not this model live beside it, in the package ``testcars``.
``calib`` never imports ``optimize``, ``iptm`` or ``testcars``.
"""
# first, before any kernel is decorated: numba's compiled code is keyed by the source version
from calib._numba_cache import CACHE_DIR as _NUMBA_CACHE_DIR  # noqa: F401
from calib._version import __version__

from calib.errors import (ChannelLossWarning, IptmError, IptmWarning, LogFormatError, MissingChannelsError,
                          ParameterError, ResultFileError, ScenarioError)
from calib.drivelog import CHANNELS, DriveLog, LogMeta, file_sha256
from calib.fileio import atomic_path, read_config, save_figure, write_json, write_text
from calib.store import Store, code_version, content_key, default_root, result_key
from calib.economy import format_economy, log_fuel_distance
from calib.units import RPM, convert
from calib.model import (Cycle, ParameterSet, RuleBasedController, RuleParams, SimResult,
                         available_cycles, default_parameters, load_cycle, simulate)
from calib.ingest import channel_report, read_canonical, read_log, write_canonical
from calib.fit import CalibrationResult, calibrate, replay, validate
from calib.synth import BUNDLED, HvacController, draw_truth, synthesise

__all__ = [
    "__version__",
    "IptmError", "LogFormatError", "MissingChannelsError", "ParameterError", "ResultFileError", "ScenarioError",
    "IptmWarning", "ChannelLossWarning",
    "DriveLog", "LogMeta", "CHANNELS", "file_sha256",
    "ParameterSet", "default_parameters", "Cycle", "load_cycle", "available_cycles",
    "simulate", "SimResult", "RuleBasedController", "RuleParams",
    "read_log", "channel_report", "read_canonical", "write_canonical",
    "calibrate", "CalibrationResult", "replay", "validate",
    "synthesise", "draw_truth", "BUNDLED", "HvacController",
    # files, the content-keyed cache, units and economy, for the application layer
    "write_json", "write_text", "read_config", "atomic_path", "save_figure",
    "Store", "content_key", "code_version", "result_key", "default_root",
    "convert", "RPM", "format_economy", "log_fuel_distance",
]
