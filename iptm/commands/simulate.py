"""``iptm simulate``: run the model over a cycle under the rule-based or a causal controller."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("simulate", help="simulate a drive cycle under the rule-based controller",
                       description="Run the vehicle model over a drive cycle under the rule-based controller; "
                                   "print fuel, final states and the energy-balance residual.")
    p.add_argument("--params", metavar="FILE", help="parameter set or calibration artifact (TOML/JSON); "
                                                     "default: the default 2017 Prius")
    p.add_argument("--cycle", default="artemis_urban", help="bundled cycle name, CSV file, or 'a+b' "
                                                            "(default: artemis_urban)")
    p.add_argument("--ambient", type=float, default=-10.0, metavar="DEGC", help="ambient temperature (default -10)")
    p.add_argument("--soc0", type=float, default=0.6, help="initial SOC (default 0.6)")
    p.add_argument("--tcl0", type=float, default=70.0, metavar="DEGC", help="initial coolant temperature (70)")
    p.add_argument("--tcab0", type=float, default=20.0, metavar="DEGC", help="initial cabin temperature (20)")
    p.add_argument("--heater", type=float, default=1500.0, metavar="W", help="heater demand (default 1500 W)")
    p.add_argument("--controller", choices=("rule", "ecms", "sdp", "ecms-route"), default="rule",
                   help="rule (default), ecms (thermal-aware ECMS), sdp (stochastic-DP policy) or ecms-route (the "
                        "ECMS told the route at departure: --route or --route-length-km)")
    p.add_argument("--route", metavar="FILE", help="planned route for --controller ecms-route (TOML/JSON: length_km, "
                                                    "optional [[segment]] from_km, to_km, class or speed_limit_kph, "
                                                    "ambient_degC; docs/route_aware.md)")
    p.add_argument("--route-length-km", type=float, metavar="KM", help="planned trip length for --controller "
                                                                        "ecms-route (instead of --route)")
    p.add_argument("--policy", metavar="FILE.npz", help="stored SDP policy for --controller sdp (default: build "
                                                        "one from the bundled training cycles, about a minute)")
    p.add_argument("--plot", metavar="FILE", help="write a time-series plot (PNG/PDF/SVG)")
    p.add_argument("--csv", metavar="FILE", help="write every time series as CSV")
    p.add_argument("--json", metavar="FILE", help="write the summary figures as JSON")
    p.set_defaults(func=run)


def load_params(path):
    from calib.model import ParameterSet, default_parameters

    return ParameterSet.load(path) if path else default_parameters()


def run(args) -> int:
    from calib import atomic_path, write_json
    from calib.model import simulate

    ps = load_params(args.params)
    ctrl = None
    from optimize.causal import make_route_controller, route_from_args

    route = route_from_args(args.route, args.route_length_km)
    if (route is None) == (args.controller == "ecms-route"):
        from calib import IptmError

        raise IptmError("--controller ecms-route needs --route FILE or --route-length-km KM" if route is None
                        else "--route / --route-length-km are for --controller ecms-route")
    if route is not None:
        ctrl = make_route_controller(ps, route, knowledge="route", T_amb=args.ambient, Q_heat=args.heater,
                                     soc_target=args.soc0)
    elif args.controller != "rule" or args.policy:
        from optimize.causal import TRAIN_CYCLES, DemandMarkov, SDPPolicy, make_controller

        if args.policy and args.controller != "sdp":
            from calib import IptmError

            raise IptmError("--policy is for --controller sdp")
        pol = SDPPolicy.load(args.policy) if args.policy else None
        mk = DemandMarkov.estimate(ps, TRAIN_CYCLES) if args.controller == "sdp" and pol is None else None
        if mk is not None:
            print(f"building the SDP policy from {', '.join(TRAIN_CYCLES)} at {args.ambient:g} degC ...", flush=True)
        ctrl = make_controller(args.controller, ps, T_amb=args.ambient, Q_heat=args.heater, soc_target=args.soc0,
                               policy=pol, markov=mk)
    res = simulate(ps, args.cycle, ctrl, T_amb=args.ambient, soc0=args.soc0, T_cl0=args.tcl0, T_cab0=args.tcab0,
                   Q_heat=args.heater)
    s = res.summary()
    print(f"controller {s['controller'][:90]}")
    print(f"cycle {s['cycle']}: {s['distance_km']:.2f} km in {s['duration_s']:.0f} s at {args.ambient:g} degC")
    print(f"fuel            {s['fuel_g']:.1f} g ({s['L_per_100km']:.2f} L/100 km, {s['mpg']:.1f} mpg)")
    print(f"fuel corrected  {s['fuel_corrected_g']:.1f} g (for final SOC, coolant and cabin energy)")
    print(f"final SOC       {s['soc_final']:.3f} (start {s['soc_initial']:.3f})")
    print(f"final coolant   {s['T_cl_final_degC']:.1f} degC, cabin {s['T_cab_final_degC']:.1f} degC "
          f"(mean {s['T_cab_mean_degC']:.1f})")
    print(f"engine starts   {s['engine_starts']}, on {s['engine_on_s']:.0f} s, idle {s['idle_s']:.0f} s")
    if s["heater_shortfall_J"] >= 500.0:  # shown only when it rounds to at least 1 kJ
        print(f"heater shortfall {s['heater_shortfall_J'] / 1e3:.0f} kJ (coolant too cold to deliver the demand)")
    print(f"energy balance residual {s['energy_balance_residual_rel']:.1e} (relative)")
    if args.plot:
        res.plot(args.plot)
        print(f"plot: {args.plot}")
    if args.csv:
        with atomic_path(args.csv) as tmp:
            res.to_pandas().to_csv(tmp)
        print(f"time series: {args.csv}")
    if args.json:
        write_json(args.json, {**s, "energy_balance": res.energy_balance()})
    return 0
