"""The main job: ingest -> calibrate (with held-out validation) -> optimise four strategies -> report.

Used by ``iptm run`` and by the dashboard; it orchestrates library calls and holds no physics.

Caching (the one content-keyed cache, :class:`calib.store.Store`: ``--cache``, ``IPTM_CACHE_DIR`` or
``.iptm-cache/``): ingested logs are keyed by file hash and reader options; calibrations by the logs' hashes,
the base parameters and the software version; each strategy's optimisation by :func:`calib.store.result_key`
(the parameter values, the scenario, the grids, the strategy and the software version). Re-running on the
same inputs reuses all of it; after a small change only what depends on it is recomputed.

A report is assembled in ``reports/.partial-<run-id>/`` and renamed to ``reports/<run-id>/`` only when
complete, so an interrupted run leaves no half-written report behind (and never touches earlier ones).
"""
from __future__ import annotations

import datetime as _dt
import json
import secrets
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from calib import ChannelLossWarning, IptmError, ScenarioError
from calib import Store, code_version, content_key, result_key

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
    #: ``on_progress(k, n, stage, fraction, text)`` at every stage's start, advance and end (the dashboard's bar)
    on_progress: object = None


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
    from optimize.formulations import DEFAULT_GRIDS, parse_grid_steps
    from optimize import DPScenario

    if path is None:
        return DPScenario(), DEFAULT_GRIDS, STRATEGIES, None
    path = Path(path)
    from calib import read_config

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


class StageProgress:
    """The main job's progress: one line per stage on stderr (``[k/n] stage: bar | elapsed text``, the bar
    advancing within the stage) and, for the dashboard, ``callback(k, n, stage, fraction, text)``. A stage's
    work reports into its own line; nothing nests a second counter inside it."""

    TICKS = 1000

    def __init__(self, stages, show: bool = True, callback=None):
        self.stages, self.show, self.callback = list(stages), show, callback
        self._bar, self._stage, self._text = None, None, ""

    def _emit(self, fraction: float) -> None:
        if self.callback is not None:
            self.callback(self.stages.index(self._stage) + 1, len(self.stages), self._stage,
                          min(max(float(fraction), 0.0), 1.0), self._text)

    def start(self, stage: str, text: str = "") -> None:
        """Close the stage before and open ``stage`` (one of ``stages``) at 0."""
        from tqdm import tqdm

        self.close()
        self._stage, self._text = stage, text
        k = self.stages.index(stage) + 1
        self._bar = tqdm(total=self.TICKS, desc=f"[{k}/{len(self.stages)}] {stage}", disable=not self.show,
                         file=sys.stderr, bar_format="{desc}: {bar:20}| {elapsed}{postfix}")
        self._bar.set_postfix_str(text)
        self._emit(0.0)

    def update(self, fraction: float, text: str | None = None) -> None:
        """The current stage ``fraction`` (0..1) done; ``text`` says what it is doing."""
        if self._stage is None:
            return
        if text is not None:
            self._text = text
            self._bar.set_postfix_str(text, refresh=False)
        self._bar.n = int(round(min(max(fraction, 0.0), 1.0) * self.TICKS))
        self._bar.refresh()
        self._emit(fraction)

    def abort(self) -> None:
        """Stop showing the current stage (the run failed): its line stays where it stopped."""
        if self._bar is not None:
            self._bar.close()
        self._bar, self._stage = None, None

    def close(self, text: str | None = None) -> None:
        """The current stage is done (``text``: its result)."""
        if self._stage is not None and self._bar is not None:
            self.update(1.0, text)
            self._bar.close()
        self._bar, self._stage = None, None


# ---------------------------------------------------------------------------------------------------
# stages
# ---------------------------------------------------------------------------------------------------
def ingest_all(paths, store: Store | None, dbc=None, progress=True, strict=False, on_log=None):
    """Read every log (cached); any bad log stops the run here, before heavy work, naming the file.

    A damaged log is read as far as it can be trusted (its label says [RECOVERED]) unless ``strict``.
    ``on_log(i, n, path)``: called after each log is read (the main job's stage line).
    """
    from tqdm import tqdm

    from calib.ingest import channel_report, input_digest, loss_text, read_canonical, read_log, write_canonical
    from calib.ingest import warn_damage

    logs = []
    paths = list(paths)
    for p in tqdm(paths, desc="ingest", unit="log", disable=not progress, file=sys.stderr):
        p = Path(p)
        if not p.is_file():
            raise IptmError(f"{p}: no such log file")
        key = content_key(input_digest(p, dbc=dbc), code_version("calib"))
        cached = store.path("ingest", key, "parquet") if store else None
        log = None
        if cached is not None and cached.is_file():
            store.touch(cached)
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
                store.written(cached)
        logs.append((p, log, channel_report(log)))
        if on_log is not None:
            on_log(len(logs), len(paths), p)
    return logs


def calibrate_cached(fit_logs, val_logs, base, store: Store | None, progress=True):
    """Calibrate (or reuse a cached calibration of the same logs and base parameters).

    Returns (ParameterSet, calibration dict, text report, validation-plot PNG paths in the cache, artifact).
    The cache entry (kind ``calib``) also holds the saved :class:`calib.fit.driver.CalibrationResult`
    (``result/``, docs/results.md)."""
    from calib.fit import calibrate

    # "figures-2": measured-vs-simulated on every log (fitted and held out) and the residuals figure; the whole
    # parameter entries (bounds and priors too) enter the key: they shape the fit
    key = result_key("calibration", params=base.to_dict()["parameters"], code=("calib", "iptm"),
                     inputs=[[lg.content_digest() for lg in fit_logs], [lg.content_digest() for lg in val_logs]])
    folder = store.get_dir("calib", key) if store else None
    if folder is not None:
        try:
            return _calibration_entry(folder)
        except (OSError, ValueError, IptmError):
            pass  # damaged cache entry: recompute
    res = calibrate(fit_logs, base=base, validate=val_logs or None, progress=progress)
    fill = lambda d: _write_calibration(d, res, fit_logs, val_logs)  # noqa: E731
    if store is not None:
        folder = store.put_dir("calib", key, fill)
    else:  # no cache: a temporary folder of this process's own for the figures the report copies, removed at exit
        import atexit
        import shutil
        import tempfile

        folder = Path(tempfile.mkdtemp(prefix="iptm-calib-"))
        atexit.register(shutil.rmtree, folder, True)
        fill(folder)
    return _calibration_entry(folder)


def _write_calibration(folder: Path, res, fit_logs, val_logs) -> None:
    from calib import write_json, write_text
    from calib.fit import plot_residual_comparison, plot_validation
    from calib import replay

    res.to_artifact(folder / "calibration.toml")
    res.save(folder / "result")
    write_json(folder / "calibration.json", res.to_dict())
    write_text(folder / "report.txt", res.report())
    reps = []
    for role, logs_ in (("fit", fit_logs), ("validation", val_logs)):
        for i, lg in enumerate(logs_):
            rep = replay(lg, res.params)
            what = "held out" if role == "validation" else "fitted"
            reps.append((f"{lg.label()} ({what})", rep))
            plot_validation(rep, folder / f"{role}_{i}_{Path(lg.name).stem}.png",
                            title=f"{lg.label()} ({what}): measured vs simulated")
    plot_residual_comparison(reps, folder / "residuals.png", title="residuals (simulated - measured) on the fitted "
                                                                   "and the held-out logs")


def _calibration_entry(folder: Path):
    from calib import ParameterSet

    return (ParameterSet.load(folder / "calibration.toml"), json.loads((folder / "calibration.json").read_text()),
            (folder / "report.txt").read_text(), _figures(folder), folder / "calibration.toml")


def _figures(folder: Path) -> list[Path]:
    """The calibration figures in report order: fitted logs, held-out logs, residuals."""
    return (sorted(folder.glob("fit_*.png")) + sorted(folder.glob("validation_*.png"))
            + sorted(folder.glob("residuals.png")))


class _StageBar:
    """A strategy's share of the main job's optimisation stage, with tqdm's ``set_postfix_str``/``update``:
    strategy ``i`` of ``n`` covers ``[i/n, (i+1)/n]`` of the stage; :meth:`steps` advances it within."""

    def __init__(self, stage: StageProgress, i: int, n: int, name: str):
        self.stage, self.i, self.n, self.name = stage, i, n, name
        self.fraction = i / n  # of the stage; never moves back

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def set_postfix_str(self, text: str) -> None:
        self.stage.update(self.fraction, f"{self.name}: {text}")

    def steps(self, done: int, total: int) -> None:
        """The DP's backward pass: ``done`` of ``total`` steps."""
        self.fraction = max(self.fraction, (self.i + min(done / max(total, 1), 1.0)) / self.n)
        self.stage.update(self.fraction, f"{self.name}: solving, step {done} of {total}")

    def update(self, _n: int = 1) -> None:
        self.fraction = (self.i + 1) / self.n
        self.stage.update(self.fraction)


def _save_part(folder: Path, cs, o, strat: str) -> None:
    """A strategy's cache entry: its simulations, its DP outcome (if it has one), timing and rule thresholds."""
    from calib import write_json

    for name, sim in cs.sims.items():
        sim.write_into(folder / f"sim-{name}")
    if o is not None:
        o.save(folder / "outcome")
    write_json(folder / "entry.json", {"sims": list(cs.sims), "timing": cs.timings.get(strat, 0.0), "rule": cs.rule})


def _load_part(folder: Path):
    """``(sims, outcome or None, timing, rule)`` of a cache entry written by :func:`_save_part`; None where it
    cannot be read (it is then solved again and replaced)."""
    from calib import SimResult
    from optimize.formulations import DPOutcome

    try:
        entry = json.loads((folder / "entry.json").read_text())
        sims = {name: SimResult.load(folder / f"sim-{name}") for name in entry["sims"]}
        o = DPOutcome.load(folder / "outcome") if (folder / "outcome").is_dir() else None
    except (OSError, ValueError, KeyError, TypeError, IptmError):
        return None
    if o is not None:
        o.cached = True  # the report and the CLI say it came from the cache
    return sims, o, entry.get("timing", 0.0), entry.get("rule")


def _states_text(outcome: dict | None) -> str:
    if not outcome or not outcome.get("n_states"):
        return ""
    return f"{outcome['n_states']:,} states x {outcome.get('n_controls', 0):,} controls, "


def optimize_cached(params, scen, grids, strategies, store: Store | None, progress=True, cycle_log=None,
                    hold: bool | None = None, stage: StageProgress | None = None, on_steps=None):
    """Run the case study strategy by strategy, reusing cached results keyed by parameter values,
    scenario (with the cycle file's hash), grids, strategy, solver options (``hold``: Thermal-Cabin-DP's
    hold-the-bound heater control; None: its default) and software version. ``grids``: as
    :func:`optimize.casestudy.run_case_study`; each strategy's key holds its own grid. ``stage``: the main
    job's stage line, which then shows the strategies (and a DP's backward pass, where the solver reports
    it) in place of a bar per strategy. ``on_steps(done, total)``: the DP's backward pass (the dashboard's bar).

    A strategy's entry in the cache (kind ``dp``, :func:`calib.store.result_key`) holds its saved results:
    ``sim-NAME/`` simulations and ``outcome/`` the DP outcome (docs/results.md), loaded as they were solved."""
    from dataclasses import replace

    from tqdm import tqdm

    from calib import file_sha256
    from optimize import LABELS, CaseStudy, run_case_study
    from optimize import FORMULATIONS
    from optimize.formulations import FormulationGrids

    grids = FormulationGrids.coerce(grids)
    if cycle_log is not None:
        from calib import load_cycle
        from calib import write_text

        cyc = load_cycle(cycle_log)
        folder = (store.root if store else Path(".")) / "cycles"
        path = folder / f"{cycle_log.meta.sha256[:16] or 'log'}_{Path(cycle_log.name).stem}.csv"
        write_text(path, "time_s,speed_kph\n" + "\n".join(f"{t:g},{v * 3.6:.4f}" for t, v in zip(cyc.t, cyc.v)))
        scen = replace(scen, cycle=str(path))
    cyc_id = scen.cycle
    if Path(scen.cycle).is_file():
        cyc_id = file_sha256(scen.cycle)
    sims, outcomes, timings, rule = {}, {}, {}, None
    for i, strat in enumerate(strategies):
        opts = {} if hold is None or strat != "thermal_cabin" else {"hold": bool(hold)}
        key = result_key(strat, params=params, scenario={**scen.to_dict(), "cycle": cyc_id},
                         grids=grids.of(strat).to_dict() if strat in FORMULATIONS else None, options=opts)
        folder = store.get_dir("dp", key) if store else None
        part = _load_part(folder) if folder is not None else None
        # alone (``iptm optimize``): one bar per strategy, named, with its state count (a single bar over all
        # strategies gives a time-left estimate that jumps whenever a strategy of another size starts); in the
        # main job the stage's own line shows the strategy, with no second counter inside it
        name = LABELS.get(strat, strat)
        bar = _StageBar(stage, i, len(strategies), name) if stage is not None else tqdm(
            total=1, desc=f"[{i + 1}/{len(strategies)}] {name}", unit="strategy", disable=not progress,
            file=sys.stderr, bar_format="{desc}: {bar:20}| {elapsed} {postfix}")
        with bar:
            if part is not None:
                p_sims, o, timing, p_rule = part
                sims.update(p_sims)
                if o is not None:
                    outcomes[strat] = o
                timings[strat] = timing
                rule = p_rule or rule
                bar.set_postfix_str(_states_text(o.describe() if o else None) + "from the cache")
            else:
                bar.set_postfix_str("solving" if strat != "rule" else "tuning the thresholds")
                steps = on_steps or (bar.steps if stage is not None else None)
                cs = run_case_study(params, scen, (strat,), progress=False, grids=grids, hold=hold,
                                    step_progress=steps)
                sims.update(cs.sims)
                outcomes.update(cs.outcomes)
                timings.update(cs.timings)
                rule = cs.rule or rule
                o = cs.outcomes.get(strat)
                if store is not None:
                    store.put_dir("dp", key, lambda d, cs=cs, o=o, strat=strat: _save_part(d, cs, o, strat))
                bar.set_postfix_str(_states_text(o.describe() if o else None) + f"solved in {cs.timings.get(strat, 0.0):.1f} s")
            bar.update(1)
    order = [k for k in ("rule", "baseline", "thermal", "thermal_cabin", "baseline_warm") if k in sims]
    return CaseStudy({k: sims[k] for k in order}, outcomes, scen, grids, rule, timings)


def _truth_for(paths):
    """The truth parameter file written by ``iptm synth`` next to SYNTHETIC logs, when there is one."""
    from calib import ParameterSet

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


def _run_stages(cfg, stage, t0, scen, grids, store, paths, val_paths, fit_paths, base, halve):
    # 1. every log is read before any heavy work: a bad one stops the run here, naming the file
    to_read = list(dict.fromkeys(paths + val_paths))
    stage.start("ingest", f"{len(to_read)} log(s)")
    ingested = ingest_all(to_read, store, cfg.dbc, False, cfg.strict,
                          on_log=lambda i, n, p: stage.update(i / n, f"read {p.name} ({i} of {n})"))
    stage.close()
    by_path = {p: lg for p, lg, _ in ingested}
    from calib.ingest import split_fit_validation

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

    # 2. calibration (the fitters report no steps: the line says what is fitted and when it is done)
    stage.start("calibrate", f"fitting on {', '.join(lg.label() for lg in fit_logs)}"
                + (f"; validating on {', '.join(lg.label() for lg in val_logs)}" if val_logs else ""))
    params, calib_info, calib_text, val_pngs, artifact = calibrate_cached(fit_logs, val_logs, base, store, False)
    stage.close("done")

    # 3. optimisation
    stage.start("optimise", f"{', '.join(cfg.strategies)} on {scen.cycle if cyc_log is None else cyc_log.label()}")
    cs = optimize_cached(params, scen, grids, cfg.strategies, store, cfg.progress, cycle_log=cyc_log, stage=stage)
    stage.close()
    if halve:
        stage.start("grid convergence", f"{', '.join(halve)} with every grid step halved")
        cs_half = optimize_cached(params, scen, grids.halved(), halve, store, cfg.progress, cycle_log=cyc_log,
                                  stage=stage)
        from optimize import case_study_halving

        cs.convergence = case_study_halving(cs, cs_half)
        stage.close()

    # 4. report
    stage.start("report", "writing the report")
    from iptm.report import build_report

    run_key = content_key([lg.content_digest() for _, lg, _ in ingested], scen.to_dict(), grids.to_dict(),
                          list(cfg.strategies))
    report_dir = build_report(
        reports_dir=Path(cfg.reports_dir), run_id=new_run_id(run_key), ingested=ingested, fit_logs=fit_logs,
        val_logs=val_logs, params=params, calib_info=calib_info, calib_text=calib_text, val_pngs=val_pngs,
        artifact=artifact, case_study=cs, scenario=scen, grids=grids, base_params=cfg.base_params,
        command_line=cfg.command_line, wall_s=time.perf_counter() - t0, drive_warnings=drive_warnings,
        truth=truth)
    stage.close(f"written: {report_dir.name}")
    return report_dir, ingested


def run(cfg: RunConfig) -> RunOutcome:
    """The whole chain; returns where the report is and the headline figures."""
    from calib import ParameterSet, default_parameters
    from optimize import DPScenario
    from optimize.formulations import FormulationGrids

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

    from optimize import ROUTINE_HALVING

    halve = [s for s in cfg.strategies if s in ROUTINE_HALVING] if cfg.convergence else []
    # one line per stage, numbered over the stages this run has
    stages = ["ingest", "calibrate", "optimise"] + (["grid convergence"] if halve else []) + ["report"]
    stage = StageProgress(stages, cfg.progress, cfg.on_progress)
    try:
        report_dir, _ = _run_stages(cfg, stage, t0, scen, grids, store, paths, val_paths, fit_paths, base, halve)
    except BaseException:
        stage.abort()  # a failed stage is not shown as done
        raise
    summary = json.loads((report_dir / "report.json").read_text())["summary"]
    return RunOutcome(report_dir, summary, time.perf_counter() - t0)
