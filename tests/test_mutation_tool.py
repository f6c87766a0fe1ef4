"""The mutation runner's operators (scripts/mutation.py): each mutant differs from the source in exactly the
stated way, docstrings and messages are left alone."""
import ast
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("mutation", ROOT / "scripts" / "mutation.py")
mutation = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mutation)

SRC = '''"""Doc 1."""
__all__ = ["f"]


def f(a, b):
    """Doc 2."""
    if a < b and not b:
        return -a + 2 * b
    x = 0.5
    x += a
    return "message" if a == b else x  # pragma: no mutate
'''


def _mutants():
    return {d: ast.unparse(ast.parse(mutation.mutate(SRC, i))) for i, _ln, d in mutation.sites(SRC)}


def test_operators_and_exclusions():
    m = _mutants()
    # line 11 is excluded by its pragma; docstrings and __all__ are never mutated
    assert sorted(m) == sorted(["compare 0: Lt -> LtE", "And -> Or", "drop unary Not", "Add -> Sub",
                                "drop unary USub", "Mult -> Div", "2 -> 3", "0.5 -> 1.5", "Add= -> Sub="])
    def edited(old, new):
        return ast.unparse(ast.parse(SRC.replace(old, new)))

    assert m["compare 0: Lt -> LtE"] == edited("a < b", "a <= b")
    assert m["drop unary Not"] == edited("not b", "b")
    assert m["drop unary USub"] == edited("-a + 2", "a + 2")
    assert m["Add= -> Sub="] == edited("x += a", "x -= a")
    for text in m.values():
        assert "Doc 1." in text and "Doc 2." in text and "'message'" in text


def test_every_mutant_differs_and_compiles():
    src = (ROOT / "calib" / "ingest" / "resample.py").read_text()
    base = ast.unparse(ast.parse(src))
    seen = set()
    for i, _ln, _d in mutation.sites(src):
        out = mutation.mutate(src, i)
        compile(out, "resample.py", "exec")
        assert out != base
        seen.add(out)
    assert len(seen) == len(mutation.sites(src))


def test_every_argued_equivalent_mutant_still_exists_where_pyproject_says():
    # equivalences are keyed by module, line and mutation: an edit that moves the code must move the entry
    import tomllib

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["iptm"]["mutation"]
    missing = []
    for e in cfg["equivalent"]:
        here = {(ln, d) for _i, ln, d in mutation.sites((ROOT / e["module"]).read_text())}
        if (e["line"], e["mutation"]) not in here:
            missing.append(f'{e["module"]}:{e["line"]} {e["mutation"]}')
    assert not missing, missing


def test_pooled_score_has_the_exact_binomial_interval():
    from scipy.stats import binom

    out = mutation.pooled([{"killed": 29, "survived": 5}, {"killed": 38, "survived": 14}])
    assert (out["killed"], out["scored"]) == (67, 86)
    lo, hi = out["ci95"]
    # Clopper-Pearson: each end is the proportion at which the observed count is just 2.5 % likely
    assert binom.sf(66, 86, lo) == pytest.approx(0.025, abs=1e-4)
    assert binom.cdf(67, 86, hi) == pytest.approx(0.025, abs=1e-4)
    # all killed: the upper end is 1 and the lower end solves p ** n = 0.025
    all_k = mutation.pooled([{"killed": 20, "survived": 0}])
    assert all_k["ci95"] == [pytest.approx(0.025 ** (1 / 20), abs=1e-4), 1.0]
    with pytest.raises(SystemExit, match="no mutant"):
        mutation.pooled([{"killed": 0, "survived": 0}])


def test_weighted_score_weights_each_modules_pooled_score_by_its_mutants():
    # worked by hand: module a (300 mutants) 3+4 killed of 5+5 -> 0.7; module b (100) 5 of 5 -> 1.0;
    # 0.75 * 0.7 + 0.25 * 1.0 = 0.775; variance 0.75^2 * 0.21 / 10 + 0 = 0.0118125
    reps = [{"killed": 8, "survived": 2, "per_module": {"a": {"killed": 3, "survived": 2}, "b": {"killed": 5, "survived": 0}}},
            {"killed": 4, "survived": 1, "per_module": {"a": {"killed": 4, "survived": 1}}}]
    out = mutation.pooled(reps, {"a": 300, "b": 100, "c": 50})
    assert out["score"] == pytest.approx(12 / 15, abs=1e-4)
    w = out["weighted"]
    assert w["score"] == pytest.approx(0.775, abs=1e-4)
    half = 1.96 * 0.0118125 ** 0.5
    assert w["ci95"] == [pytest.approx(0.775 - half, abs=1e-4), pytest.approx(min(0.775 + half, 1.0), abs=1e-4)]
    # a module no sample reached is named, and weighs nothing in the estimate
    assert w["modules_not_sampled"] == ["c"] and w["mutants"] == 400
    assert w["per_module"]["a"] == {"killed": 7, "scored": 10, "score": 0.7, "mutants": 300}


def test_rerun_finds_a_survivor_moved_by_an_edit_elsewhere_and_refuses_a_changed_one():
    """A survivor of an earlier report is re-run where it now is: at its index when nothing moved; on the line
    that reads as its source when lines were added above it (its index and line shift); refused when its
    line changed or reads the same at two places."""
    i, ln, d = next(s for s in mutation.sites(SRC) if s[2] == "0.5 -> 1.5")
    r = dict(index=i, line=ln, mutation=d, source="x = 0.5")
    assert mutation.relocate(r, SRC) == (i, ln)
    moved = SRC.replace('    """Doc 2."""\n', '    """Doc 2."""\n    y = 3 * a\n    z = y - 1\n')
    j, ln2 = mutation.relocate(r, moved)
    assert ln2 == ln + 2 and j != i
    out = mutation.mutate(moved, j)
    assert "x = 1.5" in out and "x = 0.5" not in out and "y = 3 * a" in out
    assert mutation.relocate(r, SRC.replace("x = 0.5", "x = 0.25")) is None
    assert mutation.relocate(r, moved.replace("    x += a\n", "    x += a\n    x = 0.5\n")) is None


def test_reclassify_judges_an_earlier_report_by_todays_equivalents_where_the_code_now_is():
    """A survivor recorded at line 7 of SRC, after an edit that moved that line to 8, is equivalent when
    pyproject lists it at line 8, and a survivor otherwise; a killed mutant stays killed; one whose line no
    longer reads as recorded keeps its recorded status."""
    sites = mutation.sites(SRC)
    i, ln, d = next((i, ln, d) for i, ln, d in sites if ln == 7)
    src_line = SRC.splitlines()[ln - 1].strip()
    surv = {"module": "m.py", "index": i, "line": ln, "mutation": d, "status": "survived", "source": src_line}
    killed = dict(surv, status="killed")
    moved = "# one line more\n" + SRC
    listed = {"equivalent": [{"module": "m.py", "line": ln + 1, "mutation": d, "reason": "r"}]}
    out = mutation.reclassify([surv, killed], listed, lambda m: moved)
    assert [r["status"] for r in out] == ["equivalent", "killed"] and out[0]["line"] == ln + 1
    assert mutation.reclassify([surv], {"equivalent": []}, lambda m: moved)[0]["status"] == "survived"
    gone = moved.replace(src_line, src_line + "  # edited")  # moved and edited: not found, though listed
    assert mutation.reclassify([surv], listed, lambda m: gone)[0] == surv



def test_rerun_tells_apart_two_equal_mutations_of_one_line_by_the_source_the_report_was_made_in():
    """``a - 1`` and ``max(..., 1)`` on one line both mutate as ``1 -> 2``: after a line added above renumbers
    the mutants (1 and 2 become 4 and 6), the line alone cannot say which one survived; the module's source at
    the report's commit can (the mutations of a line keep their order), and each relocates to its own
    constant."""
    src = "def f(a):\n    return max(a - 1, 1)\n"
    moved = "def f(a):\n    b = 2.0 * a - 3\n    return max(a - 1, 1)\n"
    ones = sorted(i for i, ln, d in mutation.sites(src) if d == "1 -> 2")
    assert len(ones) == 2
    for i in ones:
        r = dict(index=i, line=2, mutation="1 -> 2", source="return max(a - 1, 1)")
        assert mutation.relocate(r, moved) is None
        j, ln = mutation.relocate(r, moved, src)
        assert ln == 3 and j != i
        assert mutation.mutate(moved, j).splitlines()[2] == mutation.mutate(src, i).splitlines()[1]
