"""Optimal experiment design: which drive would inform the parameters a calibration left weak.

:mod:`~calib.design.oed` (Fisher information, posterior covariance, D-optimal and posterior-sd criteria,
exhaustive search), :mod:`~calib.design.prior` (a calibration artifact as the prior, weak parameters),
:mod:`~calib.design.drive` (road and dynamometer drive plans for the model under its rule-based
controller, the plan CSV and figure).
"""
from calib.design.drive import (Design, Plan, Planner, header_lines, log_inputs, make_plan, plan_frame, plot_plan,
                                simulate_cycle, write_plan_csv)
from calib.design.prior import DESIGNABLE, ArtifactPrior, subsystem_of

__all__ = ["ArtifactPrior", "DESIGNABLE", "Design", "Plan", "Planner", "make_plan", "plot_plan", "write_plan_csv",
           "header_lines", "log_inputs", "plan_frame", "simulate_cycle", "subsystem_of"]
