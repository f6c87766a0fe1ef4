"""Causal energy management learned from driving statistics, measured against the DP optimum.

- :mod:`optimize.causal.markov`: Markov chain of the wheel-power demand per ambient band, from drive
  cycles and ingested logs, with held-out validation.
- :mod:`optimize.causal.sdp`: stationary policy over (SOC, coolant, demand) by stochastic DP.
- :mod:`optimize.causal.ecms`: thermal-aware ECMS with adaptive co-states.
- :mod:`optimize.causal.controllers`: both as controllers with the rule-based controller's signature.
- :mod:`optimize.causal.compare`: corrected fuel on held-out drives against the DP and tuned rule-based.
- :mod:`optimize.causal.hindsight`: the ECMS with its settings tuned on the very drive (structure against
  knowledge of the drive).
- :mod:`optimize.causal.route`: the ECMS told the route at departure (length, road classes), co-states
  scheduled by distance to go.
"""
from optimize.causal.controllers import CONTROLLERS, ECMSController, SDPController, make_controller
from optimize.causal.ecms import ECMSParams
from optimize.causal.hindsight import tune_ecms_on_drive
from optimize.causal.markov import DemandMarkov
from optimize.causal.route import (ENDS_EARLY_AT, KNOWLEDGE, LENGTH_ERRORS, Route, RouteECMSController, RouteECMSParams,
                                   class_costates, drive_route, ended_early, load_route, make_route_controller,
                                   route_from_args, route_of_cycle)
from optimize.causal.sdp import SDPConfig, SDPPolicy, build_policy
from optimize.causal.compare import (AMBIENTS, DRIVE_SETS, GOAL_GAP_PCT, SELECTED, SOC_TOL, TRAIN_CYCLES, VALUATIONS,
                                     compare_causal, drives_of, step_timing, valuation_scenario, valued_fuel)
from optimize.causal.hindsight import drive_ecms, summarize
from optimize.causal.onestep import fit_stop_regen

__all__ = ["DemandMarkov", "SDPConfig", "SDPPolicy", "build_policy", "ECMSParams", "ECMSController",
           "SDPController", "make_controller", "CONTROLLERS", "tune_ecms_on_drive", "Route", "RouteECMSController",
           "RouteECMSParams", "load_route", "make_route_controller", "route_from_args", "ENDS_EARLY_AT", "KNOWLEDGE",
           "LENGTH_ERRORS", "class_costates", "drive_route", "ended_early", "route_of_cycle", "GOAL_GAP_PCT", "SOC_TOL",
           "VALUATIONS",
           "compare_causal", "DRIVE_SETS", "drives_of", "TRAIN_CYCLES", "AMBIENTS", "SELECTED", "step_timing",
           "valuation_scenario", "valued_fuel", "drive_ecms", "summarize", "fit_stop_regen"]
