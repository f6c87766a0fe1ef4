"""The ECMS with its settings tuned on the very drive: what its structure can reach when it knows the drive.

A causal controller's gap to the DP has two parts: what its structure (one-step Hamiltonian with a price on
charge and on coolant heat) cannot express, and what it does not know (the drive ahead, when it ends).
Tuning the controller's settings on the drive itself, as the tuned rule-based baseline is tuned, removes
the second part as far as the settings can carry it, and so splits the gap:

    gap(causal ECMS) = gap(ECMS tuned on the drive) + [causal ECMS - ECMS tuned on the drive]

Two searches, each over a grid, keeping only runs that end within ``soc_band`` of the starting SOC (the
band the causal controllers are held to) and taking the least fuel under the comparison's valuation:

- ``adaptive``: the committed :class:`~optimize.causal.ecms.ECMSParams` (its SOC and coolant feedback
  included) with the base levels ``s0`` and ``mu0`` searched;
- ``constant``: constant co-states ``s`` and ``mu`` (``k_s = k_mu = 0``), Pontryagin's minimum principle
  with the co-states held fixed, the textbook benchmark of the equivalence-factor method. Without feedback
  the final SOC moves fast with ``s``, so for each ``mu`` the interval of the coarse grid in which the final
  SOC crosses the band is searched again on a grid ten times finer.

A grid search finds an upper bound of each structure's best on the drive, not its exact optimum.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from optimize.causal.controllers import ECMSController
from optimize.causal.ecms import ECMSParams

#: Base levels of the equivalence factor and of the coolant co-state searched (``adaptive``).
ADAPTIVE_S0 = tuple(np.round(np.arange(0.2, 1.201, 0.1), 3))
ADAPTIVE_MU0 = (0.0, 0.25, 0.5, 1.0)
#: Constant co-states searched (``constant``): the equivalence factor needs a finer grid without feedback.
CONSTANT_S = tuple(np.round(np.arange(0.3, 1.501, 0.05), 3))
CONSTANT_MU = (0.0, 0.25, 0.5, 1.0)
SEARCHES = ("adaptive", "constant")


@dataclass
class HindsightECMS:
    """Every setting tried on one drive (``tried``: s, mu, dsoc, fuel under the valuation or nan when
    outside the band) and the best within the band (``best``; None if no setting ends in it)."""

    search: str
    tried: list = field(default_factory=list)
    best: dict | None = None


def summarize(runs: list, goal_pct: float = 3.0) -> dict:
    """Counts over runs of ``studies/ecms_hindsight/ecms_hindsight.py`` (each with ``dp_g``, ``rule_g``, ``ecms_g`` and the
    ``adaptive`` and ``constant`` searches' ``best``): per strategy (``causal``, the committed ECMS; the two
    searches; ``rule``, the rule tuned on the drive) the runs within ``goal_pct`` of Thermal-DP, better
    than the rule tuned on the drive, with no setting in the band, and the largest gap (%)."""
    def fuel(r, k):  # None: no setting of the search ended in the band
        if k in ("causal", "rule"):
            return r["ecms_g" if k == "causal" else "rule_g"]
        return (r[k]["best"] or {}).get("fuel_valued_g")

    out = {"runs": len(runs)}
    for k in ("causal", "adaptive", "constant", "rule"):
        gaps = [None if (f := fuel(r, k)) is None else 100.0 * (f / r["dp_g"] - 1.0) for r in runs]
        out[f"{k}_within"] = sum(g is not None and g <= goal_pct for g in gaps)
        out[f"{k}_max_gap_pct"] = max((g for g in gaps if g is not None), default=float("nan"))
        if k != "rule":
            out[f"{k}_better_than_rule"] = sum((f := fuel(r, k)) is not None and f < r["rule_g"] for r in runs)
        if k in SEARCHES:
            out[f"{k}_no_setting_in_band"] = sum(g is None for g in gaps)
    return out


def drive_ecms(params, mp, cyc, scen, ep):
    """The ECMS with settings ``ep`` over the drive cycle ``cyc`` from ``scen``'s initial state and ambient."""
    from calib.model.simulate import simulate

    return simulate(params, cyc, ECMSController(mp, ep, scen.T_amb), T_amb=scen.T_amb, soc0=scen.soc0,
                    T_cl0=scen.T_cl0, T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)


def tune_ecms_on_drive(params, scenario, *, search: str = "adaptive", valuation: str = "corrected",
                       soc_band: float = 0.01, s_grid=None, mu_grid=None,
                       ecms: ECMSParams | None = None) -> HindsightECMS:
    """Search the ECMS settings on ``scenario``'s drive (:data:`SEARCHES`); see the module docstring.

    ``valuation`` as in :func:`optimize.causal.compare.compare_causal` (for ``continuation`` the scenario
    must carry the ``continued`` terminal and its band, as the comparison's does)."""
    from optimize.causal.compare import valued_fuel

    if search not in SEARCHES:
        from calib.errors import IptmError

        raise IptmError(f"hindsight ECMS: search {search!r}; choose one of {', '.join(SEARCHES)}")
    mp = params.model_params() if hasattr(params, "model_params") else params
    base = replace(ecms or ECMSParams(), Q_heat_W=scenario.Q_heat, soc_target=scenario.soc0)
    if search == "constant":
        base = replace(base, k_s=0.0, k_mu=0.0)
        s_grid, mu_grid = s_grid or CONSTANT_S, mu_grid or CONSTANT_MU
    else:
        s_grid, mu_grid = s_grid or ADAPTIVE_S0, mu_grid or ADAPTIVE_MU0
    cyc = scenario.load_cycle()
    out = HindsightECMS(search)

    def run(s, mu):
        sim = drive_ecms(params, mp, cyc, scenario, replace(base, s0=float(s), mu0=float(mu)))
        summ = sim.summary()
        dsoc = summ["soc_final"] - summ["soc_initial"]
        fuel = valued_fuel(sim, scenario, valuation)[0] if abs(dsoc) <= soc_band else np.nan
        row = {"s": float(s), "mu": float(mu), "dsoc": float(dsoc), "fuel_g": float(summ["fuel_g"]),
               "fuel_valued_g": float(fuel), "T_cl_final": float(summ["T_cl_final_degC"])}
        out.tried.append(row)
        if np.isfinite(fuel) and (out.best is None or fuel < out.best["fuel_valued_g"]):
            out.best = row
        return row

    for mu in mu_grid:
        rows = [run(s, mu) for s in s_grid]
        if search != "constant":
            continue
        # a higher price on charge ends higher: refine between the last setting below the band and the
        # first above it
        below = [r["s"] for r in rows if r["dsoc"] < -soc_band]
        above = [r["s"] for r in rows if r["dsoc"] > soc_band]
        lo = max(below) if below else min(s_grid)
        hi = min([s for s in above if s > lo], default=max(s_grid))
        for s in np.linspace(lo, hi, 11)[1:-1]:
            run(round(float(s), 6), mu)
    return out
