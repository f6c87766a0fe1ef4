"""Parameter sweeps: many independent DP / rule-based runs on dask.distributed.

A *study* is a TOML file::

    [study]
    name = "saving_vs_ambient"
    strategies = ["rule", "thermal"]        # any of rule, baseline, thermal, thermal_cabin
    reference = "rule"                       # savings are against this strategy (default: the first)
    grids = {soc = 0.01, tcl = 1, pbat = 500}   # steps replacing each formulation's default (or "soc=0.01,tcl=1")

    [scenario]                               # base DPScenario fields
    duration_s = 600

    [vary]                                   # cross product of these DPScenario fields
    T_amb = [-20, -10, 0]
    cycle = ["artemis_urban", "nycc"]

    [[case]]                                 # optional: a list of scenario overrides (each crossed with [vary])
    Q_heat = 1500

    [link]                                   # optional: fields that take another field's value in every case
    T_cl0 = "T_amb"                          # (e.g. a cold start: coolant and cabin at the ambient)

    [params]                                 # optional: parameter sets (default: the default 2017 Prius)
    files = ["my_car.toml"]                  # parameter files or calibration artifacts (relative to the study)
    montecarlo = {artifact = "calib.toml", n = 20, seed = 1, nominal = false}

Monte-Carlo draws: every parameter of the artifact with status ``estimated`` and a standard error is drawn
from normal(value, stderr), clipped to its bounds; scalar parameters independently, a table parameter with
one standard normal for the whole table (its shape is kept; ``f_cl`` is held non-increasing). A
draw that fails validation is redrawn (up to 50 times). Draw ``i`` of a study is the same on every run
(numpy ``default_rng([seed, i])``).

Cases = parameter sets x ([[case]] entries or one empty entry) x the [vary] cross product. Each case is a
JSON-able dict; :func:`run_case` is a pure function of it and never raises (a failing strategy is recorded
with its error). :func:`run_study` submits the cases missing from a content-keyed result store
(:class:`calib.store.Store`, the cache the pipeline and the dashboard use; key :func:`calib.store.result_key`
= parameter values + scenario + grids + strategies + software version: ``calib.__version__`` and a digest of
the ``calib`` and ``optimize`` sources)
to a dask.distributed cluster - a ``LocalCluster`` of 2 single-threaded worker processes by default, or any
scheduler by address - and writes each result to the store as it arrives, so an interrupted study resumes
and a finished one is never recomputed. A worker that dies mid-case has its case re-run elsewhere
(dask's scheduler reschedules it; ``retries`` more on top). The result is one tidy table, one row per case
and strategy (:data:`TABLE_COLUMNS`), written to Parquet atomically, plus plots: saving vs ambient per cycle
and the spread of the saving over Monte-Carlo draws.
"""
from __future__ import annotations

import asyncio
import itertools
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from optimize.plotting import plot_study  # noqa: F401 - part of this module's API

__all__ = ["Study", "load_study", "study_from_dict", "run_sequential", "run_case", "run_study", "results_table", "write_table", "plot_study",
           "montecarlo_draws", "STRATEGIES", "local_client"]

STRATEGIES = ("rule", "baseline", "thermal", "thermal_cabin")
#: Names in plots.
_KIND = "sweep"
_RESULT_FIELDS = ("fuel_g", "fuel_corrected_g", "soc_final", "T_cl_final_degC", "T_cl_mean_degC",
                  "T_cab_final_degC", "T_cab_mean_degC", "engine_starts", "idle_s")


# ---------------------------------------------------------------------------------------------------
# study definition
# ---------------------------------------------------------------------------------------------------
@dataclass
class ParamSpec:
    """One parameter set of a study: a label, the Monte-Carlo draw index (None: not a draw), the set."""

    label: str
    draw: int | None
    pset: object  # calib.model.params.ParameterSet


@dataclass
class Study:
    """A parsed study (see the module docstring). ``hold_s``: seconds each case sleeps before solving
    (for testing fault tolerance; not part of the content key)."""

    name: str = "study"
    strategies: tuple = ("rule", "thermal")
    reference: str | None = None
    grids: dict = field(default_factory=dict)
    scenario: dict = field(default_factory=dict)
    vary: dict = field(default_factory=dict)
    cases: list = field(default_factory=list)
    param_sets: list = field(default_factory=list)
    link: dict = field(default_factory=dict)
    hold_s: float = 0.0
    source: str = ""

    def __post_init__(self):
        from calib.errors import ScenarioError
        from optimize.formulations.scenario import DPScenario

        for what, val, kinds in (("strategies", self.strategies, (list, tuple)), ("grids", self.grids, (dict, str)),
                                 ("vary", self.vary, (dict,)), ("link", self.link, (dict,))):
            if not isinstance(val, kinds):
                raise ScenarioError(f"study {self.name}: {what} must be a "
                                    f"{'list' if list in kinds else 'table'}, got {val!r}")
        if not all(isinstance(x, str) for x in self.strategies):
            raise ScenarioError(f"study {self.name}: strategies must be names, got {list(self.strategies)!r}")
        self.strategies = tuple(self.strategies)
        if not self.strategies:
            raise ScenarioError(f"study {self.name}: no strategies")
        bad = [s for s in self.strategies if s not in STRATEGIES]
        if bad:
            raise ScenarioError(f"study {self.name}: unknown strategy {bad[0]!r}; choose from {', '.join(STRATEGIES)}")
        if self.reference is None:
            self.reference = self.strategies[0]
        if self.reference not in self.strategies:
            raise ScenarioError(f"study {self.name}: reference {self.reference!r} is not among the strategies")
        from optimize.formulations.scenario import parse_grid_steps

        try:  # the steps given (each replaces that step of every formulation's default grid)
            self.grids = parse_grid_steps(self.grids)
        except ScenarioError as exc:
            raise ScenarioError(f"study {self.name}: bad grid {self.grids!r}: {exc}") from None
        for k, v in self.vary.items():
            if not isinstance(v, list) or not v:
                raise ScenarioError(f"study {self.name}: [vary] {k} must be a non-empty list")
        from dataclasses import fields as _fields

        known = {f.name for f in _fields(DPScenario)}
        for k, src in self.link.items():
            if k not in known or src not in known:
                raise ScenarioError(f"study {self.name}: [link] {k} = {src!r}: both must be scenario fields; "
                                    f"known: {sorted(known)}")
        # validate field names early (one-line errors before anything is submitted)
        # every value of [vary] checked once here (not every combination), so a bad one is refused on loading
        first = {k: v[0] for k, v in self.vary.items()}
        for entry in self.cases or [{}]:
            self._scenario({**self.scenario, **entry, **first})
            for k, values in self.vary.items():
                for v in values[1:]:
                    self._scenario({**self.scenario, **entry, **first, k: v})
        if not self.param_sets:
            from calib.model.params import default_parameters

            self.param_sets = [ParamSpec("default", None, default_parameters())]

    def _scenario(self, d: dict):
        from optimize.formulations.scenario import DPScenario

        from calib.errors import ScenarioError

        try:
            scen = DPScenario.from_dict(d)
            if self.link:
                from dataclasses import replace

                scen = replace(scen, **{k: getattr(scen, src) for k, src in self.link.items()})
        except ScenarioError as exc:
            if self.source and not self.source.startswith("<") and self.source not in str(exc):
                raise ScenarioError(f"{self.source}: {exc}") from None
            raise
        return scen

    def expand(self) -> list[dict]:
        """The cases: JSON-able dicts with ``case_id``, ``key`` (content key), ``labels`` and what
        :func:`run_case` needs."""
        from calib.store import result_key

        names = list(self.vary)
        combos = list(itertools.product(*(self.vary[n] for n in names))) or [()]
        out = []
        for ps in self.param_sets:
            pdict = ps.pset.to_dict()
            for entry in self.cases or [{}]:
                for combo in combos:
                    scen = self._scenario({**self.scenario, **entry, **dict(zip(names, combo))})
                    sd = _scenario_dict(scen)
                    key = result_key(sorted(self.strategies), params=ps.pset, scenario=sd, grids=self.grids)
                    out.append({"case_id": len(out), "key": key, "study": self.name,
                                "labels": {"params": ps.label, "draw": ps.draw},
                                "scenario": sd, "grids": dict(self.grids), "strategies": list(self.strategies),
                                "params": pdict, "hold_s": float(self.hold_s)})
        return out


def code_version() -> str:
    """The version plus a digest of the ``calib`` and ``optimize`` sources (:func:`calib.store.code_version`)."""
    from calib.store import code_version as _code_version

    return _code_version("calib", "optimize")


def _scenario_dict(scen) -> dict:
    from dataclasses import asdict

    d = asdict(scen)
    return {k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v) for k, v in d.items()}


#: Tables that validation requires to be non-increasing; a Monte-Carlo draw is held to that.
_NON_INCREASING = ("f_cl",)


def montecarlo_draws(artifact, n: int, seed: int = 1, label: str | None = None) -> list[ParamSpec]:
    """``n`` parameter sets drawn from the estimated parameters' normal(value, stderr), clipped to bounds."""
    from calib.errors import ParameterError
    from calib.model.params import ParameterSet

    base = artifact if isinstance(artifact, ParameterSet) else ParameterSet.load(artifact)
    label = label or (Path(artifact).stem if not isinstance(artifact, ParameterSet) else
                      base.meta.get("name", "params"))
    est = [nm for nm in base if base.param(nm).status == "estimated" and base.param(nm).stderr is not None]
    if not est:
        raise ParameterError(f"{label}: no parameter with status 'estimated' and a standard error to draw from "
                             "(use a calibration artifact)")
    out = []
    for i in range(int(n)):
        rng = np.random.default_rng([int(seed), i])
        for _attempt in range(50):
            vals = {}
            for nm in est:
                p = base.param(nm)
                lo, hi = p.bounds
                z = rng.standard_normal()
                if p.is_table:
                    se = np.broadcast_to(np.asarray(p.stderr, dtype=float), (len(p.value),))
                    v = np.clip(np.asarray(p.value, dtype=float) + se * z, lo, hi)
                    if nm in _NON_INCREASING:
                        # the calibration's constraint: an entry drawn above a colder one (f_cl above its
                        # warm reference, whose sd is 0) is held at it, as the fit's estimate would be
                        v = np.minimum.accumulate(v)
                    vals[nm] = v.tolist()
                else:
                    vals[nm] = float(np.clip(p.value + float(p.stderr) * z, lo, hi))
            try:
                ps = base.with_values(**vals)
                break
            except ParameterError:
                continue
        else:
            raise ParameterError(f"{label}: Monte-Carlo draw {i} failed validation 50 times")
        ps.meta["montecarlo"] = {"draw": i, "seed": int(seed)}
        out.append(ParamSpec(f"{label}", i, ps))
    return out


def load_study(path) -> Study:
    """Read a study TOML file (relative parameter paths are relative to the file)."""
    from calib.errors import ScenarioError

    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"study file {path} not found")
    from calib.fileio import read_config

    d = read_config(path, ScenarioError, "study file")
    try:
        return _study_checked(d, path)
    except ScenarioError:
        raise
    except (TypeError, ValueError, AttributeError, OverflowError) as exc:
        # a field of the wrong kind the checks do not name ([params] files not a list, hold_s not a number...)
        raise ScenarioError(f"{path}: a field has the wrong type ({str(exc).splitlines()[0][:120]})") from None


def _study_checked(d, path):
    from calib.errors import IptmError, ScenarioError

    try:
        return study_from_dict(d, base_dir=path.parent, source=str(path), default_name=path.stem)
    except IptmError as exc:  # a scenario field, or a parameter file the study names: the study says which
        if str(path) in str(exc):
            raise
        raise ScenarioError(f"{path}: {exc}") from None


def study_from_dict(d: dict, base_dir=".", source: str = "<dict>", default_name: str = "study") -> Study:
    """A study from the parsed TOML structure (``{"study": {...}, "scenario": {...}, "vary": {...}, ...}``);
    relative parameter paths are relative to ``base_dir``. For callers that build studies in code (the
    dashboard)."""
    from calib.errors import ScenarioError
    from calib.model.params import ParameterSet

    base_dir = Path(base_dir)
    known = {"study", "scenario", "vary", "case", "params", "link"}
    bad = set(d) - known
    if bad:
        raise ScenarioError(f"{source}: unknown table(s) {sorted(bad)}; known: {sorted(known)}")
    st = dict(d.get("study", {}))
    okst = {"name", "strategies", "reference", "grids", "hold_s"}
    if set(st) - okst:
        raise ScenarioError(f"{source}: unknown [study] key(s) {sorted(set(st) - okst)}; known: {sorted(okst)}")
    cases = d.get("case", [])
    if not isinstance(cases, list):
        raise ScenarioError(f"{source}: [[case]] must be an array of tables")
    pr = dict(d.get("params", {}))
    if set(pr) - {"files", "montecarlo"}:
        raise ScenarioError(f"{source}: unknown [params] key(s) {sorted(set(pr) - {'files', 'montecarlo'})}")
    rel = lambda f: (base_dir / f) if not Path(f).is_absolute() else Path(f)  # noqa: E731
    psets = []
    files = pr.get("files", [])
    if isinstance(files, str):
        files = [files]
    for f in files:
        psets.append(ParamSpec(Path(f).stem, None, ParameterSet.load(rel(f))))
    mc = pr.get("montecarlo")
    if mc:
        if "artifact" not in mc:
            raise ScenarioError(f"{source}: [params] montecarlo needs artifact = FILE")
        art = rel(mc["artifact"])
        if mc.get("nominal", False):
            psets.append(ParamSpec(art.stem, None, ParameterSet.load(art)))
        psets.extend(montecarlo_draws(art, int(mc.get("n", 20)), int(mc.get("seed", 1))))
    return Study(name=st.get("name", default_name), strategies=st.get("strategies", ("rule", "thermal")),
                 reference=st.get("reference"), grids=st.get("grids", {}), scenario=d.get("scenario", {}),
                 vary=d.get("vary", {}), cases=cases, param_sets=psets, link=d.get("link", {}),
                 hold_s=float(st.get("hold_s", 0.0)), source=source)


# ---------------------------------------------------------------------------------------------------
# one case
# ---------------------------------------------------------------------------------------------------
def _error_text(exc: BaseException) -> str:
    msg = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {msg[0] if msg else ''}".strip()


def _in_dask_worker() -> bool:
    """True in a dask worker process: in a task, or in a function the client runs there (``Client.run``,
    which ``get_worker`` does not see)."""
    try:
        from distributed import get_worker
        from distributed.worker import Worker
    except ImportError:
        return False
    try:
        get_worker()
        return True
    except ValueError:
        return bool(getattr(Worker, "_instances", ()))


def _agree_numba_threads():
    """Make the environment's ``NUMBA_NUM_THREADS`` agree with numba's thread count.

    numba reads the variable at import and again at every compilation, and refuses (RuntimeError, "Cannot set
    NUMBA_NUM_THREADS...") a count that differs from the one its thread pool started with. A dask nanny sets
    the worker's environment after the worker imported numba (it unpickles the caller's modules first), so
    the two differ there; once the pool runs (a warm-up that ran a parallel kernel), every later compilation
    of the study would fail."""
    from numba.core import config
    from numba.np.ufunc import parallel

    env = os.environ.get("NUMBA_NUM_THREADS")
    if env is None or env.strip() == str(config.NUMBA_NUM_THREADS):
        return
    if not parallel._is_initialized:
        config.reload_config()  # the pool will start with the environment's count
    else:
        # the pool runs with config's count and cannot be resized: the environment follows it (the count
        # this process uses is capped with numba.set_num_threads instead)
        os.environ["NUMBA_NUM_THREADS"] = str(config.NUMBA_NUM_THREADS)


def _limit_threads():
    """numba's environment made consistent in any process; inside a dask worker, numba uses one thread (the
    worker processes are the parallelism). numba's count is per calling thread: this runs in each case."""
    _agree_numba_threads()
    if _in_dask_worker():
        import numba

        numba.set_num_threads(1)


def run_case(case: dict) -> dict:
    """Run every strategy of one case; return a JSON-able record. Never raises: errors are recorded
    (``record["error"]`` for the case, ``record["results"][strategy]["error"]`` per strategy)."""
    t0, c0 = time.perf_counter(), time.process_time()
    rec = {"key": case.get("key"), "results": {}, "error": None, "pid": os.getpid()}
    try:
        _limit_threads()
        if case.get("hold_s"):
            time.sleep(float(case["hold_s"]))
        from calib.model.params import ParameterSet
        from optimize.formulations.scenario import DEFAULT_GRIDS, DPScenario
        from optimize.formulations.solve import solve_formulation
        from optimize.tuning import tune_rule_based

        ps = ParameterSet.from_dict(case["params"])
        scen = DPScenario.from_dict({k: v for k, v in case["scenario"].items() if v is not None})
        grids = DEFAULT_GRIDS.with_steps(**case["grids"])
        cyc = scen.load_cycle()
    except Exception as exc:  # noqa: BLE001 - recorded, the study goes on
        rec["error"] = _error_text(exc)
        rec["elapsed_s"] = time.perf_counter() - t0
        return rec
    errors = []
    for s in case["strategies"]:
        t1 = time.perf_counter()
        try:
            if s == "rule":
                tr = tune_rule_based(ps, cyc, T_amb=scen.T_amb, soc0=scen.soc0, T_cl0=scen.T_cl0,
                                     T_cab0=scen.T_cab0, Q_heat=scen.Q_heat)
                sim = tr.result
                extra = {"rule_n_feasible": tr.n_feasible}
            else:
                o = solve_formulation(s, ps, scen, grids)
                sim = o.on_thermal if s == "baseline" else o.sim
                extra = {}
            summ = sim.summary()
            r = {k: float(summ[k]) for k in _RESULT_FIELDS}
            r["charge_sustaining"] = bool(summ["soc_final"] >= summ["soc_initial"] - scen.soc_tol)
            r.update(extra)
            r["error"] = None
        except Exception as exc:  # noqa: BLE001
            r = {"error": _error_text(exc)}
            errors.append(f"{s}: {r['error']}")
        r["t_s"] = time.perf_counter() - t1
        rec["results"][s] = r
    rec["error"] = "; ".join(errors) or None
    rec["elapsed_s"] = time.perf_counter() - t0
    rec["cpu_s"] = time.process_time() - c0
    return rec


# ---------------------------------------------------------------------------------------------------
# the study on a cluster
# ---------------------------------------------------------------------------------------------------
def local_client(n_workers: int = 2):
    """A ``Client`` on a ``LocalCluster`` of ``n_workers`` single-threaded processes (numba: 1 thread each)."""
    from distributed import Client, LocalCluster

    env = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None,
                           env=env)
    return Client(cluster)


def _valid_record(r) -> bool:
    return isinstance(r, dict) and isinstance(r.get("results"), dict) and "error" in r


def run_study(study, client=None, store_dir=None, progress_callback=None, *, n_workers: int = 2,
              retries: int = 2, retry_failed: bool = False) -> pd.DataFrame:
    """Run a study; return the tidy table (:func:`results_table`).

    Args:
        study: a :class:`Study` or a path to a study TOML.
        client: a ``distributed.Client``, a scheduler address (``"tcp://host:8786"``), or None for a
            ``LocalCluster`` of ``n_workers`` processes (started and closed here). Nothing else changes.
        store_dir: the folder of the content-keyed cache (:class:`calib.store.Store`; default ``IPTM_CACHE_DIR``,
            else ``.iptm-cache``), cases under its ``sweep/``; cases found there are not
            recomputed; each finished case is stored as soon as it arrives (an interrupted study resumes).
        progress_callback: ``f(done, total, record)`` after each case (cached cases first, record None).
        retries: extra attempts per case on top of dask's rescheduling after a worker death.
        retry_failed: recompute cases whose stored record holds an error (errors are stored: an infeasible
            scenario fails the same way every time).
    """
    from calib.store import Store

    if not isinstance(study, Study):
        study = load_study(study)
    cases = study.expand()
    store = Store(store_dir)  # None: the one cache's folder (calib.store.default_root)
    records, todo = {}, {}
    for c in cases:
        if c["key"] in records or c["key"] in todo:
            continue
        r = store.get_json(_KIND, c["key"])
        if _valid_record(r) and not (retry_failed and r.get("error")):
            r["cached"] = True
            records[c["key"]] = r
        else:
            todo[c["key"]] = c
    total = len(records) + len(todo)
    done = len(records)
    if progress_callback and done:
        progress_callback(done, total, None)
    if todo:
        own = None
        if client is None:
            client = own = local_client(n_workers)
        elif isinstance(client, str):
            from distributed import Client

            client = own = Client(client)
        pending = set()
        try:
            from distributed import as_completed

            # a fresh task key per call: tasks cancelled by an interrupted call on the same cluster cannot
            # collide with this call's (the content key names the result, the token the computation)
            token = uuid.uuid4().hex[:8]
            futs = {client.submit(run_case, c, key=f"iptm-sweep-{k}-{token}", pure=False, retries=retries): k
                    for k, c in todo.items()}
            pending = set(futs)
            for fut in as_completed(list(futs)):
                pending.discard(fut)
                k = futs[fut]
                try:
                    rec = fut.result()
                except (Exception, asyncio.CancelledError) as exc:  # noqa: BLE001 - infrastructure failure
                    # (KilledWorker after too many worker deaths, a task cancelled by someone else): not stored
                    rec = {"key": k, "results": {}, "error": _error_text(exc), "infrastructure": True}
                else:
                    store.put_json(_KIND, k, rec)
                rec["cached"] = False
                records[k] = rec
                done += 1
                fut.release()
                if progress_callback:
                    progress_callback(done, total, rec)
        except BaseException:
            # interrupted (Ctrl-C) or broken: stop what is still queued; finished cases are in the store
            try:
                client.cancel(list(pending))
            except Exception:  # noqa: BLE001
                pass
            raise
        finally:
            if own is not None:
                cluster = getattr(own, "cluster", None)
                own.close()
                if cluster is not None:
                    cluster.close()
    df = results_table(cases, records, study.reference)
    df.attrs["study"] = study.name
    return df


def run_sequential(study, progress_callback=None) -> pd.DataFrame:
    """Every case in this process, one after the other, no store (reference for tests and benchmarks)."""
    if not isinstance(study, Study):
        study = load_study(study)
    cases = study.expand()
    records = {}
    for i, c in enumerate(cases):
        if c["key"] not in records:
            records[c["key"]] = run_case(c)
        if progress_callback:
            progress_callback(i + 1, len(cases), records[c["key"]])
    return results_table(cases, records, study.reference)


# ---------------------------------------------------------------------------------------------------
# the table
# ---------------------------------------------------------------------------------------------------
_SCEN_COLS = ("cycle", "T_amb", "soc0", "T_cl0", "T_cab0", "Q_heat", "Q_heat_min", "Q_heat_max", "soc_min",
              "soc_max", "T_cl_min", "T_cl_max", "cab_lb_offset", "T_cab_ub", "duration_s", "soc_tol")
#: Columns of the tidy table (one row per case and strategy).
TABLE_COLUMNS = ("study", "case_id", "case_key", "params", "draw") + _SCEN_COLS + (
    "strategy", "reference", "status", "error") + _RESULT_FIELDS + (
    "charge_sustaining", "saving_pct", "saving_corrected_pct", "t_s", "cached")


def results_table(cases: list, records: dict, reference: str) -> pd.DataFrame:
    """Tidy table: one row per case and strategy; ``saving_pct`` = 100 (1 - fuel / fuel of the
    reference strategy of the same case); ``status`` ok / failed."""
    rows = []
    for c in cases:
        rec = records.get(c["key"]) or {"results": {}, "error": "not run"}
        ref = rec["results"].get(reference) or {}
        for s in c["strategies"]:
            r = rec["results"].get(s) or {}
            err = r.get("error") or (None if r else rec.get("error") or "not run")
            row = {"study": c["study"], "case_id": c["case_id"], "case_key": c["key"],
                   "params": c["labels"]["params"], "draw": c["labels"]["draw"]}
            row.update({k: c["scenario"].get(k) for k in _SCEN_COLS})
            row.update(strategy=s, reference=reference, status="failed" if err else "ok", error=err)
            for k in _RESULT_FIELDS:
                row[k] = r.get(k, np.nan) if not err else np.nan
            row["charge_sustaining"] = r.get("charge_sustaining") if not err else None
            f, fr = row["fuel_g"], ref.get("fuel_g", np.nan) if not ref.get("error") else np.nan
            fc, fcr = row["fuel_corrected_g"], ref.get("fuel_corrected_g", np.nan) if not ref.get("error") else np.nan
            row["saving_pct"] = 100 * (1 - f / fr) if fr and np.isfinite(fr) else np.nan
            row["saving_corrected_pct"] = 100 * (1 - fc / fcr) if fcr and np.isfinite(fcr) else np.nan
            row["t_s"] = r.get("t_s", np.nan)
            row["cached"] = bool(rec.get("cached", False))
            rows.append(row)
    df = pd.DataFrame(rows, columns=list(TABLE_COLUMNS))
    float_cols = [k for k in _SCEN_COLS if k != "cycle"] + list(_RESULT_FIELDS) + ["saving_pct",
                                                                                  "saving_corrected_pct", "t_s"]
    df[float_cols] = df[float_cols].astype(float)
    df["draw"] = df["draw"].astype("Int64")
    df["case_id"] = df["case_id"].astype(int)
    return df


def write_table(df: pd.DataFrame, path) -> Path:
    """Write the table as Parquet, atomically."""
    from calib.fileio import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)
    return path


# ---------------------------------------------------------------------------------------------------
# plots
# ---------------------------------------------------------------------------------------------------


def summary_pivot(df: pd.DataFrame, metric: str = "saving_pct") -> pd.DataFrame:
    """Median ``metric`` per (strategy, cycle) x ambient (for printing)."""
    ok = df[(df["status"] == "ok") & (df["strategy"] != df["reference"])]
    if ok.empty:
        return pd.DataFrame()
    return ok.pivot_table(index=["strategy", "cycle"], columns="T_amb", values=metric, aggfunc="median")


def format_failures(df: pd.DataFrame) -> str:
    """One line per failed case of a study's table: its case, scenario, parameters, strategy and error."""
    bad = df[df["status"] == "failed"]
    return "\n".join(f"case {r.case_id} ({r.cycle}, {r.T_amb:g} degC, {r.params}) {r.strategy}: {r.error}"
                     for r in bad.itertuples())

