"""The main job: ingest -> calibrate (with held-out validation) -> optimise four strategies -> report.

Used by ``iptm run`` and by the dashboard; it orchestrates library calls and holds no physics.

Caching (``.iptm-cache/`` next to the reports, content-keyed, :class:`calib.store.Store`): ingested logs
are keyed by file hash and reader options; calibrations by the logs' hashes, the base parameters and the
options; each strategy's optimisation by the parameter values, the scenario, the grids and the software
version. Re-running on the same inputs reuses all of it; after a small change only what depends on it is
recomputed.

A report is assembled in ``reports/.partial-<run-id>/`` and renamed to ``reports/<run-id>/`` only when
complete, so an interrupted run leaves no half-written report behind (and never touches earlier ones).
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import secrets
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from calib.errors import ChannelLossWarning, IptmError, ScenarioError
from calib.store import Store, code_version, content_key

DEFAULT_LOG_GLOB = "*.blf"
STRATEGIES = ("rule", "baseline", "thermal", "thermal_cabin")


@dataclass
class RunConfig:
    """Everything a run depends on."""

    logs: list
    scenario: object = None  # optimize.formulations.DPScenario
    grids: object = None  # optimize.formulations.FormulationGrids (or one DPGrids for all); None: the defaults
    strategies: tuple = STRATEGIES
    cycle_from_log: str | None = None  # path of a log whose speed trace is the cycle
    validate: list = field(default_factory=list)  # held-out logs (default: the last of several logs)
    base_params: str | None = None
    dbc: str | None = None
    strict: bool = False  # refuse damaged logs instead of reading what they still hold
    reports_dir: Path = Path("reports")
    cache_dir: Path | None = None
    progress: bool = True
    command_line: str = ""
    convergence: bool = True  # also solve Baseline- and Thermal-DP with every grid step halved


def load_scenario(path=None):
    """Read a scenario TOML (``[scenario]`` DPScenario fields, ``[grids]`` grid steps, ``[run]`` strategies).

    ``[scenario] cycle`` is a bundled name, a speed-trace CSV, or ``"from log"`` with ``cycle_log = FILE``
    (default: the first log of the run).

    ``[grids]`` steps replace those of every formulation's default grid
    (:data:`optimize.formulations.DEFAULT_GRIDS`); without ``[grids]`` each formulation solves on its default.

    Returns
    -------
    (DPScenario, FormulationGrids, strategies, cycle_log or None)
    """
    from optimize.formulations.scenario import DEFAULT_GRIDS, DPScenario, parse_grid_steps

    if path is None:
        return DPScenario(), DEFAULT_GRIDS, STRATEGIES, None
    path = Path(path)
    from calib.fileio import read_config

    d = read_config(path, ScenarioError, "scenario file")
    unknown = set(d) - {"scenario", "grids", "run"}
    if unknown:
        raise ScenarioError(f"{path}: unknown section(s) {sorted(unknown)}; use [scenario], [grids], [run]")
    sc = dict(d.get("scenario", {}))
    cycle_log = None
    if str(sc.get("cycle", "")).replace("_", " ").lower() == "from log":
        cycle_log = sc.pop("cycle_log", "") or ""
        sc["cycle"] = "artemis_urban"  # replaced by the log's trace at run time
    try:
        scen = DPScenario.from_dict(sc)
    except ScenarioError as exc:
        raise ScenarioError(f"{path}: {exc}") from None
    except TypeError as exc:
        raise ScenarioError(f"{path}: [scenario]: {exc}") from None
    try:
        grids = DEFAULT_GRIDS.with_steps(**parse_grid_steps(d.get("grids", {})))
    except ScenarioError as exc:
        raise ScenarioError(f"{path}: [grids]: {exc}") from None
    run = d.get("run", {})
    strategies = run.get("strategies", STRATEGIES) if isinstance(run, dict) else None
    if not isinstance(strategies, (list, tuple)) or not all(isinstance(s, str) for s in strategies):
        raise ScenarioError(f"{path}: [run] strategies must be a list of names ({', '.join(STRATEGIES)}), "
                            f"got {strategies!r}")
    strategies = tuple(strategies)
    bad = [s for s in strategies if s not in STRATEGIES]
    if bad:
        raise ScenarioError(f"{path}: unknown strategies {bad}; choose from {', '.join(STRATEGIES)}")
    return scen, grids, strategies, cycle_log


def default_logs(root=None) -> list[Path]:
    """The bundled logs the main job runs on when none are named (:func:`iptm.bundled.bundled_logs_dir`)."""
    if root is None:
        from iptm.bundled import bundled_logs_dir

        root = bundled_logs_dir()
    files = sorted(Path(root).glob(DEFAULT_LOG_GLOB))
    if not files:
        raise IptmError(f"no logs given and none bundled in {root}/ (expected {DEFAULT_LOG_GLOB}); "
                        "run `iptm synth --out logs` or name your logs")
    return files


def _say(msg: str, progress: bool) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------------
# stages
# ---------------------------------------------------------------------------------------------------
def ingest_all(paths, store: Store | None, dbc=None, progress=True, strict=False):
    """Read every log (cached); any bad log stops the run here, before heavy work, naming the file.

    A damaged log is read as far as it can be trusted (its label says [RECOVERED]) unless ``strict``.
    """
    from tqdm import tqdm

    from calib.ingest import channel_report, input_digest, loss_text, read_canonical, read_log, write_canonical
    from calib.ingest.damage import warn_damage

    logs = []
    for p in tqdm(list(paths), desc="ingest", unit="log", disable=not progress, file=sys.stderr):
        p = Path(p)
        if not p.is_file():
            raise IptmError(f"{p}: no such log file")
        key = content_key(input_digest(p, dbc=dbc), code_version("calib"))
        cached = store.path("ingest", key, "parquet") if store else None
        log = None
        if cached is not None and cached.is_file():
            try:
                log = read_canonical(cached)
            except IptmError:
                log = None
            if log is not None and log.meta.damage:
                if strict:
                    log = None  # read again so that strict raises the damage as an error
                else:
                    warn_damage(p, log.meta.damage)
            if log is not None and loss_text(log.meta):
                warnings.warn(ChannelLossWarning(f"{p}: {loss_text(log.meta)}"), stacklevel=2)
        if log is None:
            log = read_log(p, dbc=dbc, strict=strict)
            if store is not None:
                write_canonical(log, cached)
        logs.append((p, log, channel_report(log)))
    return logs


def calibrate_cached(fit_logs, val_logs, base, store: Store | None, progress=True):
    """Calibrate (or reuse a cached calibration of the same logs and base parameters).

    Returns (ParameterSet, calibration dict, text report, validation-plot PNG paths in the cache).
    """
    from calib.fit.driver import calibrate
    from calib.model.params import ParameterSet
    from calib.fit.validate import plot_residual_comparison, plot_validation, replay

    # "figures-2": measured-vs-simulated on every log (fitted and held out) and the residuals figure
    key = content_key([lg.content_digest() for lg in fit_logs], [lg.content_digest() for lg in val_logs],
                      base.to_dict()["parameters"], code_version("calib", "iptm"))
    folder = store.root / "calib" / key if store else None
    if folder is not None and (folder / "done").is_file():
        try:
            ps = ParameterSet.load(folder / "calibration.toml")
            info = json.loads((folder / "calibration.json").read_text())
            text = (folder / "report.txt").read_text()
            return ps, info, text, _figures(folder), folder / "calibration.toml"
        except (OSError, ValueError, IptmError):
            pass  # damaged cache entry: recompute
    res = calibrate(fit_logs, base=base, validate=val_logs or None, progress=progress)
    # a folder of this process's own: two runs calibrating the same logs at once must not share one
    tag = f".partial-{os.getpid()}-{secrets.token_hex(3)}"
    tmp = Path(str(folder) + tag) if folder else Path(".iptm-calib" + tag)
    tmp.mkdir(parents=True)
    res.to_artifact(tmp / "calibration.toml")
    from calib.fileio import write_json, write_text

    write_json(tmp / "calibration.json", res.to_dict())
    write_text(tmp / "report.txt", res.report())
    reps = []
    for role, logs_ in (("fit", fit_logs), ("validation", val_logs)):
        for i, lg in enumerate(logs_):
            rep = replay(lg, res.params)
            what = "held out" if role == "validation" else "fitted"
            reps.append((f"{lg.label()} ({what})", rep))
            plot_validation(rep, tmp / f"{role}_{i}_{Path(lg.name).stem}.png",
                            title=f"{lg.label()} ({what}): measured vs simulated")
    plot_residual_comparison(reps, tmp / "residuals.png", title="residuals (simulated - measured) on the fitted and the "
                                                      "held-out logs")
    (tmp / "done").write_text("")
    if folder is None:
        folder = tmp
    else:
        try:
            tmp.rename(folder)
        except OSError:
            if (folder / "done").is_file():
                # another run filed the same calibration first (the key is the content: the same result)
                shutil.rmtree(tmp, ignore_errors=True)
            else:  # a damaged entry left by an interrupted run
                shutil.rmtree(folder, ignore_errors=True)
                tmp.rename(folder)
    return (ParameterSet.load(folder / "calibration.toml"), json.loads((folder / "calibration.json").read_text()),
            (folder / "report.txt").read_text(), _figures(folder), folder / "calibration.toml")


def _figures(folder: Path) -> list[Path]:
    """The calibration figures in report order: fitted logs, held-out logs, residuals."""
    return (sorted(folder.glob("fit_*.png")) + sorted(folder.glob("validation_*.png"))
            + sorted(folder.glob("residuals.png")))


class _StoredOutcome:
    """What the report needs of a DP outcome, restored from the cache."""

    cached = True

    def __init__(self, d: dict, T_cab_lb=None):
        self._d = d
        self.extra = d  # describe() flattens the outcome's extra figures into the dict
        self.T_cab_lb = T_cab_lb  # the comfort bound at steps 1..N (a list), for the cabin figure

    def describe(self) -> dict:
        return self._d

    @property
    def dp_cost(self) -> float:
        return self._d["dp_cost_g"]

    @property
    def predicted_cost(self) -> float:
        return self._d["predicted_cost_g"]


def _states_text(outcome: dict | None) -> str:
    if not outcome or not outcome.get("n_states"):
        return ""
    return f"{outcome['n_states']:,} states x {outcome.get('n_controls', 0):,} controls, "


def optimize_cached(params, scen, grids, strategies, store: Store | None, progress=True, cycle_log=None,
                    hold: bool | None = None):
    """Run the case study strategy by strategy, reusing cached results keyed by parameter values,
    scenario (with the cycle file's hash), grids, strategy, solver options (``hold``: Thermal-Cabin-DP's
    hold-the-bound heater control; None: its default) and software version. ``grids``: as
    :func:`optimize.casestudy.run_case_study`; each strategy's key holds its own grid."""
    from dataclasses import replace

    from tqdm import tqdm

    from calib.drivelog import file_sha256
    from calib.model.simulate import sim_from_arrays, sim_to_arrays
    from optimize.casestudy import LABELS, CaseStudy, run_case_study
    from optimize.formulations.scenario import FORMULATIONS, FormulationGrids

    grids = FormulationGrids.coerce(grids)
    if cycle_log is not None:
        from calib.model.cycles import load_cycle
        from calib.fileio import write_text

        cyc = load_cycle(cycle_log)
        folder = (store.root if store else Path(".")) / "cycles"
        path = folder / f"{cycle_log.meta.sha256[:16] or 'log'}_{Path(cycle_log.name).stem}.csv"
        write_text(path, "time_s,speed_kph\n" + "\n".join(f"{t:g},{v * 3.6:.4f}" for t, v in zip(cyc.t, cyc.v)))
        scen = replace(scen, cycle=str(path))
    cyc_id = scen.cycle
    if Path(scen.cycle).is_file():
        cyc_id = file_sha256(scen.cycle)
    pvals = {k: v["value"] for k, v in params.to_dict()["parameters"].items()}
    sims, outcomes, timings, rule = {}, {}, {}, None
    for i, strat in enumerate(strategies):
        opts = {} if hold is None or strat != "thermal_cabin" else {"hold": bool(hold)}
        key = content_key(pvals, {**scen.to_dict(), "cycle": cyc_id}, grids.of(strat).to_dict() if strat in FORMULATIONS else {},
                          strat, code_version("calib", "optimize"),
                          *([opts] if opts else []))
        entry = store.get_json("dp", key) if store else None
        arrays = {name: store.get_npz("dp", f"{key}-{name}") for name in (entry or {}).get("sims", [])}
        # one bar per strategy, named, with its state count: a single bar over all strategies gives a
        # time-left estimate that jumps whenever a strategy of another size starts
        with tqdm(total=1, desc=f"[{i + 1}/{len(strategies)}] {LABELS.get(strat, strat)}", unit="strategy",
                  disable=not progress, file=sys.stderr, bar_format="{desc}: {bar:20}| {elapsed} {postfix}") as bar:
            if entry is not None and all(a is not None for a in arrays.values()):
                for name, a in arrays.items():
                    sims[name] = sim_from_arrays(a)
                if entry.get("outcome"):
                    outcomes[strat] = _StoredOutcome(entry["outcome"], entry.get("T_cab_lb"))
                timings[strat] = entry.get("timing", 0.0)
                rule = entry.get("rule") or rule
                bar.set_postfix_str(_states_text(entry.get("outcome")) + "from the cache")
            else:
                bar.set_postfix_str("solving" if strat != "rule" else "tuning the thresholds")
                cs = run_case_study(params, scen, (strat,), progress=False, grids=grids, hold=hold)
                sims.update(cs.sims)
                outcomes.update(cs.outcomes)
                timings.update(cs.timings)
                rule = cs.rule or rule
                o = cs.outcomes.get(strat)
                if store is not None:
                    for name, sim in cs.sims.items():
                        store.put_npz("dp", f"{key}-{name}", sim_to_arrays(sim))
                    store.put_json("dp", key, {"sims": list(cs.sims), "timing": cs.timings.get(strat, 0.0),
                                               "rule": cs.rule, "outcome": o.describe() if o else None,
                                               "T_cab_lb": None if getattr(o, "T_cab_lb", None) is None
                                               else [float(x) for x in o.T_cab_lb]})
                bar.set_postfix_str(_states_text(o.describe() if o else None) + f"solved in {cs.timings.get(strat, 0.0):.1f} s")
            bar.update(1)
    order = [k for k in ("rule", "baseline", "thermal", "thermal_cabin", "baseline_warm") if k in sims]
    return CaseStudy({k: sims[k] for k in order}, outcomes, scen, grids, rule, timings)


def _truth_for(paths):
    """The truth parameter file written by ``iptm synth`` next to SYNTHETIC logs, when there is one."""
    from calib.model.params import ParameterSet

    for folder in dict.fromkeys(Path(p).parent for p in paths):
        f = folder / "truth_params.toml"
        if f.is_file():
            try:
                return f, ParameterSet.load(f)
            except IptmError:
                return None
    return None


def new_run_id(cfg_key: str) -> str:
    """Time, the configuration's key and a random part: two identical runs started in the same second get
    distinct ids (and report folders)."""
    return (_dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S") + "-" + cfg_key[:6] + "-"
            + secrets.token_hex(2))


@dataclass
class RunOutcome:
    report_dir: Path
    summary: dict
    wall_s: float


def run(cfg: RunConfig) -> RunOutcome:
    """The whole chain; returns where the report is and the headline figures."""
    from calib.model.params import ParameterSet, default_parameters
    from optimize.formulations.scenario import DPScenario, FormulationGrids

    t0 = time.perf_counter()
    scen = cfg.scenario or DPScenario()
    grids = FormulationGrids.coerce(cfg.grids)
    store = Store(cfg.cache_dir) if cfg.cache_dir else None
    paths = [Path(p) for p in cfg.logs]
    val_paths = [Path(p) for p in cfg.validate]
    if not val_paths and len(paths) > 1:
        val_paths = [paths[-1]]  # hold out the last log for validation
    fit_paths = [p for p in paths if p not in val_paths]
    base = ParameterSet.load(cfg.base_params) if cfg.base_params else default_parameters()

    # 1. every log is read before any heavy work: a bad one stops the run here, naming the file
    _say(f"[1/4] ingesting {len(paths) + len([p for p in val_paths if p not in paths])} log(s)", cfg.progress)
    ingested = ingest_all(list(dict.fromkeys(paths + val_paths)), store, cfg.dbc, cfg.progress, cfg.strict)
    by_path = {p: lg for p, lg, _ in ingested}
    from calib.ingest.drives import split_fit_validation

    # copies of one drive (e.g. the same drive as BLF and CSV) are fitted once, and never used to validate
    fit_logs, val_logs, drive_warnings = split_fit_validation([by_path[p] for p in fit_paths],
                                                              [by_path[p] for p in val_paths])
    for w in drive_warnings:
        _say(f"warning: {w}", True)
    truth = _truth_for(paths) if all(lg.meta.synthetic for _, lg, _ in ingested) else None
    cycle_log = cfg.cycle_from_log
    if cycle_log is not None:
        cyc_path = Path(cycle_log) if cycle_log else paths[0]
        cyc_log = by_path.get(cyc_path) or ingest_all([cyc_path], store, cfg.dbc, False, cfg.strict)[0][1]
    else:
        cyc_log = None

    # 2. calibration
    _say(f"[2/4] calibrating on {', '.join(lg.label() for lg in fit_logs)}"
         + (f"; validating on {', '.join(lg.label() for lg in val_logs)}" if val_logs else ""), cfg.progress)
    params, calib_info, calib_text, val_pngs, artifact = calibrate_cached(fit_logs, val_logs, base, store,
                                                                         cfg.progress)

    # 3. optimisation
    _say(f"[3/4] optimising {', '.join(cfg.strategies)} on {scen.cycle if cyc_log is None else cyc_log.label()}",
         cfg.progress)
    cs = optimize_cached(params, scen, grids, cfg.strategies, store, cfg.progress, cycle_log=cyc_log)
    if cfg.convergence:
        from optimize.convergence import ROUTINE_HALVING, case_study_halving

        halve = [s for s in cfg.strategies if s in ROUTINE_HALVING]
        if halve:
            _say(f"[3/4] grid convergence: {', '.join(halve)} with every grid step halved", cfg.progress)
            cs_half = optimize_cached(params, scen, grids.halved(), halve, store, cfg.progress, cycle_log=cyc_log)
            cs.convergence = case_study_halving(cs, cs_half)

    # 4. report
    _say("[4/4] writing the report", cfg.progress)
    from iptm.report import build_report

    run_key = content_key([lg.content_digest() for _, lg, _ in ingested], scen.to_dict(), grids.to_dict(),
                          list(cfg.strategies))
    report_dir = build_report(
        reports_dir=Path(cfg.reports_dir), run_id=new_run_id(run_key), ingested=ingested, fit_logs=fit_logs,
        val_logs=val_logs, params=params, calib_info=calib_info, calib_text=calib_text, val_pngs=val_pngs,
        artifact=artifact, case_study=cs, scenario=scen, grids=grids, base_params=cfg.base_params,
        command_line=cfg.command_line, wall_s=time.perf_counter() - t0, drive_warnings=drive_warnings,
        truth=truth)
    summary = json.loads((report_dir / "report.json").read_text())["summary"]
    return RunOutcome(report_dir, summary, time.perf_counter() - t0)
