"""calib: the physics of the workbench: the vehicle model, parameter sets, ingestion of drive logs,
calibration with uncertainty and validation.

A script needs only this front door::

    import calib
    log = calib.read_log("logs/winter_cold_start.blf")
    result = calib.fit.driver([log], validate=[calib.read_log("logs/winter_warm_restart.blf")])
    sim = calib.model.simulate(result.params, "udds", T_amb=-7.0)

Sub-packages: :mod:`calib.model` (equations, parameters, cycles, simulation, stock controller, fuel maps),
:mod:`calib.ingest` (readers, writers, resampling, channel report), :mod:`calib.fit` (identification
toolkit, subsystem fitters, driver, validation), :mod:`calib.synth` (SYNTHETIC logs with a known truth).
``calib`` never imports ``optimize`` or ``iptm``.
"""
from ._version import __version__

from .errors import (IptmError, LogFormatError, MissingChannelsError, ParameterError,
                     ScenarioError)
from .drivelog import DriveLog, LogMeta
from .model import (Cycle, ParameterSet, RuleBasedController, RuleParams, SimResult,
                    available_cycles, default_parameters, load_cycle, simulate)
from .ingest import channel_report, read_canonical, read_log, write_canonical
from .fit import CalibrationResult, calibrate, replay, validate
from .synth import synthesise

__all__ = [
    "__version__",
    "IptmError", "LogFormatError", "MissingChannelsError", "ParameterError", "ScenarioError",
    "DriveLog", "LogMeta",
    "ParameterSet", "default_parameters", "Cycle", "load_cycle", "available_cycles",
    "simulate", "SimResult", "RuleBasedController", "RuleParams",
    "read_log", "channel_report", "read_canonical", "write_canonical",
    "calibrate", "CalibrationResult", "replay", "validate",
    "synthesise",
]
