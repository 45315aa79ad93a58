"""One HTML page that opens offline: figures (embedded PNG), metric tables, dataset and model cards, and the
papers' numbers beside ours.

    page = Report("vslab — twin run of 2026-11-23")
    page.section("Experiment 2", text="…", figures=[png], tables={"error (mm)": df}, cards={"model": card})
    page.write(lab.report / "index.html")  # lab: a pipeline.lab.Lab

Everything is inlined (images as data URIs, no scripts, no fonts fetched): the file can be mailed or archived.
"""

from __future__ import annotations

import base64
import html
import json
import os
import posixpath
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd

from pipeline.lab import LabPath, is_local

STYLE = """
body { font: 15px/1.45 system-ui, sans-serif; max-width: 1100px; margin: 2em auto; padding: 0 1em; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 2em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { font-size: .9em; color: #555; }
table { border-collapse: collapse; margin: .6em 0 1.2em; font-size: .9em; }
th, td { border: 1px solid #ddd; padding: .25em .6em; text-align: right; } th { background: #f4f4f4; }
td:first-child, th:first-child { text-align: left; }
details { margin: .4em 0; } pre { background: #f7f7f7; padding: .6em; overflow-x: auto; font-size: .85em; }
.meta { color: #666; font-size: .9em; }
"""


@dataclass
class Section:
    title: str
    text: str = ""
    figures: list[Path] = field(default_factory=list)
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    cards: dict[str, dict] = field(default_factory=dict)


@dataclass
class Report:
    title: str
    sections: list[Section] = field(default_factory=list)

    def section(self, title: str, **content) -> Section:
        self.sections.append(Section(title, **content))
        return self.sections[-1]

    def html(self, base: Path | None = None) -> str:
        """The page; links (the PDFs beside the PNGs) are relative to ``base``, the page's folder."""
        created = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        body = [f"<h1>{html.escape(self.title)}</h1>", f'<p class="meta">written {created}</p>']
        body += ['<nav><ul>'] + [
            f'<li><a href="#s{k}">{html.escape(s.title)}</a></li>' for k, s in enumerate(self.sections)
        ] + ["</ul></nav>"]  # fmt: skip
        for k, s in enumerate(self.sections):
            body.append(f'<h2 id="s{k}">{html.escape(s.title)}</h2>')
            if s.text:
                body += [f"<p>{html.escape(p)}</p>" for p in s.text.strip().split("\n\n")]
            for name, table in s.tables.items():
                body.append(f"<h3>{html.escape(name)}</h3>")
                body.append(_table(table))
            for png in s.figures:
                body.append(_figure(png, base))
            for name, card in s.cards.items():
                pretty = html.escape(json.dumps(card, indent=1, default=str))
                body.append(f"<details><summary>{html.escape(name)}</summary><pre>{pretty}</pre></details>")
        head = f'<meta charset="utf-8"><title>{html.escape(self.title)}</title><style>{STYLE}</style>'
        return f"<!doctype html>\n<html><head>{head}</head><body>\n" + "\n".join(body) + "\n</body></html>\n"

    def write(self, path: LabPath) -> LabPath:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.html(path.parent), encoding="utf-8")
        return path


def _table(df: pd.DataFrame) -> str:
    return df.to_html(float_format=lambda v: f"{v:.3g}", na_rep="–", border=0, escape=True)


def _key(path: Path) -> str:
    """A local path or a store's key, as a POSIX path (to make the PDF links relative)."""
    return os.path.abspath(path) if is_local(path) else "/" + path.path


def _figure(png: Path, base: Path | None) -> str:
    """The PNG inlined as a data URI, captioned with its name and a link to the PDF beside it."""
    if not png.is_file():
        return f"<p><em>missing figure {html.escape(png.name)}</em></p>"
    data = base64.b64encode(png.read_bytes()).decode()
    pdf = png.with_suffix(".pdf")
    link = posixpath.relpath(_key(pdf), _key(base)) if base is not None else str(pdf)
    caption = html.escape(png.stem) + (f' (<a href="{html.escape(link)}">PDF</a>)' if pdf.is_file() else "")
    image = f'<img alt="{html.escape(png.stem)}" src="data:image/png;base64,{data}">'
    return f"<figure>{image}<figcaption>{caption}</figcaption></figure>"
