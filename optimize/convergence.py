"""Grid convergence: solve a formulation on a grid and with every grid step halved; compare the fuel.

The fuel compared is the re-simulated (true-model) fuel of each solution, raw and corrected (equal final
stored energy), and the mean cabin temperature; for Baseline-DP its own f_cl = 1 optimum. A grid counts
as converged when halving every step changes the corrected fuel by less than 0.1 % and the mean cabin
temperature by less than 0.1 degC. ``iptm optimize --convergence`` prints it.

:func:`trajectory_checks` looks for the two grid artefacts a converged answer must not show: the heater
switching between neighbouring grid values step after step (chatter), and the cabin state sitting on a
grid node for long stretches (pinned: the interpolated cost-to-go has a kink at every node, and an
off-grid forward pass that is drawn to the kink is a property of the grid, not of the car).
"""

from __future__ import annotations

from optimize.formulations.artefacts import ON_NODE_K, trajectory_checks  # noqa: F401 (re-exported)
from optimize.formulations.scenario import DPGrids, DPScenario, FormulationGrids
from optimize.formulations.solve import solve_formulation

#: Convergence criteria: relative change of corrected fuel (%) and of the mean cabin temperature (degC).
FUEL_TOL_PCT = 0.1
CABIN_TOL_K = 0.1
#: Formulations whose every-step-halved solve is cheap enough to run beside every case study (Baseline-DP
#: 4 times, Thermal-DP 8 times the work); Thermal-Cabin-DP's is 32 times, run on request.
ROUTINE_HALVING = ("baseline", "thermal")
def halving_row(formulation: str, grids: DPGrids, sim, sim_half, o=None, o_half=None) -> dict:
    """One convergence row from a formulation's re-simulated runs on ``grids`` and on ``grids.halved()``
    (``o``, ``o_half``: their DP outcomes, for time and size)."""
    r = {"formulation": formulation, "grid": grids.to_dict(), "grid_half": grids.halved().to_dict()}
    for tag, sm, oo in (("", sim, o), ("_half", sim_half, o_half)):
        summ = sm.summary()
        r["fuel_g" + tag] = sm.fuel_g
        r["fuel_corrected_g" + tag] = summ["fuel_corrected_g"]
        r["T_cab_mean_degC" + tag] = summ["T_cab_mean_degC"]
        r["soc_final" + tag] = float(sm.soc[-1])
        r["time_s" + tag] = getattr(oo, "t_total", None)
        r["n_states" + tag] = getattr(oo, "n_states", None)
        r["n_controls" + tag] = getattr(oo, "n_controls", None)
    r["rel_change_pct"] = 100.0 * (r["fuel_g_half"] - r["fuel_g"]) / r["fuel_g"]
    r["rel_change_corrected_pct"] = 100.0 * (r["fuel_corrected_g_half"] - r["fuel_corrected_g"]) / abs(
        r["fuel_corrected_g"])
    r["T_cab_mean_change_K"] = r["T_cab_mean_degC_half"] - r["T_cab_mean_degC"]
    r["converged"] = bool(abs(r["rel_change_corrected_pct"]) < FUEL_TOL_PCT
                          and abs(r["T_cab_mean_change_K"]) < CABIN_TOL_K)
    return r


def case_study_halving(cs, cs_half) -> list:
    """Convergence rows of a case study (:class:`optimize.casestudy.CaseStudy`) against the same case study
    solved with every grid step halved, for each DP formulation both hold. Baseline-DP has two rows:
    ``baseline``, its controls re-simulated on the thermal model (the run the case study compares, whose
    corrected fuel values coolant heat that Baseline-DP does not optimise), and ``baseline_warm``, its own
    optimum on its own model (f_cl = 1)."""
    rows = []
    for f in ("baseline_warm", "baseline", "thermal", "thermal_cabin"):
        dp = "baseline" if f == "baseline_warm" else f
        if f in cs.sims and f in cs_half.sims and dp in cs.outcomes:
            rows.append(halving_row(f, cs.grids.of(dp), cs.sims[f], cs_half.sims[f], cs.outcomes.get(dp),
                                    cs_half.outcomes.get(dp)))
    return rows


def convergence_study(params, scenario: DPScenario | None = None, formulations=("baseline", "thermal"),
                      grids=None, progress: bool = False, step_progress=None) -> list:
    """One row per formulation: fuel on its grid (``grids``: as :func:`optimize.casestudy.run_case_study`)
    and with every step halved, relative change (%). ``step_progress(done_steps, total_steps)``: handed to
    every solve, called as its backward pass goes (:func:`optimize.dp.engine.solve`)."""
    scen, grids = scenario or DPScenario(), FormulationGrids.coerce(grids)
    rows = []
    for f in formulations:
        g = grids.of(f)
        runs = []
        for tag, gg in (("", g), ("_half", g.halved())):
            o = solve_formulation(f, params, scen, gg, progress=step_progress)
            runs.append(o)
            if progress:
                print(f"{f} {'halved' if tag else 'default'} grid: {o.sim.fuel_g:.3f} g, SOC_N "
                      f"{o.sim.soc[-1]:.4f} [{o.t_total:.1f} s]", flush=True)
        rows.append(halving_row(f, g, runs[0].sim, runs[1].sim, runs[0], runs[1]))
    return rows


def format_convergence(rows) -> str:
    """The convergence study as text: fuel per grid and the change when every step is halved."""
    lines = [f"{'formulation':<14s} {'fuel (grid) g':>14s} {'fuel (halved) g':>16s} {'change %':>9s} "
             f"{'corrected %':>12s} {'cabin mean K':>13s}  converged (< {FUEL_TOL_PCT:g} %, < {CABIN_TOL_K:g} K)?"]
    for r in rows:
        lines.append(f"{r['formulation']:<14s} {r['fuel_g']:14.3f} {r['fuel_g_half']:16.3f} "
                     f"{r['rel_change_pct']:9.3f} {r['rel_change_corrected_pct']:12.3f} "
                     f"{r['T_cab_mean_change_K']:13.3f}  {'yes' if r['converged'] else 'NO'}")
    return "\n".join(lines)


def format_case_study_convergence(cs) -> str:
    """A case study's convergence rows (:attr:`optimize.casestudy.CaseStudy.convergence`) as text, and one
    line per DP formulation of the case study whose halved grid was not solved, saying how to run it."""
    rows = cs.convergence or []
    checked = {"baseline" if r["formulation"] == "baseline_warm" else r["formulation"] for r in rows}
    lines = [format_convergence(rows)] if rows else []
    for f in (k for k in cs.outcomes if k not in checked):
        lines.append(f"{f}: not checked with this run (every step halved is 32 times the work); "
                     f"`iptm optimize --params CALIBRATION --formulation {f} --convergence` solves it (CALIBRATION: "
                     f"this run's calibration.toml)")
    return "\n".join(lines)
