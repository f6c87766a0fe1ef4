"""A self-contained HTML report: sections of text, tables and figures (PNG embedded as base64)."""
from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;
padding:0 1em;color:#222;line-height:1.45}
h1{border-bottom:2px solid #444}h2{border-bottom:1px solid #bbb;margin-top:2em}
table{border-collapse:collapse;margin:.8em 0;font-size:.9em}th,td{border:1px solid #ccc;padding:3px 7px;
text-align:right}th{background:#f1f1f1}td:first-child,th:first-child{text-align:left}
img{max-width:100%;border:1px solid #ddd;margin:.5em 0}.synthetic{background:#fff3cd;border:1px solid #e0c060;
padding:.5em 1em;font-weight:600}.note{color:#555;font-size:.9em}code{background:#f4f4f4;padding:0 3px}
nav a{margin-right:1em}.tablewrap{overflow-x:auto;max-width:100%}pre{overflow-x:auto;max-width:100%;
background:#f8f8f8;padding:.5em}p,figcaption{overflow-wrap:anywhere}.warn{background:#fdecea;border:1px solid #e0a0a0;
padding:.4em 1em}
"""


@dataclass
class Section:
    """One report section: an id, a heading and a list of blocks (``("p", text)``, ``("html", raw)``,
    ``("table", DataFrame, caption)``, ``("figure", png_path, caption)``, ``("pre", text)``)."""

    id: str
    title: str
    blocks: list = field(default_factory=list)

    def p(self, text: str):
        self.blocks.append(("p", text))
        return self

    def raw(self, markup: str):
        self.blocks.append(("html", markup))
        return self

    def table(self, df: pd.DataFrame, caption: str = ""):
        self.blocks.append(("table", df, caption))
        return self

    def figure(self, path, caption: str = ""):
        self.blocks.append(("figure", Path(path), caption))
        return self

    def pre(self, text: str):
        self.blocks.append(("pre", text))
        return self


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    return v


def render(title: str, sections: list[Section], banner: str = "", warnings=()) -> str:
    """The page: ``banner`` (the SYNTHETIC-data notice) and each of ``warnings`` (e.g. subsystems left at their
    priors) above everything else, then the sections."""
    out = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
           f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    if banner:
        out.append(f"<p class='synthetic'>{html.escape(banner)}</p>")
    for w in warnings:
        out.append(f"<p class='warn banner'>{html.escape(w)}</p>")
    out.append("<nav>" + "".join(f"<a href='#{s.id}'>{html.escape(s.title)}</a>" for s in sections) + "</nav>")
    for s in sections:
        out.append(f"<h2 id='{s.id}'>{html.escape(s.title)}</h2>")
        for b in s.blocks:
            kind = b[0]
            if kind == "p":
                out.append(f"<p>{html.escape(b[1])}</p>")
            elif kind == "html":
                out.append(b[1])
            elif kind == "pre":
                out.append(f"<pre>{html.escape(b[1])}</pre>")
            elif kind == "table":
                df, cap = b[1], b[2]
                if cap:
                    out.append(f"<p class='note'>{html.escape(cap)}</p>")
                out.append("<div class='tablewrap'>" + df.map(_fmt).to_html(index=False, border=0, na_rep="",
                                                                            escape=True) + "</div>")
            elif kind == "figure":
                data = base64.b64encode(b[1].read_bytes()).decode()
                out.append(f"<figure><img alt='{html.escape(b[2])}' src='data:image/png;base64,{data}'>"
                           f"<figcaption class='note'>{html.escape(b[2])}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)
