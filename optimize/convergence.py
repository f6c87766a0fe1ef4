"""Grid convergence: solve a formulation on a grid and with every grid step halved; compare the fuel.

The fuel compared is the re-simulated (true-model) fuel of each solution; for Baseline-DP its own
f_cl = 1 optimum. ``iptm optimize --convergence`` prints it.
"""
from __future__ import annotations

from optimize.formulations.scenario import DPGrids, DPScenario
from optimize.formulations.solve import solve_formulation


def convergence_study(params, scenario: DPScenario | None = None, formulations=("baseline", "thermal"),
                      grids: DPGrids | None = None, progress: bool = False) -> list:
    """One row per formulation: fuel on ``grids`` and on ``grids.halved()``, relative change (%)."""
    scen, g = scenario or DPScenario(), grids or DPGrids()
    rows = []
    for f in formulations:
        r = {"formulation": f, "grid": g.to_dict(), "grid_half": g.halved().to_dict()}
        for tag, gg in (("", g), ("_half", g.halved())):
            o = solve_formulation(f, params, scen, gg)
            r["fuel_g" + tag] = o.sim.fuel_g
            r["soc_final" + tag] = float(o.sim.soc[-1])
            r["time_s" + tag] = o.t_total
            r["n_states" + tag] = o.n_states
            r["n_controls" + tag] = o.n_controls
            if progress:
                print(f"{f} {'halved' if tag else 'default'} grid: {o.sim.fuel_g:.3f} g, SOC_N "
                      f"{o.sim.soc[-1]:.4f} [{o.t_total:.1f} s]", flush=True)
        r["rel_change_pct"] = 100.0 * (r["fuel_g_half"] - r["fuel_g"]) / r["fuel_g"]
        rows.append(r)
    return rows


def format_convergence(rows) -> str:
    """The convergence study as text: fuel per grid and the change when every step is halved."""
    lines = [f"{'formulation':<14s} {'fuel (grid) g':>14s} {'fuel (halved) g':>16s} {'change %':>9s}  < 0.5 %?"]
    for r in rows:
        lines.append(f"{r['formulation']:<14s} {r['fuel_g']:14.3f} {r['fuel_g_half']:16.3f} "
                     f"{r['rel_change_pct']:9.3f}  {'yes' if abs(r['rel_change_pct']) < 0.5 else 'NO'}")
    return "\n".join(lines)
