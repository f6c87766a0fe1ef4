"""``iptm sweep``: a study (cross product / list of scenarios x parameter sets) on dask.distributed."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("sweep", help="run a parameter study (many DP / rule-based cases) on dask.distributed",
                       description="Expand a study TOML (scenario fields to vary, parameter sets, Monte-Carlo "
                                   "draws from a calibration's uncertainty) into cases, run the chosen strategies "
                                   "of every case on a local cluster (default) or a Dask scheduler, and write one "
                                   "tidy table (Parquet) plus plots. Finished cases are kept in a content-keyed "
                                   "store: they are never recomputed and an interrupted study resumes. See "
                                   "studies/README.md.")
    p.add_argument("study", metavar="STUDY.toml", help="study file")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="Dask scheduler address (e.g. tcp://host:8786); default: a LocalCluster on this machine")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="worker processes of the local cluster (default 2; ignored with --scheduler)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="output folder for results.parquet and the plots (default reports/sweeps/<study name>)")
    p.add_argument("--plots", metavar="DIR", default=None, help="write the plots here instead of --out")
    p.add_argument("--metric", choices=("both", "saving_pct", "saving_corrected_pct"), default="both",
                   help="saving plotted: on fuel (saving_pct), on fuel corrected for the final SOC, coolant and "
                        "cabin energy (saving_corrected_pct), or both side by side (default)")
    p.add_argument("--store", metavar="DIR", default=None,
                   help="the cache folder whose sweep/ holds the cases (default $IPTM_CACHE_DIR, else .iptm-cache)")
    p.add_argument("--retry-failed", action="store_true", help="recompute cases stored with an error")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--json", metavar="FILE", help="write the table and the summary as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    import time
    from pathlib import Path

    import numpy as np

    from calib import IptmError, write_json
    from optimize import format_failures, load_study, plot_study, run_study, summary_pivot, write_table

    if args.workers < 1:
        raise IptmError("--workers must be at least 1")
    study = load_study(args.study)
    cases = study.expand()
    out = Path(args.out) if args.out else Path("reports") / "sweeps" / study.name
    where = args.scheduler or f"a local cluster of {args.workers} worker processes"
    print(f"study {study.name}: {len(cases)} cases x strategies {', '.join(study.strategies)} "
          f"(savings vs {study.reference}); grids {study.grids}; on {where}", flush=True)
    t0 = time.perf_counter()

    def progress(done, total, rec):
        if args.quiet:
            return
        if rec is None:
            print(f"  {done}/{total} cases already in the store", flush=True)
            return
        st = "ok" if not rec.get("error") else f"FAILED: {rec['error']}"
        print(f"  {done}/{total} [{time.perf_counter() - t0:6.1f} s] case {rec.get('key')}: {st}", flush=True)

    df = run_study(study, client=args.scheduler, store_dir=args.store, progress_callback=progress,
                   n_workers=args.workers, retry_failed=args.retry_failed)
    wall = time.perf_counter() - t0
    table = write_table(df, out / "results.parquet")
    plots = plot_study(df, Path(args.plots) if args.plots else out, metric=args.metric)
    n_failed = int((df.groupby("case_id")["status"].apply(lambda s: (s == "failed").any())).sum())
    n_cached = int(df.groupby("case_id")["cached"].first().sum())
    print(f"{len(cases)} cases in {wall:.1f} s ({n_cached} from the store, {n_failed} with a failure)")
    import pandas as pd

    # the corrected saving (final SOC, coolant and cabin heat valued) is the headline: printed first
    what = {"saving_corrected_pct": "corrected-fuel saving", "saving_pct": "raw fuel saving (as burnt)"}
    for m in (("saving_corrected_pct", "saving_pct") if args.metric == "both" else (args.metric,)):
        piv = summary_pivot(df, m)
        if not piv.empty:
            with pd.option_context("display.width", 200, "display.max_columns", 40):
                print(f"median {what[m]} ({m}) vs {study.reference} [%], by ambient (degC):")
                print(piv.to_string(float_format=lambda v: f"{v:.2f}"))
    if n_failed:
        print(format_failures(df))
    print(f"table: {table}")
    for p in plots:
        print(f"plot: {p}")
    if args.json:
        rows = [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()}
                for r in df.astype(object).where(df.notna(), None).to_dict(orient="records")]
        write_json(args.json, {"study": study.name, "source": study.source, "strategies": list(study.strategies),
                               "reference": study.reference, "grids": study.grids, "n_cases": len(cases),
                               "n_failed": n_failed, "n_cached": n_cached, "wall_s": wall, "table_path": str(table),
                               "plots": plots, "table": rows})
    return 0
