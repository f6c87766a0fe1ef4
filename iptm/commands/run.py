"""``iptm run``: the main job: ingest, calibrate, optimise, report."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("run", help="the whole chain: ingest, calibrate, optimise all strategies, report",
                       description="Ingest the logs, calibrate the model (holding out the last log for "
                                   "validation when there are several), optimise rule-based, Baseline-DP, "
                                   "Thermal-DP and Thermal-Cabin-DP on the scenario, and write a report to "
                                   "reports/<run-id>/. Without logs, uses the bundled SYNTHETIC logs/*.blf.")
    p.add_argument("logs", nargs="*", metavar="LOG", help="drive logs (CSV, MCAP, candump, ASC, BLF, MF4)")
    p.add_argument("--scenario", metavar="FILE", help="scenario TOML (default: the paper's case study)")
    p.add_argument("--validate", action="append", default=[], metavar="LOG",
                   help="held-out log for validation (repeatable; default: the last of several logs)")
    p.add_argument("--params", metavar="FILE", help="base parameter set (priors); default: the 2017 Prius")
    p.add_argument("--dbc", metavar="FILE", help="DBC for CAN logs (default: the bundled Prius DBC)")
    p.add_argument("--reports", default="reports", metavar="DIR", help="where reports go (default reports/)")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="cache folder (default $IPTM_CACHE_DIR, else .iptm-cache; size cap $IPTM_CACHE_MAX_MB)")
    p.add_argument("--no-cache", action="store_true", help="recompute everything")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--no-convergence", action="store_true",
                   help="skip the grid-convergence check (Baseline- and Thermal-DP solved again with every grid "
                        "step halved)")
    p.add_argument("--strict", action="store_true",
                   help="refuse damaged logs (default: read what they still hold, say what was lost)")
    p.add_argument("--json", metavar="FILE", help="write the summary figures as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    import shlex
    import sys
    from pathlib import Path

    from calib import write_json
    from calib import default_root
    from iptm import pipeline

    from iptm.commands.calibrate import check_log_format

    logs = [Path(p) for p in args.logs] or pipeline.default_logs()
    for p in list(logs) + [Path(v) for v in args.validate]:
        if p.is_file():  # a missing one is named by the ingest stage
            check_log_format(p, None)  # before any stage starts: `iptm run` has no --format
    scen, grids, strategies, cycle_log = pipeline.load_scenario(args.scenario)
    from iptm.commands.optimize import check_initial_state

    check_initial_state(scen, strategies, source=args.scenario)  # before the logs are read
    cfg = pipeline.RunConfig(logs=logs, scenario=scen, grids=grids, strategies=strategies,
                             cycle_from_log=cycle_log, validate=[Path(p) for p in args.validate],
                             base_params=args.params, dbc=args.dbc, strict=args.strict,
                             reports_dir=Path(args.reports),
                             cache_dir=None if args.no_cache else Path(args.cache or default_root()),
                             progress=not args.quiet,
                             convergence=not args.no_convergence,
                             command_line=" ".join(shlex.quote(a) for a in ["iptm"] + sys.argv[1:]))
    out = pipeline.run(cfg)
    s = out.summary
    print()
    print(f"iptm run {s['run_id']} finished in {out.wall_s:.1f} s"
          + ("  [SYNTHETIC logs]" if s["synthetic_data"] else ""))
    print(f"calibration: {s.get('calibration_text') or str(s['n_estimated']) + ' parameters estimated'}")
    for w in s.get("at_prior") or []:
        print(f"not fitted: {w}")
    print(f"terminal condition on coolant and cabin: {s.get('terminal')}; corrected fuel (final SOC, coolant and "
          "cabin heat valued) first, raw fuel (as burnt) beside it")

    def eco(L, m):
        return f" ({L:.2f} L/100 km, {m:.1f} mpg)" if L is not None and m is not None else ""

    for k, v in s["strategies"].items():
        sav = v.get("saving_vs_rule_pct")
        print(f"  {k:15s} corrected {v['fuel_corrected_g']:8.2f} g{eco(v.get('L_per_100km_corrected'), v.get('mpg_corrected'))}"
              f"  raw {v['fuel_g']:8.2f} g{eco(v.get('L_per_100km'), v.get('mpg'))}  SOC_N {v['soc_final']:.3f}"
              + (f"  saving vs rule-based {sav:5.2f} % corrected ({v.get('raw_saving_vs_rule_pct', float('nan')):.2f} % raw)"
                 if sav is not None else ""))
    print(s.get("ordering") or f"ordering in corrected fuel: {'holds' if s['ordering_ok'] else 'does not hold'}")
    for r in s.get("convergence") or []:
        print(f"grid convergence, {r['formulation']}: every step halved changes the corrected fuel by "
              f"{r['rel_change_corrected_pct']:+.3f} % and the mean cabin by {r['T_cab_mean_change_K']:+.4f} K: "
              + ("converged" if r["converged"] else "NOT converged"))
    print(f"report: {out.report_dir / 'index.html'}")
    if args.json:
        write_json(args.json, {**s, "report_dir": str(out.report_dir)})
    return 0
