"""Causal rows of the case study (:func:`optimize.casestudy.run_case_study` with ``ecms`` / ``sdp``)."""
from __future__ import annotations


def causal_sims(params, scen, cycle, kinds, say=print) -> dict:
    """Simulate each causal controller on the scenario's drive; the SDP's statistics come from the training
    cycles of :mod:`optimize.causal.compare` (the drive itself is left out when it is one of them)."""
    from calib.model.simulate import simulate

    from optimize.causal.compare import TRAIN_CYCLES
    from optimize.causal.controllers import make_controller
    from optimize.causal.markov import DemandMarkov

    out = {}
    mk = None
    if "sdp" in kinds:
        train = [c for c in TRAIN_CYCLES if c != scen.cycle]
        mk = DemandMarkov.estimate(params, train)
    for kind in kinds:
        ctrl = make_controller(kind, params, T_amb=scen.T_amb, Q_heat=scen.Q_heat, soc_target=scen.soc0, markov=mk)
        out[kind] = simulate(params, cycle, ctrl, T_amb=scen.T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0,
                             T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)
        s = out[kind].summary()
        say(f"{kind}: {s['fuel_g']:.2f} g, corrected {s['fuel_corrected_g']:.2f} g, SOC_N {s['soc_final']:.4f}",
            flush=True)
    return out
