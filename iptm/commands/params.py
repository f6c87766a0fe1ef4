"""``iptm params``: write a parameter set: the defaults, a base file, optionally with a measured fuel map."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("params", help="write a parameter set (defaults, or with a measured fuel map)",
                       description="Write the default 2017 Prius parameter set (or --params BASE) as TOML/JSON, "
                                   "optionally replacing the engine's optimal operating line by one derived "
                                   "from a measured speed x torque fuel map (CSV with units in the header).")
    p.add_argument("--params", metavar="FILE", help="base parameter set (default: the 2017 Prius)")
    p.add_argument("--fuel-map", metavar="CSV", help="measured fuel map: speed [rpm], torque [N*m], fuel [g/s]")
    p.add_argument("--out", required=True, metavar="FILE", help="output .toml or .json")
    p.add_argument("--json", metavar="FILE", help="write the operating-line table as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from calib import write_json
    from calib.model import ParameterSet, default_parameters

    ps = ParameterSet.load(args.params) if args.params else default_parameters()
    if args.fuel_map:
        from calib.model import apply_fuel_map

        ps = apply_fuel_map(ps, args.fuel_map)
    ps.save(args.out)
    eta, n = ps.param("eta_ool"), ps.param("n_ool_rpm")
    print(f"optimal operating line ({eta.source}):")
    print(f"  {'P_e kW':>8s} {'speed rpm':>10s} {'efficiency':>10s}")
    for P, s, e in zip(eta.x, n.value, eta.value):
        print(f"  {P / 1e3:8.1f} {s:10.0f} {e:10.3f}")
    print(f"parameter set: {args.out}")
    if args.json:
        write_json(args.json, {"P_e_W": eta.x, "n_rpm": n.value, "eta": eta.value, "out": args.out})
    return 0
