"""optimize: fuel-optimal control of the calibrated model by dynamic programming.

A script needs only this front door (the first minute of the paper's drive; ``run_case_study(params, scen)``
adds the tuned rule-based controller and the three formulations):

>>> import calib, optimize
>>> params = calib.default_parameters()
>>> scen = optimize.DPScenario(cycle="artemis_urban", T_amb=-10.0, duration_s=60.0)
>>> out = optimize.solve_thermal(params, scen)          # Thermal-DP on its default grids
>>> bool(out.sim.soc[-1] >= scen.soc0 - scen.soc_tol)    # charge-sustaining
True
>>> 0.0 < out.fuel_g < 100.0
True

Sub-packages and modules: :mod:`optimize.dp` (the generic DP engine), :mod:`optimize.formulations`
(scenario and grids, parameter-vector layout, the compiled transition, fused kernels, solve),
:mod:`optimize.tuning` (per-scenario tuning of the rule-based controller), :mod:`optimize.casestudy`,
:mod:`optimize.convergence`, :mod:`optimize.sweep` (parameter studies on dask). ``optimize`` uses
``calib``'s model and never imports ``iptm``.
"""
import calib  # noqa: F401  (first: it keys numba's kernel cache by the source version, calib._numba_cache)

from .dp import DPProblem, DPResult, ValueFunctions, backward_pass, cartesian, forward_pass, solve
from .formulations import (FORMULATIONS, DPGrids, DPOutcome, DPScenario, parse_grid_spec, solve_baseline,
                           solve_formulation, solve_thermal, solve_thermal_cabin)
from .tuning import TunedRule, tune_rule_based, tune_rule_on_drives
from .casestudy import CaseStudy, run_case_study
from .convergence import (CABIN_TOL_K, FUEL_TOL_PCT, ROUTINE_HALVING, case_study_halving, convergence_study,
                          format_case_study_convergence, format_convergence, halving_row)
from .labels import LABELS, PAPER_CONDITION
from .sweep import (ParamSpec, Study, format_failures, load_study, local_client, plot_study, run_case, run_study,
                    summary_pivot, write_table)

__all__ = [
    "DPProblem", "DPResult", "ValueFunctions", "cartesian", "solve", "backward_pass", "forward_pass",
    "DPScenario", "DPGrids", "DPOutcome", "parse_grid_spec", "FORMULATIONS",
    "solve_baseline", "solve_thermal", "solve_thermal_cabin", "solve_formulation",
    "TunedRule", "tune_rule_based", "tune_rule_on_drives", "CaseStudy", "run_case_study", "convergence_study", "format_convergence",
    "Study", "load_study", "run_study",
    # for the application layer: strategy labels, convergence checks of a case study, the sweep's parts
    "LABELS", "PAPER_CONDITION", "CABIN_TOL_K", "FUEL_TOL_PCT", "ROUTINE_HALVING", "case_study_halving",
    "format_case_study_convergence", "halving_row",
    "ParamSpec", "run_case", "local_client", "write_table", "plot_study", "summary_pivot", "format_failures",
]
