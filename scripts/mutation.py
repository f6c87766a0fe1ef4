"""Mutation testing of the core modules: one small change at a time, in a scratch copy, against the tests
that should notice it.

Why not mutmut or cosmic-ray: mutmut 3 swaps each function for a "trampoline" and skips every decorated
function, which is every ``@njit`` function (the model equations, the DP kernels, the replay loops): the
core would not be mutated at all. cosmic-ray does mutate them (it writes each mutant into the source file on
disk and puts the original back afterwards), but a session has one test command and one environment, while
each module here needs its own tests and numba mode (below), and its mutants would be written into the
checkout being worked on. Here a mutant is the module's source with one AST node changed, written into a
scratch copy of the repository; the selected tests run there in a fresh process.

Numba: a cached kernel in another file inlines the *old* version of a mutated compiled function, so a
module with compiled code runs either with ``NUMBA_DISABLE_JIT=1`` (plain Python: no compilation, no cache)
or compiled with an empty numba cache per mutant (``jit = "fresh"``, for the DP kernels, too slow as plain
Python). A module without compiled code of its own (a fitter, the DP engine's Python side), or whose
compiled code no compiled function of another file calls (the fused DP kernels), runs compiled with a cache
shared by all its mutants (``jit = "shared"``): numba checks a cached function against its own source
file's time stamp and size, so the mutated file is compiled again and only callers elsewhere could be stale.
Set per module in ``[tool.iptm.mutation]`` of pyproject.toml, with ``boundscheck = true`` where a mutant could
write past an array's end (numba does not check indices by default: such a write is undefined behaviour
that a test may not notice; with the check it raises).

Operators (as mutmut's numeric ones): ``+ <-> -``, ``* <-> /``, ``** -> *``, ``//, % -> /``; comparison
boundaries ``< <-> <=``, ``> <-> >=``, ``== <-> !=``, ``in <-> not in``, ``is <-> is not``; ``and <-> or``;
unary ``-x -> x``, ``not x -> x``; number constants ``n -> n + 1``; ``True <-> False``; augmented
assignments ``+= <-> -=``, ``*= <-> /=``. Strings (messages) are not mutated; nor are docstrings, ``__all__``
or lines marked ``# pragma: no mutate``.

Usage::

    python scripts/mutation.py [--module calib/units.py ...] [--sample N] [--seed S] [--out FILE]
                               [--time-limit SECONDS] [--jobs J]

Writes a JSON report (score, every mutant's outcome, the survivors with their source line) and prints a
summary. A mutant is *killed* when the tests fail or time out (a timeout is counted and listed apart).
"""
from __future__ import annotations

import argparse
import ast
import functools
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

try:
    import tomllib
except ImportError:  # pragma: no cover - python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
COPY = ("calib", "optimize", "iptm", "tests", "pyproject.toml", "logs", "studies")

BINOP = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult, ast.Pow: ast.Mult,
         ast.FloorDiv: ast.Div, ast.Mod: ast.Div}
CMPOP = {ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq,
         ast.NotEq: ast.Eq, ast.In: ast.NotIn, ast.NotIn: ast.In, ast.Is: ast.IsNot, ast.IsNot: ast.Is}
BOOLOP = {ast.And: ast.Or, ast.Or: ast.And}


def _skip_lines(src: str) -> set:
    return {i + 1 for i, line in enumerate(src.splitlines()) if "pragma: no mutate" in line}


def _docstring_nodes(tree) -> set:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def _excluded_ids(tree) -> set:
    """Nodes not mutated: ``__all__`` assignments, annotations, decorators (executed at import)."""
    out = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            out.update(id(n) for n in ast.walk(node))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for d in node.decorator_list:
                out.update(id(n) for n in ast.walk(d))
            if node.returns is not None:
                out.update(id(n) for n in ast.walk(node.returns))
            for a in node.args.args + node.args.kwonlyargs + node.args.posonlyargs:
                if a.annotation is not None:
                    out.update(id(n) for n in ast.walk(a.annotation))
        if isinstance(node, ast.AnnAssign):
            out.update(id(n) for n in ast.walk(node.annotation))
    return out


def sites(src: str):
    """Every mutation of a module's source: list of (index, lineno, description)."""
    tree = ast.parse(src)
    skip_l, docs, excl = _skip_lines(src), _docstring_nodes(tree), _excluded_ids(tree)
    out = []
    for node in ast.walk(tree):
        if id(node) in excl or getattr(node, "lineno", None) in skip_l:
            continue
        for desc in _node_mutations(node, docs):
            out.append((getattr(node, "lineno", 0), desc))
    return [(i, ln, d) for i, (ln, d) in enumerate(out)]


def _node_mutations(node, docs):
    if isinstance(node, ast.BinOp) and type(node.op) in BINOP:
        yield f"{type(node.op).__name__} -> {BINOP[type(node.op)].__name__}"
    elif isinstance(node, ast.AugAssign) and type(node.op) in (ast.Add, ast.Sub, ast.Mult, ast.Div):
        yield f"{type(node.op).__name__}= -> {BINOP[type(node.op)].__name__}="
    elif isinstance(node, ast.Compare):
        for j, op in enumerate(node.ops):
            if type(op) in CMPOP:
                yield f"compare {j}: {type(op).__name__} -> {CMPOP[type(op)].__name__}"
    elif isinstance(node, ast.BoolOp):
        yield f"{type(node.op).__name__} -> {BOOLOP[type(node.op)].__name__}"
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.Not)):
        yield f"drop unary {type(node.op).__name__}"
    elif isinstance(node, ast.Constant) and id(node) not in docs:
        if isinstance(node.value, bool):
            yield f"{node.value} -> {not node.value}"
        elif isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            yield f"{node.value!r} -> {node.value + 1!r}"


def mutate(src: str, index: int) -> str:
    """The source with mutation ``index`` (as numbered by :func:`sites`) applied."""
    tree = ast.parse(src)
    skip_l, docs, excl = _skip_lines(src), _docstring_nodes(tree), _excluded_ids(tree)
    k = 0
    for node in ast.walk(tree):
        if id(node) in excl or getattr(node, "lineno", None) in skip_l:
            continue
        for j, _desc in enumerate(list(_node_mutations(node, docs))):
            if k == index:
                if isinstance(node, ast.UnaryOp):  # drop the operator: put the operand in its place
                    _replace(tree, node, node.operand)
                else:
                    _apply(node, j)
                return ast.unparse(ast.fix_missing_locations(tree))
            k += 1
    raise IndexError(index)


def _apply(node, j):
    if isinstance(node, ast.BinOp):
        node.op = BINOP[type(node.op)]()
    elif isinstance(node, ast.AugAssign):
        node.op = BINOP[type(node.op)]()
    elif isinstance(node, ast.Compare):
        idx = [i for i, op in enumerate(node.ops) if type(op) in CMPOP][j]
        node.ops[idx] = CMPOP[type(node.ops[idx])]()
    elif isinstance(node, ast.BoolOp):
        node.op = BOOLOP[type(node.op)]()
    elif isinstance(node, ast.Constant):
        node.value = (not node.value) if isinstance(node.value, bool) else node.value + 1


def _replace(tree, old, new):
    for parent in ast.walk(tree):
        for field, value in ast.iter_fields(parent):
            if value is old:
                setattr(parent, field, new)
                return
            if isinstance(value, list):
                for i, v in enumerate(value):
                    if v is old:
                        value[i] = new
                        return
    raise ValueError("node not found")


def relocate(r: dict, src: str, old_src: str | None = None):
    """(index, line) of an earlier report's mutant ``r`` in the module's current source ``src``: at its index
    when that is still the same mutation at the same line, else the one site with the same mutation on a
    line reading as ``r["source"]`` (moved by an edit elsewhere in the module). Where that line holds the
    same mutation more than once (``x - 1`` and ``max(..., 1)``), the module's source when the report was
    made, ``old_src``, tells which: the mutations of one line keep their order. None when there is no such
    site, or more than one and no ``old_src`` to choose."""
    ss = {i: (ln, d) for i, ln, d in sites(src)}
    if ss.get(r["index"]) == (r["line"], r["mutation"]):
        return r["index"], r["line"]
    lines = src.splitlines()
    cand = [(i, ln) for i, (ln, d) in ss.items() if d == r["mutation"] and ln and lines[ln - 1].strip() == r.get("source")]
    if len(cand) == 1:
        return cand[0]
    if len(cand) < 2 or old_src is None or len({ln for _, ln in cand}) != 1:
        return None
    old = sorted(i for i, ln, d in sites(old_src) if ln == r["line"] and d == r["mutation"])
    if r["index"] not in old or len(old) != len(cand):
        return None
    return sorted(cand)[old.index(r["index"])]


def _clean_head() -> str | None:
    """HEAD's commit when the modules under test are as committed (so a report can name the source its
    mutants were numbered in), else None."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--", *config()["modules"]], cwd=ROOT,
                               capture_output=True, text=True)
    except OSError:  # no git here
        return None
    return head.stdout.strip() if head.returncode == 0 and dirty.returncode == 0 and not dirty.stdout.strip() else None


@functools.lru_cache(maxsize=None)
def source_at(commit: str | None, module: str) -> str | None:
    """A module's source at ``commit`` (the one a report was made at), or None; read once per pair."""
    if not commit:
        return None
    try:
        out = subprocess.run(["git", "show", f"{commit}:{module}"], cwd=ROOT, capture_output=True, text=True)
    except OSError:
        return None
    return out.stdout if out.returncode == 0 else None


def reclassify(mutants, cfg, read_source, commit=None) -> list:
    """An earlier report's mutants judged by today's list of equivalents: each survivor (or earlier
    equivalent) is found in its module's current source (:func:`relocate`, ``read_source(module)``) and is
    equivalent if pyproject lists it at that line, a survivor otherwise; one no longer found keeps its
    recorded status. Killed mutants stay killed: the tests are not re-run. ``commit``: the one the report's
    survivors were numbered at (see :func:`relocate`)."""
    equiv = {(e["module"], e["line"], e["mutation"]) for e in cfg.get("equivalent", [])}
    srcs, out = {}, []
    for r in mutants:
        if r["status"] not in ("survived", "equivalent"):
            out.append(r)
            continue
        if r["module"] not in srcs:
            srcs[r["module"]] = read_source(r["module"])
        at = relocate(r, srcs[r["module"]], source_at(commit, r["module"]))
        if at is None:
            out.append(r)
            continue
        eq = (r["module"], at[1], r["mutation"]) in equiv
        out.append(dict(r, index=at[0], line=at[1], status="equivalent" if eq else "survived"))
    return out


def rejudge(report: dict, cfg, read_source) -> dict:
    """``report`` summarised again with today's equivalents (:func:`reclassify`); no test is run."""
    muts = reclassify(report["mutants"], cfg, read_source, report.get("commit"))
    out = summarise(muts, muts, {})
    out.update({k: report[k] for k in ("seed", "sample", "wall_s") if k in report})
    out["planned"] = report.get("planned", len(muts))
    return out


def config() -> dict:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return data["tool"]["iptm"]["mutation"]


def _scratch() -> Path:
    d = Path(tempfile.mkdtemp(prefix="iptm-mut-"))
    for name in COPY:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, d / name, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
        elif src.exists():
            shutil.copy2(src, d / name)
    return d


def _run_tests(work: Path, tests: list, jit, timeout: float, boundscheck: bool = False):
    """jit: False -> NUMBA_DISABLE_JIT=1; "fresh" -> compiled, empty numba cache; "shared" -> compiled with the
    scratch copy's persistent cache (only for modules without compiled code of their own). ``boundscheck``:
    compiled with numba's index checks (NUMBA_BOUNDSCHECK=1), so that a write past an array's end raises
    instead of passing unseen."""
    env = dict(os.environ, PYTHONPATH=str(work), MPLBACKEND="Agg", PYTHONDONTWRITEBYTECODE="1")
    env.pop("NUMBA_DISABLE_JIT", None)
    env.pop("NUMBA_BOUNDSCHECK", None)
    if boundscheck:
        env["NUMBA_BOUNDSCHECK"] = "1"
    cache = None
    if jit == "shared":
        env["NUMBA_CACHE_DIR"] = str(work / ".numba-cache")
    elif jit:
        cache = tempfile.mkdtemp(prefix="iptm-mut-nb-")
        env["NUMBA_CACHE_DIR"] = cache
    else:
        env["NUMBA_DISABLE_JIT"] = "1"
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-m", "not slow and not browser",
           "-o", "addopts=", *tests]
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=timeout)
        status = "survived" if r.returncode == 0 else ("killed" if r.returncode == 1 else f"error rc={r.returncode}")
        tail = (r.stdout + r.stderr)[-600:]
    except subprocess.TimeoutExpired:
        status, tail = "timeout", ""
    finally:
        if cache:
            shutil.rmtree(cache, ignore_errors=True)
    return status, time.perf_counter() - t0, tail


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--module", action="append", help="module path(s) from [tool.iptm.mutation] (default: all)")
    ap.add_argument("--sample", type=int, default=0, help="at most N mutants per module, drawn with --seed")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="reports/mutation.json")
    ap.add_argument("--time-limit", type=float, default=0.0, help="stop starting new mutants after this many s")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--list", action="store_true", help="only list the mutants")
    ap.add_argument("--rerun", metavar="JSON", help="run again only the survivors of an earlier report (after "
                                                     "adding tests); the report merges the two runs")
    ap.add_argument("--resummarise", metavar="JSON", help="recompute a report's score with the current list of "
                                                           "equivalent mutants (no test is run)")
    ap.add_argument("--pool", nargs="+", metavar="JSON", help="pooled score of several reports (first passes of "
                                                                "different seeds) with its 95 %% interval; no test is run")
    ap.add_argument("--current-equivalents", action="store_true",
                    help="with --pool: judge each report's survivors by today's list of equivalent mutants "
                         "(found in the current source; killed ones stay killed, no test is run)")
    a = ap.parse_args(argv)
    def read(m):
        return (ROOT / m).read_text()

    if a.pool:
        cfg = config()
        sizes = {m: len(sites(read(m))) for m in cfg["modules"]}
        reports = [json.loads(Path(f).read_text()) for f in a.pool]
        if a.current_equivalents:
            reports = [rejudge(r, cfg, read) for r in reports]
        print(json.dumps(pooled(reports, sizes), indent=1))
        return 0
    cfg = config()
    if a.resummarise:
        report = rejudge(json.loads(Path(a.resummarise).read_text()), cfg, read)
        Path(a.out).write_text(json.dumps(report, indent=1))
        print(json.dumps({k: v for k, v in report.items() if k not in ("mutants", "survivors")}, indent=1))
        return 0
    mods = a.module or list(cfg["modules"])
    plan = []
    earlier = []
    earlier_report = {}
    if a.rerun:
        earlier_report = json.loads(Path(a.rerun).read_text())
        earlier = earlier_report["mutants"]
        surv = [r for r in earlier if r["status"] in ("survived", "equivalent")]
        for r in surv:
            at = relocate(r, (ROOT / r["module"]).read_text(), source_at(earlier_report.get("commit"), r["module"]))
            if at is None:
                raise SystemExit(f"{r['module']}:{r['line']} {r['mutation']} changed since {a.rerun}; run the full "
                                 "sample again")
            if at != (r["index"], r["line"]):
                print(f"{r['module']}:{r['line']} {r['mutation']} is now at line {at[1]}", flush=True)
            r["index"], r["line"] = at
        if a.module:
            surv = [r for r in surv if r["module"] in a.module]
        plan = [(r["module"], r["index"], r["line"], r["mutation"]) for r in surv]
        mods = sorted({p[0] for p in plan})
        earlier = [r for r in earlier if r not in surv]
    for m in ([] if a.rerun else mods):
        mc = cfg["modules"][m]
        src = (ROOT / m).read_text()
        ss = sites(src)
        if a.sample and len(ss) > a.sample:
            ss = sorted(random.Random(f"{a.seed}:{m}").sample(ss, a.sample))
        plan += [(m, i, ln, d) for i, ln, d in ss]
        print(f"{m}: {len(sites(src))} mutants, {len(ss)} to run; tests {' '.join(mc['tests'])}", flush=True)
    if a.rerun:
        print(f"re-running {len(plan)} survivors of {a.rerun}", flush=True)
    if a.list:
        for m, i, ln, d in plan:
            print(f"{m}:{ln}  #{i}  {d}")
        return 0
    commit = _clean_head()
    t_start = time.perf_counter()
    # the sources as they are now: a module edited in the checkout during the run (hours) changes no mutant
    snap = {m: (ROOT / m).read_text() for m in mods}
    works = [_scratch() for _ in range(a.jobs)]
    results = []
    try:
        # baselines: the unmutated (unparsed) sources must pass, and give each module's test time
        base_t = {}
        for m in mods:
            mc = cfg["modules"][m]
            w = works[0]
            (w / m).write_text(ast.unparse(ast.parse(snap[m])))
            st, dt, tail = _run_tests(w, mc["tests"], mc.get("jit", False), 1800, mc.get("boundscheck", False))
            (w / m).write_text(snap[m])
            print(f"baseline {m}: {st} in {dt:.0f} s", flush=True)
            if st != "survived":
                print(tail)
                print(f"SKIPPED {m}: its tests fail on the unmutated source; fix them first", flush=True)
                continue
            base_t[m] = dt
        # round-robin over modules, so that a time limit still leaves every module sampled
        queues = [[x for x in plan if x[0] == m] for m in mods if m in base_t]
        todo = [q[i] for i in range(max(map(len, queues), default=0)) for q in queues if i < len(q)]
        lock_free = list(works)

        def one(item):
            m, i, ln, d = item
            if a.time_limit and time.perf_counter() - t_start > a.time_limit:
                return None
            w = lock_free.pop()
            try:
                mc = cfg["modules"][m]
                orig = snap[m]
                try:
                    (w / m).write_text(mutate(orig, i))
                except Exception as exc:  # an AST change that does not unparse: not a mutant
                    return dict(module=m, index=i, line=ln, mutation=d, status=f"invalid: {exc}")
                st, dt, tail = _run_tests(w, mc["tests"], mc.get("jit", False), max(60.0, 4 * base_t[m]),
                                          mc.get("boundscheck", False))
                (w / m).write_text(orig)
                src_line = orig.splitlines()[ln - 1].strip() if ln else ""
                r = dict(module=m, index=i, line=ln, mutation=d, status=st, seconds=round(dt, 1), source=src_line)
                print(f"{st:9s} {m}:{ln} {d}  ({dt:.0f} s)  {src_line[:80]}", flush=True)
                return r
            finally:
                lock_free.append(w)

        with ThreadPoolExecutor(a.jobs) as ex:
            for r in ex.map(one, todo):
                if r is not None:
                    results.append(r)
    finally:
        for w in works:
            shutil.rmtree(w, ignore_errors=True)
    report = summarise(earlier + results, plan, cfg)
    report.update(seed=a.seed, sample=a.sample, wall_s=round(time.perf_counter() - t_start))
    if commit:  # the survivors' indices and lines are those of this commit's source
        report["commit"] = commit
    if a.rerun:  # the merged report describes the earlier run's sample, plus the time of this re-run
        report.update({k: earlier_report[k] for k in ("seed", "sample", "planned", "wall_s") if k in earlier_report})
        report["rerun_wall_s"] = round(time.perf_counter() - t_start)
    out = ROOT / a.out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(report, indent=1))
    tmp.replace(out)
    print(json.dumps({k: v for k, v in report.items() if k not in ("mutants", "survivors")}, indent=1))
    for s in report["survivors"]:
        print(f"SURVIVED {s['module']}:{s['line']} {s['mutation']}  {s['source'][:90]}")
    return 0


def pooled(reports, sizes: dict | None = None) -> dict:
    """Killed / scored mutants over several reports as they were recorded, with the exact (Clopper-Pearson)
    95 % interval of a binomial proportion: the mutants of a seeded sample are a random draw from all."""
    from scipy.stats import beta

    k = sum(r["killed"] for r in reports)
    n = k + sum(r["survived"] for r in reports)
    if n == 0:
        raise SystemExit("--pool: the reports score no mutant")
    lo = float(beta.ppf(0.025, k, n - k + 1)) if k > 0 else 0.0
    hi = float(beta.ppf(0.975, k + 1, n - k)) if k < n else 1.0
    out = {"killed": k, "scored": n, "score": round(k / n, 4), "ci95": [round(lo, 4), round(hi, 4)],
           "seeds": [r.get("seed") for r in reports]}
    if sizes:
        out["weighted"] = stratified(reports, sizes)
    return out


def stratified(reports, sizes: dict) -> dict:
    """Score of all mutants estimated from per-module samples: each module's pooled score weighted by its
    number of mutants (``sizes``), with a normal-approximation 95 % interval of the stratified mean. Every
    sample draws the same number per module, so the plain pooled score weights a small module as much as a
    large one; this is the estimate of the score a full run would give."""
    per = {}
    for r in reports:
        for m, d in r.get("per_module", {}).items():
            a = per.setdefault(m, [0, 0])
            a[0] += d["killed"]
            a[1] += d["killed"] + d["survived"]
    missing = sorted(set(sizes) - {m for m, (_, n) in per.items() if n})
    tot = sum(sizes[m] for m in per if m in sizes and per[m][1])
    est = var = 0.0
    mods = {}
    for m, (k, n) in sorted(per.items()):
        if m not in sizes or n == 0:
            continue
        p, w = k / n, sizes[m] / tot
        est += w * p
        var += w * w * p * (1.0 - p) / n
        mods[m] = {"killed": k, "scored": n, "score": round(p, 3), "mutants": sizes[m]}
    half = 1.96 * var ** 0.5
    return {"score": round(est, 4), "ci95": [round(max(est - half, 0.0), 4), round(min(est + half, 1.0), 4)],
            "mutants": tot, "modules_not_sampled": missing, "per_module": mods}


def summarise(results, plan, cfg) -> dict:
    """Score = killed / (run - equivalent); equivalent mutants are listed in pyproject with a reason."""
    equiv = {(e["module"], e["line"], e["mutation"]): e["reason"] for e in cfg.get("equivalent", [])}
    run = [r for r in results if not r["status"].startswith("invalid")]
    for r in run:
        key = (r["module"], r["line"], r["mutation"])
        if r["status"] == "survived" and key in equiv:
            r["status"] = "equivalent"
            r["reason"] = equiv[key]
    killed = [r for r in run if r["status"] in ("killed", "timeout") or r["status"].startswith("error")]
    surv = [r for r in run if r["status"] == "survived"]
    eqv = [r for r in run if r["status"] == "equivalent"]
    per = {}
    for r in run:
        d = per.setdefault(r["module"], {"killed": 0, "survived": 0, "equivalent": 0})
        key = "killed" if r in killed else r["status"]
        d[key] += 1
    for d in per.values():
        n = d["killed"] + d["survived"]
        d["score"] = round(d["killed"] / n, 3) if n else None
    n = len(killed) + len(surv)
    return {"score": round(len(killed) / n, 4) if n else None, "killed": len(killed), "survived": len(surv),
            "equivalent": len(eqv), "timeouts": sum(r["status"] == "timeout" for r in run),
            "planned": len(plan), "run": len(run), "per_module": per, "survivors": surv, "mutants": results}


if __name__ == "__main__":
    sys.exit(main())
