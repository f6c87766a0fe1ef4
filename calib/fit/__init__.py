"""Calibration: the identification toolkit, per-log arrays and replay kernels, one fitter per subsystem,
the driver :func:`calibrate`, and validation on held-out logs.

Modules: :mod:`~calib.fit.toolkit` (result types, lmfit wrapper, uncertainty, identifiability),
:mod:`~calib.fit.replay` (log arrays, compiled replays), :mod:`~calib.fit.battery`, :mod:`~calib.fit.fuel`,
:mod:`~calib.fit.thermal`, :mod:`~calib.fit.cabin` (the subsystem fitters), :mod:`~calib.fit.driver`
(:func:`calibrate`), :mod:`~calib.fit.validate` (replay of a log, metrics, plots).
"""
from calib.fit.toolkit import ParamEstimate, SubsystemFit
from calib.fit.driver import SUBSYSTEM_PARAMS, CalibrationResult, calibrate
from calib.fit.validate import Replay, diagnostics, plot_residuals, plot_validation, replay, validate

__all__ = ["calibrate", "CalibrationResult", "SUBSYSTEM_PARAMS", "ParamEstimate", "SubsystemFit",
           "replay", "validate", "Replay", "plot_validation", "diagnostics", "plot_residuals"]
