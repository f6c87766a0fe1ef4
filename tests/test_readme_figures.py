"""The README's generated figures match the committed benchmark JSON (no benchmark is re-run here), and the
check notices a figure edited by hand."""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("figures", ROOT / "scripts" / "figures.py")
figures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(figures)


def test_readme_blocks_match_the_benchmark_json():
    data = figures.load()
    assert "sim" in data, "reports/figures/bench-sim.json missing: run `make figures`"
    assert "mutation" in data, "reports/mutation.json missing: run scripts/mutation.py"
    assert figures.check(figures.README.read_text(), data) == []
    assert figures.check(figures.DOCS.read_text(), data, figures.DOC_RENDER) == []
    assert "epa" in data, "reports/figures/bench-epa.json missing: run `make figures`"
    assert figures.check(figures.COLD_DOC.read_text(), data, figures.COLD_RENDER) == []


def test_check_catches_an_edited_figure():
    data = figures.load()
    text = figures.render_readme(figures.README.read_text(), data)
    assert figures.check(text, data) == []
    us06 = next(r for r in data["sim"]["epa"] if r["cycle"] == "US06")
    old = f"{us06['error_pct']:+.1f} % |"
    assert old in text
    edited = text.replace(old, f"{us06['error_pct'] + 0.3:+.1f} % |")
    assert [b[0] for b in figures.check(edited, data)] == ["epa"]
    # a timing quoted without its noise is also caught
    body = figures.blocks(text)["sim-speed"]
    assert [b[0] for b in figures.check(text.replace(body, "about 12 ms"), data)] == ["sim-speed"]


def test_check_catches_an_edited_mutation_score():
    data = figures.load()
    text = figures.render_readme(figures.README.read_text(), data)
    m = data["mutation"]
    old = f"score {100 * m['score']:.1f} %"
    assert old in figures.blocks(text)["mutation"]
    edited = text.replace(old, f"score {100 * m['score'] + 1:.1f} %")
    assert [b[0] for b in figures.check(edited, data)] == ["mutation"]


def test_check_catches_an_edited_causal_count():
    data = figures.load()
    assert ("fresh", "continuation") in data["causal"], "reports/causal-fresh-continuation.json missing"
    text = figures.render_readme(figures.README.read_text(), data)
    g = data["causal"][("fresh", "continuation")]["goals"]["ecms"]
    old = f"| fresh | continuation | ECMS | {g['within_3pct']}/{g['runs']} |"
    assert old in figures.blocks(text)["causal"]
    edited = text.replace(old, f"| fresh | continuation | ECMS | {g['runs']}/{g['runs']} |")
    assert [b[0] for b in figures.check(edited, data)] == ["causal"]
