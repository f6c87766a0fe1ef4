"""``iptm optimize``: the DP formulations and the case study (docs/optimization.md)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("optimize", help="DP-optimal power split, engine thermal management and cabin heating",
                       description="Tune the rule-based controller and solve Baseline-DP, Thermal-DP and "
                                   "Thermal-Cabin-DP on a scenario (each formulation on its converged default grid); print the "
                                   "comparison "
                                   "table with the savings next to the paper's (Gong et al., CCTA 2019).")
    p.add_argument("--params", metavar="FILE", help="parameter set or calibration artifact (TOML/JSON)")
    p.add_argument("--scenario", metavar="FILE", help="DP scenario file (TOML/JSON, fields of DPScenario); "
                                                      "command-line options override it")
    p.add_argument("--cycle", default=None, help="bundled cycle name or CSV file (default artemis_urban)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="use the first S seconds of the cycle")
    p.add_argument("--ambient", type=float, default=None, metavar="DEGC", help="ambient temperature (-10)")
    p.add_argument("--soc0", type=float, default=None, help="initial SOC (0.6)")
    p.add_argument("--tcl0", type=float, default=None, metavar="DEGC", help="initial coolant temperature (70)")
    p.add_argument("--tcab0", type=float, default=None, metavar="DEGC", help="initial cabin temperature (20)")
    p.add_argument("--heater", type=float, default=None, metavar="W", help="heater demand of rule-based, "
                                                                            "Baseline and Thermal-DP (1500)")
    p.add_argument("--terminal", choices=("free", "match", "valued", "continued"), default=None,
                   help="terminal condition on coolant and cabin: valued (default; heat left in them valued as "
                        "in the corrected fuel), match (at least the rule-based run's final values), continued "
                        "(final state valued by the rule-based controller's fuel over UDDS six times; charge too) or "
                        "free (the paper's)")
    p.add_argument("--formulation", default="all",
                   help="rule, baseline, thermal, thermal_cabin, a comma list, or all (default)")
    p.add_argument("--grid", default=None, metavar="SPEC",
                   help="grid steps, e.g. soc=0.01,tcl=1,tcab=1,pbat=500,qheat=50 (the paper's Table II); the steps "
                        "given replace every formulation's own; default: each formulation's converged grid "
                        "(Baseline soc 0.005, pbat 250; Thermal the paper's; Thermal-Cabin tcl 2, tcab 1.5, "
                        "pbat 750, qheat 100)")
    p.add_argument("--convergence", action="store_true",
                   help="solve each chosen DP formulation on the grid and with every step halved; print the fuel "
                        "change (all = baseline and thermal)")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="content-keyed result cache shared with `iptm run` and the dashboard (default "
                        "$IPTM_CACHE_DIR, else .iptm-cache): a strategy already solved for the same parameters, "
                        "scenario and grids is reused")
    p.add_argument("--no-cache", action="store_true", help="solve everything again")
    p.add_argument("--plots", metavar="DIR", help="write the paper's figures (PNG) into DIR")
    p.add_argument("--json", metavar="FILE", help="write the table and DP figures as JSON")
    p.add_argument("--no-hold", action="store_true",
                   help="Thermal-Cabin-DP without the 'hold the bound' heater control (heater grid only; the "
                        "heater then alternates between grid values while the cabin rides its bound)")
    p.set_defaults(func=run)


def _scenario(args):
    """The scenario (file, then command-line options), and the file's ``[grids]`` and ``[run]`` when it has
    them (None otherwise): a scenario file of ``iptm run`` means the same here."""
    from pathlib import Path

    from calib import ScenarioError
    from optimize.formulations import DPScenario

    d, grids, strategies = {}, None, None
    if args.scenario:
        path = Path(args.scenario)
        if not path.is_file():
            raise ScenarioError(f"scenario file {path} not found")
        from calib import read_config

        d = read_config(path, ScenarioError, "scenario file")
        if "scenario" in d:
            from iptm.pipeline import load_scenario

            if path.suffix == ".json":
                raise ScenarioError(f"{path}: sections [scenario], [grids], [run] are read from TOML files")
            scen0, g, strat, cycle_log = load_scenario(path)
            if cycle_log is not None:
                raise ScenarioError(f"{path}: [scenario] cycle = \"from log\" takes the trace of a run's log: use "
                                    "`iptm run --scenario`, or give `iptm optimize` a cycle name or CSV")
            grids = g if "grids" in d else None
            strategies = strat if "run" in d else None
            d = scen0.to_dict()
    if args.scenario:
        try:  # the file alone first: its own mistakes name the file
            DPScenario.from_dict(d)
        except ScenarioError as exc:
            raise ScenarioError(f"{args.scenario}: {exc}") from None
    d.update(_given(args))
    return DPScenario.from_dict(d), grids, strategies


def _given(args) -> dict:
    """The scenario fields the command-line options set."""
    return {name: getattr(args, opt) for opt, name in _OPTIONS if getattr(args, opt) is not None}


#: Command-line options of the scenario and the fields they set.
_OPTIONS = (("cycle", "cycle"), ("duration", "duration_s"), ("ambient", "T_amb"), ("soc0", "soc0"),
            ("tcl0", "T_cl0"), ("tcab0", "T_cab0"), ("heater", "Q_heat"), ("terminal", "terminal"))
#: Initial states the DP formulations hold on their grids: field, grid limits, option, formulations.
_INITIAL = (("soc0", "soc_min", "soc_max", "--soc0", ("baseline", "thermal", "thermal_cabin")),
            ("T_cl0", "T_cl_min", "T_cl_max", "--tcl0", ("thermal", "thermal_cabin")))


def check_initial_state(scen, formulations, given=None, source=None) -> None:
    """Each initial state a chosen DP formulation starts on lies on its grid, checked before anything is solved:
    a ScenarioError naming the field, where it was given (an option, ``source`` or the default) and the fix.
    ``given``: field -> the option that set it."""
    from calib import ScenarioError

    given = given or {}
    for name, lo, hi, opt, forms in _INITIAL:
        used = [f for f in formulations if f in forms]
        v, a, b = getattr(scen, name), getattr(scen, lo), getattr(scen, hi)
        if not used or a <= v <= b:
            continue
        where = given.get(name) or (f"{source}: {name}" if source else f"{name} (the default)")
        fix = f"give {given[name]}" if name in given else (f"set {name} in {source}" if source else f"give {opt}")
        raise ScenarioError(f"{where} = {v:g} lies outside the grid of {', '.join(used)} [{lo} {a:g}, {hi} {b:g}]: "
                            f"{fix} between {a:g} and {b:g}, or widen {lo}/{hi} in a scenario file")


def run(args) -> int:
    from calib import ScenarioError, write_json
    from iptm.commands.simulate import load_params
    from optimize.formulations import DEFAULT_GRIDS, FORMULATIONS, parse_grid_spec

    ps = load_params(args.params)
    scen, file_grids, file_strategies = _scenario(args)
    grids = parse_grid_spec(args.grid, file_grids or DEFAULT_GRIDS)
    allf = ("rule", "baseline", "thermal", "thermal_cabin")
    if args.formulation == "all" and file_strategies is not None:
        chosen = tuple(file_strategies)  # the scenario file's [run] strategies
    else:
        chosen = allf if args.formulation == "all" else tuple(s.strip() for s in args.formulation.split(","))
    bad = [c for c in chosen if c not in allf]
    if bad:
        raise ScenarioError(f"unknown formulation {bad[0]!r}; choose from {', '.join(allf)} or all")
    if args.convergence:
        from optimize import convergence_study, format_convergence

        # "all": Baseline and Thermal (a halved Thermal-Cabin grid is 16x the work; ask for it explicitly)
        forms = ["baseline", "thermal"] if args.formulation == "all" else [c for c in chosen if c != "rule"]
        rows = convergence_study(ps, scen, forms, grids, progress=True)
        print(format_convergence(rows))
        if args.json:
            write_json(args.json, {"convergence": rows, "scenario": scen.to_dict()})
        return 0

    from calib import Store
    from iptm.pipeline import optimize_cached
    from optimize.formulations import check_grid_axes

    check_grid_axes(scen, grids, ps, chosen)  # before any progress bar: a bad grid is one message
    check_initial_state(scen, chosen, {name: "--" + opt for opt, name in _OPTIONS if getattr(args, opt) is not None},
                        args.scenario)

    # the same store entries as `iptm run`: the identical problem is solved once
    store = None if args.no_cache else Store(args.cache)
    cs = optimize_cached(ps, scen, grids, chosen, store, progress=True, hold=False if args.no_hold else None)
    cyc = scen.load_cycle()
    d = cyc.describe()
    print(f"\ncase study: {d['name']} ({d['duration_s']:.0f} s, {d['distance_km']:.2f} km), ambient "
          f"{scen.T_amb:g} degC, SOC0 {scen.soc0}, T_cl0 {scen.T_cl0} degC, T_cab0 {scen.T_cab0} degC; terminal "
          f"{scen.terminal}; grid steps " + grids.describe([f for f in FORMULATIONS if f in chosen]))
    print(cs.format_table())
    tab = cs.table()
    print("fuel economy, corrected (raw): " + "; ".join(
        f"{k} {r.L_per_100km_corrected:.2f} L/100 km, {r.mpg_corrected:.1f} mpg ({r.L_per_100km:.2f}, {r.mpg:.1f})"
        for k, r in zip(tab["key"], tab.itertuples())))
    print("charge-sustaining (SOC_N >= SOC0 - %g): %s" % (scen.soc_tol, ", ".join(
        f"{k}={'yes' if v else 'NO'}" for k, v in zip(tab["key"], tab["charge_sustaining"]))))
    if all(k in cs.sims for k in allf):
        print(cs.ordering_statement())
    if cs.outcomes:
        print(cs.format_value_check())
    if cs.rule:
        print("tuned rule-based thresholds: " + ", ".join(f"{k}={v:g}" for k, v in cs.rule["thresholds"].items()))
    for k, o in cs.outcomes.items():
        d = o.describe()
        print(f"{k}: {d['n_states']} states x {d['n_controls']} controls, backward {d['t_backward_s']:.2f} s "
              f"({d['evals_per_second'] / 1e6:.0f} M evals/s), total {d['t_total_s']:.2f} s"
              + (" (from the cache)" if getattr(o, "cached", False) else ""))
    if args.plots:
        paths = cs.plot(args.plots)
        print(f"figures: {len(paths)} PNG in {args.plots}")
    if args.json:
        write_json(args.json, cs.to_dict())
        print(f"json: {args.json}")
    return 0
