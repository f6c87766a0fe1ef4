"""Thermal-DP with the `continued` terminal held to a SOC band: reach-boundary interpolation against the
plain chord, each run valued by the direct continuation of its final state.

    .venv/bin/python studies/band_interp/band_interp.py nycc 0 [wltc_city_3b -10 ...] [--soc-step 0.01]
"""
import argparse

from calib.model import continuation_corrected, default_parameters
from optimize.dp import forward_pass
from optimize.formulations import DPGrids, DPScenario, backward_pass_fused, build_problem, resimulate


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="cycle ambient [cycle ambient ...]")
    ap.add_argument("--soc-step", type=float, default=0.01)
    ap.add_argument("--band", type=float, default=0.01)
    a = ap.parse_args()
    if len(a.pairs) % 2:
        ap.error("give cycle and ambient pairs")
    ps = default_parameters()
    for cyc, T in zip(a.pairs[::2], a.pairs[1::2]):
        scen = DPScenario(cycle=cyc, T_amb=float(T), terminal="continued", cont_soc_band=a.band)
        for interp in ("reach_first", "multilinear"):
            b = build_problem(ps, scen, DPGrids(soc=a.soc_step), 2, interp=interp)
            res = forward_pass(b.prob, backward_pass_fused(b.prob), b.x0)  # the fused kernels, as the solvers use them
            sim = resimulate(ps, b.cyc, res.u[:, 0], res.u[:, 1], res.u[:, 2], scen, interp)
            c = continuation_corrected(sim, Q_heat=scen.Q_heat, T_amb=scen.T_amb, cycle=scen.cont_cycle)
            print(f"{cyc} {float(T):g} degC, soc step {a.soc_step:g}, {interp:12s}: continuation-corrected "
                  f"{c['fuel_continuation_g']:.3f} g, fuel {sim.fuel_g:.3f} g, SOC_N {sim.soc[-1]:.4f}", flush=True)


if __name__ == "__main__":
    main()
