"""Calibration: the identification toolkit, per-log arrays and replay kernels, one fitter per subsystem,
the driver :func:`calibrate`, and validation on held-out logs.

Modules: :mod:`~calib.fit.toolkit` (result types, lmfit wrapper, uncertainty, identifiability),
:mod:`~calib.fit.replay` (log arrays, compiled replays), :mod:`~calib.fit.battery`, :mod:`~calib.fit.fuel`,
:mod:`~calib.fit.thermal`, :mod:`~calib.fit.cabin` (the subsystem fitters), :mod:`~calib.fit.driver`
(:func:`calibrate`), :mod:`~calib.fit.validate` (replay of a log, metrics, plots).
"""
from calib.fit.toolkit import ParamEstimate, SubsystemFit
from calib.fit.driver import SUBSYSTEM_PARAMS, CalibrationResult, calibrate
from calib.fit.validate import (CHANNEL_METRICS, Replay, diagnostics, plot_residual_comparison, plot_residuals,
                                plot_validation, replay, truth_comparison, validate)
from calib.fit.replay import fuel_replay, log_arrays
from calib.fit.battery import current_from_power_table, fit_battery

__all__ = ["calibrate", "CalibrationResult", "SUBSYSTEM_PARAMS", "ParamEstimate", "SubsystemFit",
           "replay", "validate", "Replay", "plot_validation", "diagnostics", "plot_residuals",
           "plot_residual_comparison", "truth_comparison", "CHANNEL_METRICS",
           "log_arrays", "fuel_replay", "fit_battery", "current_from_power_table"]
