"""The three DP formulations of the paper (docs/optimization.md s.1-2) on the generic engine.

``solve_baseline``, ``solve_thermal`` and ``solve_thermal_cabin`` take any parameter set (the default
2017 Prius, or a calibration artifact loaded with :meth:`calib.model.params.ParameterSet.load`), a
:class:`DPScenario` (TOML-friendly: plain fields) and a :class:`DPGrids` (default: the paper's Table II).
Each returns a :class:`DPOutcome` whose ``sim`` is a :class:`calib.model.simulate.SimResult` obtained by
re-simulating the forward pass's controls through :func:`calib.model.equations.step` from the true initial state, so
fuel, final states, starts, idle time, energy balance and corrected fuel come from ``.summary()`` exactly
as for the rule-based controller.

Formulations
    * **Baseline-DP**: state SOC; controls e_mode in {off, idle, on} and, when on, ``P_bat`` on the grid
      ``P_bat_min : dP : P_bat_max`` (the battery-terminal power, ``P_bat_mg = P_bat - P_aux``); off and
      idle have one control each (``P_bat_mg`` set by the demand). Stage cost: the warm fuel rate
      (model parameters with ``f_cl = 1``). Its own optimum is simulated with ``f_cl = 1``
      (``outcome.sim``); its control sequence (e_mode, P_bat_mg) re-simulated on the full thermal model
      with the scenario's heater demand is ``outcome.on_thermal`` ("Baseline-DP on the thermal model").
    * **Thermal-DP**: states SOC, T_cl; same controls; ``Q_heat`` is the scenario's demand (1500 W)
      delivered up to the heater-core limit :func:`calib.model.equations.heater_limit`. The heater limit needs the
      cabin temperature, which is not a state here: the 1500-W reference cabin trajectory (below) is used
      as an exogenous input (the limit only binds below about 25 degC coolant at -10 degC ambient; the
      re-simulation uses the true cabin state).
    * **Thermal-Cabin-DP**: states SOC, T_cl, T_cab; controls as above times ``Q_heat_cmd`` on
      ``Q_min : dQ : Q_max``; delivered heat ``min(Q_cmd, heater_limit(T_cl, T_cab, ...))``. Cabin
      constraint ``T_cab_k >= T_cab^LB(k)`` (default: the 1500-W reference trajectory minus
      ``cab_lb_offset`` = 1 degC) and ``T_cab <= T_cab_ub`` (default 22 degC); terminal
      ``T_cab_N >=`` the reference's final value. The T_cab grid is ``floor(min LB) : dT : T_cab_ub``.

Reference cabin trajectory: the cabin under a constant 1500-W demand (``DPScenario.Q_heat``), heater
limited by the coolant of the same drive under the (untuned) rule-based controller: one 12-ms simulation.

Common choices
    * Integrator: the model's explicit Euler step (Ts of the cycle, 1 s by default).
    * Terminal set ``SOC_N >= SOC_0`` by the engine's level-set boundary method (Elbert 2013) with signed
      levels, exact for this one-sided set under multilinear interpolation (``level_tol`` =
      :data:`LEVEL_TOL` = 0).
    * Terminal condition on coolant and cabin (``DPScenario.terminal``, named in every report):
      ``valued`` (default) adds the terminal cost ``-(fuel equivalent of the heat gained by coolant and
      cabin)``, the one valuation of the corrected fuel (:func:`calib.model.simulate.fuel_equivalents_g`);
      with the charge held by ``SOC_N >= SOC_0`` each DP then minimises the corrected fuel of its own
      trajectory up to the small credit for charge above SOC_0, which is not offered to the DP (the
      engine's marginal efficiency beats the rate it assumes, so the DP would charge to the ceiling);
      ``match`` adds the level-set terminal bounds ``T_cl_N >=`` (and ``T_cab_N >=``) the rule-based
      run's final values; ``free`` is the paper's (coolant free; Thermal-Cabin-DP's
      ``T_cab_N >= T_cab,1500W(N)`` as a soft cost of ``DPScenario.cab_terminal_g_per_K`` per kelvin).
    * Speed: :func:`build_tables` computes once, for every step and power control, feasibility, engine
      power, warm fuel rate, battery power and the next SOC at every SOC node (the battery square root
      leaves the inner loop); the engine's ``precompute`` hook copies step k's slice into ``tab``.
      ``f_cl``, engine-bay loss and radiator heat are tabulated per T_cl node. In the backward pass the
      transition uses the grid indices ``ix``; in the forward pass (``ix = -1``) it evaluates the same
      equations at the true state. The transition and the fused kernels call the model's own compiled
      equations (battery current, heater-core limit, radiator, engine-bay loss, coolant and cabin heat
      rates of :mod:`calib.model.equations`, in their scalar forms; numba inlines them).
    * Parameters reach the compiled code as one flat float64 vector (:func:`pack_params`): the engine's
      parallel kernel cannot take the ``ModelParams`` namedtuple (numba's parfor lowering rejects a struct
      holding arrays: "scalar type ModelParams given for non scalar argument").
    * One compiled transition (:func:`hev_transition`) serves all three formulations (the state count is
      read from the parameters), so the engine's kernels compile once.
    * The SOC state is the charge minus the step's engine-off drift (``soc="drift"``, default;
      :func:`~optimize.formulations.transition.drift_offsets`, offsets in ``extra["soc_grid_offset"]``)
      and the cost-to-go is interpolated from the reach boundary of ``SOC_N >= SOC_0``
      (``interp="reach_first"``): together they make the paper's 0.01 SOC grid converged (README, "SOC
      grid convergence"); ``soc="absolute"`` and ``interp="multilinear"`` give the fixed grid and chord.
    * Thermal-DP and Thermal-Cabin-DP use fused backward kernels (:mod:`optimize.formulations.fused`) by default and
      the engine's forward pass; they give the same value functions and trajectory as the generic engine
      (``engine="generic"``), cross-checked in ``tests/test_formulations.py``. With a terminal set on SOC
      alone both run separable kernels (levels per SOC node, the cost-to-go interpolated along coolant and
      cabin once per control): the same levels, decisions and cost, a value function nowhere above the
      engine's (``engine="fused-exact"``: the bit-identical kernels; docs/optimization.md s.5).
    * State constraints (SOC, T_cl and T_cab boxes, the cabin lower-bound trajectory) are a documented
      penalty, :data:`PENALTY_G_PER_STEP` g of fuel per grid step of violation, with the engine's
      ``clip=True`` lookup, not +inf: with +inf, a grid node that cannot avoid leaving the box (e.g. SOC
      0.8 while braking: the motor must regenerate) poisons its neighbours through interpolation, one cell
      per event, until after ~40 braking events no SOC node is finite (the level-set method of the engine
      covers terminal sets only). Re-simulated results are checked to stay inside the boxes.
"""
from optimize.formulations.scenario import (BASELINE_CONVERGED_GRIDS, CABIN_CONVERGED_GRIDS, DEFAULT_GRIDS, FORMULATIONS,
                                            GRID_AXES, TERMINALS, DPGrids, DPScenario, FormulationGrids, check_grid_axes,
                                            parse_grid_spec, parse_grid_steps)
from optimize.formulations.solve import (DPOutcome, dp_objective, estimate_problem, peak_rss_mb, resimulate, solve_baseline, solve_formulation,
                    solve_thermal, solve_thermal_cabin)
from optimize.formulations.solve import (CABIN_INTERP, CABIN_STATE, CABIN_STATES, INTERP, SOC_STATE, SOC_STATES,
                                         build_problem)
from optimize.formulations.fused import backward_pass_fused

__all__ = ["DPScenario", "DPGrids", "FormulationGrids", "DEFAULT_GRIDS", "BASELINE_CONVERGED_GRIDS", "CABIN_CONVERGED_GRIDS",
           "DPOutcome", "parse_grid_spec", "solve_baseline", "solve_thermal",
           "solve_thermal_cabin", "solve_formulation", "FORMULATIONS", "TERMINALS", "resimulate", "peak_rss_mb",
           "dp_objective", "estimate_problem",
           # grid axes and checks, the states' coordinates and interpolation, and the problem and its fused
           # backward pass, for studies that look inside a solution
           "GRID_AXES", "check_grid_axes", "parse_grid_steps", "INTERP", "CABIN_INTERP", "CABIN_STATE", "CABIN_STATES",
           "SOC_STATE", "SOC_STATES", "build_problem", "backward_pass_fused"]
