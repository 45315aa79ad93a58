"""One HTML page that opens offline: figures (embedded PNG), metric tables, dataset and model cards, and the
papers' numbers beside ours.

    page = Report("vslab — twin run of 2026-11-23")
    page.section("Experiment 2", intro="What it shows, what to compare.", text="…", figures=[png],
                 tables={"path error": df}, cards={"model": card})
    page.write(lab.report / "index.html")  # lab: a pipeline.lab.Lab

Everything is inlined (images as data URIs, no scripts, no fonts fetched): the file can be mailed or archived.

Tables go through :func:`format_table`: each column is shown in the format its unit asks for (``mean (mm)``:
two decimals; ``rate (Hz)``: a whole number; counts with thousands separators; NaN as "—"), never in
scientific notation. A table's maker may name a column's format itself in ``df.attrs["formats"]``
(column → a format spec such as ``".3f"``).
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import posixpath
import re
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
td { white-space: nowrap; font-variant-numeric: tabular-nums; } .text { text-align: left; }
div.table { overflow-x: auto; } td.paper { background: #f6f8fb; }
details { margin: .4em 0; } pre { background: #f7f7f7; padding: .6em; overflow-x: auto; font-size: .85em; }
.meta { color: #666; font-size: .9em; } .intro { font-size: 1.02em; }
"""


@dataclass
class Section:
    title: str
    text: str = ""
    intro: str = ""  # one or two sentences first: what the section shows and what to compare
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
            if s.intro:
                body.append(f'<p class="intro">{html.escape(" ".join(s.intro.split()))}</p>')
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


NA = "—"  # a missing value in a table
UNIT = re.compile(r"\(([^()]*)\)\s*$")  # "mean (mm)" → "mm": a header's unit, in parentheses at its end
DECIMALS = {"mm": 2, "m": 3, "s": 1, "Hz": 2, "kPa": 0, "bar": 1, "g": 0, "%": 1, "N·m/rad": 0,
            "N·m·s/rad": 3, "N·m": 2, "deg": 2}  # fmt: skip  # per unit: what the lab's instruments resolve
SUFFIXES = {"_mm": "mm", "_m": "m", "_s": "s", "_hz": "Hz", "_kpa": "kPa", "_bar": "bar", "_g": "g",
            "_kgm2": "kg·m²", "_pct": "%"}  # fmt: skip  # code's unit suffixes (SI names) → display units


def unit_of(header: str) -> str:
    """The unit a header names in parentheses at its end ("rate (Hz)" → "Hz"); "" when it names none."""
    found = UNIT.search(str(header))
    return found.group(1).strip() if found else ""


def header(name: object) -> str:
    """A code column name as a header with its unit: ``mean_mm`` → ``mean (mm)``, ``payload_g`` →
    ``payload (g)``; a name that already reads as a header (or has no unit suffix) stays as it is."""
    text = str(name)
    for suffix, unit in SUFFIXES.items():
        if text.endswith(suffix) and text != suffix.lstrip("_") and " " not in text:
            return f"{text.removesuffix(suffix).replace('_', ' ')} ({unit})"
    return text


def significant(value: float, digits: int = 3) -> str:
    """``value`` with ``digits`` significant digits in positional notation (never ``1e+03``)."""
    if value == 0 or not math.isfinite(value):
        return "0" if value == 0 else str(value)
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(value))))
    return f"{value:,.{decimals}f}"


def column_spec(name: str, values: pd.Series) -> str | None:
    """The format spec of a column, from its header: rates as whole numbers (one decimal where a rate is
    below 10 Hz), ratios to two decimals, the unit's decimals (:data:`DECIMALS`; mm to 0.1 in a column
    of tens of mm), whole-valued numbers with thousands separators; None: three significant digits."""
    numbers = pd.to_numeric(values, errors="coerce").dropna()
    if len(numbers) == 0 or pd.api.types.is_bool_dtype(values):
        return None
    unit, typical = unit_of(name), float(numbers.abs().median())
    if "rate" in name.lower() and unit == "Hz":  # whole numbers, but a slow stream's 0.3 Hz is not 0
        slow = numbers[(numbers != 0) & (numbers.abs() < 10)]
        return ",.1f" if len(slow) else ",.0f"
    if not unit and any(word in name.lower() for word in ("ratio", "×")):
        return ".2f"
    if unit == "mm" and typical >= 10:  # tens of mm to 0.1 mm, errors of a few mm to 0.01 mm
        return ",.1f"
    if unit in DECIMALS:
        return f",.{DECIMALS[unit]}f"
    if bool((numbers == numbers.round()).all()):
        return ",.0f"
    return None


def cell(value: object, spec: str | None) -> str:
    """One cell as text: NaN/None as :data:`NA`, numbers in ``spec`` (or three significant digits)."""
    if value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA:
        return NA
    if isinstance(value, bool):
        return "yes" if value else "no"
    if not isinstance(value, int | float):
        return str(value)
    return format(value, spec) if spec else significant(float(value))


def format_table(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` as the page shows it: its index as the first columns, every header with its unit
    (:func:`header`) and every cell as text in its column's format (``df.attrs["formats"]`` first, then
    :func:`column_spec`)."""
    formats = df.attrs.get("formats", {})
    named = [n if n is not None else "" for n in df.index.names]
    flat = df.rename_axis(named).reset_index() if any(named) or not _plain_index(df) else df.copy()
    out = {}
    for column in flat.columns:
        title = header(column)
        spec = formats.get(column, formats.get(title)) or column_spec(title, flat[column])
        out[title] = [cell(v, spec) for v in _python(flat[column])]
    return pd.DataFrame(out, columns=list(out))


def _plain_index(df: pd.DataFrame) -> bool:
    """Whether ``df``'s index is the default 0…n−1, which says nothing (and is not shown)."""
    return isinstance(df.index, pd.RangeIndex) and df.index.start == 0 and df.index.step == 1


def _python(column: pd.Series) -> list:
    """The column's values as Python objects (numpy scalars → int/float), for :func:`cell`."""
    return [v.item() if hasattr(v, "item") and not isinstance(v, str) else v for v in column.tolist()]


NUMBER = re.compile(r"-?[\d,]+(\.\d+)?")


def _css_class(column: str, cells: pd.Series) -> str:
    """The class attribute of a column's cells: "text" (left-aligned) unless every cell is a number or
    :data:`NA`, and "paper" for the papers' values (shaded, to tell them from ours at a glance)."""
    kinds = [] if all(NUMBER.fullmatch(v) or v == NA for v in cells) else ["text"]
    kinds += ["paper"] if "paper" in column else []
    return f' class="{" ".join(kinds)}"' if kinds else ""


def _table(df: pd.DataFrame) -> str:
    """``df`` through :func:`format_table` as an HTML table: numbers right-aligned, words left-aligned, the
    papers' columns shaded."""
    shown = format_table(df)
    align = [_css_class(str(c), shown[c]) for c in shown.columns]
    head = "".join(f"<th{a}>{html.escape(str(c))}</th>" for c, a in zip(shown.columns, align, strict=True))
    rows = [
        "<tr>" + "".join(f"<td{a}>{html.escape(v)}</td>" for v, a in zip(row, align, strict=True)) + "</tr>"
        for row in shown.itertuples(index=False)
    ]
    body = "\n".join(rows)
    return (
        f'<div class="table"><table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n{body}\n</tbody></table></div>'
    )


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
