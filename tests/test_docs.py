"""The README is a front page (short, the two commands, links that resolve) and the documentation site
builds from docs/ and the docstrings with warnings as errors (what `make docs` runs)."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README, *sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)]

#: [text](target) and ![alt](target), outside code
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE = re.compile(r"`[^`\n]+`")


def relative_links(page: Path) -> list[str]:
    """Links to files of the repository (``page.md``, ``page.md#section``, ``#section``), not to the web."""
    text = CODE.sub("", FENCE.sub("", page.read_text()))
    return [t for t in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def anchors(page: Path) -> set[str]:
    """The section anchors GitHub and myst (``myst_heading_anchors``) give a page's headings."""
    out = set()
    for h in re.findall(r"^#{1,6} +(.+?) *$", FENCE.sub("", page.read_text()), re.M):
        slug = re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
        out |= {slug} | {f"{slug}-{i}" for i in range(1, 4)}  # a repeated heading gets -1, -2, ...
    return out


def test_link_pattern_finds_links_and_skips_code(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("[a](x.md) ![b](img/y.png) [c](https://e.org) [d](#here) `[e](no.md)`\n"
                    "```\n[f](no2.md)\n```\n[g](z.md#sec)\n")
    assert relative_links(page) == ["x.md", "img/y.png", "#here", "z.md#sec"]
    page.write_text("# A title\n## 8. What `calib.fit` does (s.2)\n```\n# not a heading\n```\n")
    assert {"a-title", "8-what-calibfit-does-s2"} <= anchors(page) and "not-a-heading" not in anchors(page)


def test_readme_is_a_front_page():
    n = len(README.read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines; move detail into a page under docs/ and link it"


def test_readme_keeps_the_two_commands():
    text = README.read_text()
    block = text.split("## The two commands", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```sh\n(.*?)```", block, re.S).group(1)
    assert [line.split("#")[0].strip() for line in code.strip().splitlines()] == ["make run", "make test"]
    targets = re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M)
    assert {"run", "test", "docs"} <= set(targets)


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_relative_links_resolve(page):
    missing, no_section = [], []
    for link in relative_links(page):
        path, _, section = link.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            missing.append(link)
        elif section and target.suffix == ".md" and section not in anchors(target):
            no_section.append(link)
    assert not missing, f"{page.relative_to(ROOT)}: links to files that do not exist: {missing}"
    assert not no_section, f"{page.relative_to(ROOT)}: links to sections that do not exist: {no_section}"


def test_docs_build_without_warnings(tmp_path):
    """`make docs`: every page in a toctree, every cross-reference resolved, every docstring valid reST."""
    if shutil.which("sphinx-build", path=str(Path(sys.executable).parent)) is None:
        pytest.fail("Sphinx is not installed in this environment: pip install -e '.[docs]' (see docs/install.md)")
    out = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                          "-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")],
                         cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, f"sphinx-build reported:\n{out.stderr[-6000:]}"
    assert (tmp_path / "html" / "index.html").exists()
    assert (tmp_path / "html" / "api" / "calib.html").read_text().count("calib.read_log") > 0
