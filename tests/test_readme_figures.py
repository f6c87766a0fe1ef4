"""The generated figures of the README and the docs match the committed JSON (nothing is re-run here), the
check notices a figure edited by hand, and no page holds a block that scripts/figures.py does not render."""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("figures", ROOT / "scripts" / "figures.py")
figures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(figures)


def _rendered(name: str, data: dict) -> str:
    """The file ``name`` with its blocks rendered from the JSON, and its renderers."""
    render = figures.FILES[name]
    return figures.render_text((ROOT / name).read_text(), data, render), render


def test_blocks_match_the_json():
    data = figures.load()
    assert "sim" in data, "reports/figures/bench-sim.json missing: run `make figures`"
    assert "mutation" in data, "reports/mutation.json missing: run scripts/mutation.py"
    assert "run" in data, "reports/figures/run.json missing: run `make figures`"
    assert figures.check_all(data) == []


def test_every_block_on_every_page_has_its_renderer():
    """A block moved to a page that scripts/figures.py does not know would never be checked."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    found = {p.relative_to(ROOT).as_posix(): set(figures.blocks(p.read_text())) for p in pages}
    found = {f: b for f, b in found.items() if b and "_build" not in f}
    assert found == {f: set(r) for f, r in figures.FILES.items()}


def test_check_catches_an_edited_figure():
    data = figures.load()
    text, render = _rendered("docs/cold_start.md", data)
    assert figures.check(text, data, render) == []
    us06 = next(r for r in data["sim"]["epa"] if r["cycle"] == "US06")
    old = f"{us06['error_pct']:+.1f} % |"
    block = figures.blocks(text)["epa"]
    assert old in block
    # the edit inside the warm-cycle table only (the same string may appear in another block of the page)
    edited = text.replace(block, block.replace(old, f"{us06['error_pct'] + 0.3:+.1f} % |"))
    assert [b[0] for b in figures.check(edited, data, render)] == ["epa"]
    # a timing quoted without its noise is also caught
    body = figures.blocks(text)["sim-speed"]
    assert [b[0] for b in figures.check(text.replace(body, "about 12 ms"), data, render)] == ["sim-speed"]


def test_check_catches_an_edited_headline():
    data = figures.load()
    text, render = _rendered("README.md", data)
    th = data["run"]["strategies"]["thermal"]
    old = f"**{th['fuel_corrected_g']:.2f}**"
    assert old in figures.blocks(text)["headline"]
    edited = text.replace(old, f"**{th['fuel_corrected_g'] - 1:.2f}**")
    assert [b[0] for b in figures.check(edited, data, render)] == ["headline"]
    # the corrected fuel is the headline column, the raw fuel beside it
    header = figures.blocks(text)["headline"].strip().splitlines()[0]
    assert header.index("corrected fuel") < header.index("fuel g (raw)")


def test_check_catches_an_edited_mutation_score():
    data = figures.load()
    text, render = _rendered("docs/testing.md", data)
    m = data["mutation"]
    old = f"score {100 * m['score']:.1f} %"
    assert old in figures.blocks(text)["mutation"]
    edited = text.replace(old, f"score {100 * m['score'] + 1:.1f} %")
    assert [b[0] for b in figures.check(edited, data, render)] == ["mutation"]


def test_check_catches_an_edited_causal_count():
    data = figures.load()
    assert ("cmap-trip1", "continuation") in data["causal"], "reports/causal-cmap-trip1-continuation.json missing"
    text, render = _rendered("docs/studies/causal.md", data)
    g = data["causal"][("cmap-trip1", "continuation")]["goals"]["ecms"]
    old = f"| cmap-trip1 | continuation | ECMS | {g['within_3pct']}/{g['runs']} |"
    assert old in figures.blocks(text)["causal"]
    edited = text.replace(old, f"| cmap-trip1 | continuation | ECMS | {g['runs']}/{g['runs']} |")
    assert [b[0] for b in figures.check(edited, data, render)] == ["causal"]
