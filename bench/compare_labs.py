"""Are two lab directories' results the same? Compares what the main job made in each: the report's tables
cell by cell, every dataset's rows, every model's metrics and every figure's pixels.

    python bench/compare_labs.py LAB_BEFORE LAB_AFTER

A refactor that must not change behaviour runs the main job before and after it and compares the two labs.
Version ids, timings and the real-time rig session (which depends on the machine's load) are left out: ids
are allowed to change with the code, and the rig session is not deterministic. Prints one line per artefact
and exits 1 when anything differs.
"""

from __future__ import annotations

import argparse
import json
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib import image

# tables that depend on the machine (timings, the real-time session) or only list version ids
NOT_COMPARED = ("main job steps", "real-time sessions", "what the figures were made from")


class _Tables(HTMLParser):
    """The report's tables: ``{caption: [[cell, …], …]}`` (the caption is the heading before the table)."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self._heading: list[str] | None = None
        self._title = ""
        self._rows: list[list[str]] | None = None
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag in ("h2", "h3"):
            self._heading = []
        elif tag == "table":
            self._rows = []
        elif tag == "tr" and self._rows is not None:
            self._rows.append([])
        elif tag in ("td", "th") and self._rows is not None:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("h2", "h3") and self._heading is not None:
            self._title = "".join(self._heading).strip()
            self._heading = None
        elif tag == "table" and self._rows is not None:
            name = self._title
            while name in self.tables:
                name += "'"
            self.tables[name] = self._rows
            self._rows = None
        elif tag in ("td", "th") and self._cell is not None:
            self._rows[-1].append("".join(self._cell).strip())
            self._cell = None

    def handle_data(self, data):
        if self._heading is not None:
            self._heading.append(data)
        elif self._cell is not None:
            self._cell.append(data)


def report_tables(lab: Path) -> dict[str, list[list[str]]]:
    parser = _Tables()
    parser.feed((lab / "report" / "index.html").read_text())
    return {k: v for k, v in parser.tables.items() if not any(k.startswith(n) for n in NOT_COMPARED)}


def _newest(folder: Path) -> Path | None:
    cards = [(json.loads(c.read_text()).get("created", ""), c.parent) for c in folder.glob("*/card.json")]
    return max(cards)[1] if cards else None


def compare_datasets(a: Path, b: Path) -> list[str]:
    out = []
    for name in sorted(p.name for p in (a / "datasets").iterdir()):
        da, db = _newest(a / "datasets" / name), _newest(b / "datasets" / name)
        if db is None:
            out.append(f"dataset {name}: missing after")
            continue
        for table in sorted(p.name for p in da.glob("*.parquet")):
            x, y = pd.read_parquet(da / table), pd.read_parquet(db / table)
            try:
                pd.testing.assert_frame_equal(x, y, check_exact=False, rtol=1e-9, atol=1e-12)
                out.append(f"dataset {name}/{table}: same ({len(x)} rows)")
            except AssertionError as exc:
                out.append(f"dataset {name}/{table}: DIFFERENT: {str(exc).splitlines()[0]}")
    return out


def _metrics(card: dict) -> dict:
    return {k: v for k, v in card.get("metrics", {}).items()}


def compare_models(a: Path, b: Path) -> list[str]:
    out = []
    for name in sorted(p.name for p in (a / "models").iterdir() if p.is_dir()):
        ma, mb = _newest(a / "models" / name), _newest(b / "models" / name)
        if mb is None:
            out.append(f"model {name}: missing after")
            continue
        x, y = (_metrics(json.loads((m / "card.json").read_text())) for m in (ma, mb))
        same = json.dumps(x, sort_keys=True) == json.dumps(y, sort_keys=True)
        out.append(f"model {name}: metrics {'same' if same else 'DIFFERENT'}")
    return out


def compare_figures(a: Path, b: Path) -> list[str]:
    out = []
    for png in sorted((a / "figures").glob("*.png")):
        other = b / "figures" / png.name
        if not other.is_file():
            out.append(f"figure {png.stem}: missing after")
            continue
        x, y = image.imread(png), image.imread(other)
        if x.shape != y.shape:
            out.append(f"figure {png.stem}: DIFFERENT size {x.shape} vs {y.shape}")
            continue
        differing = float(np.mean(np.any(np.abs(x - y) > 1e-6, axis=-1)))
        verdict = "same" if differing == 0 else f"DIFFERENT in {differing:.2%} of pixels"
        out.append(f"figure {png.stem}: {verdict}")
    return out


def compare_tables(a: Path, b: Path) -> list[str]:
    ta, tb = report_tables(a), report_tables(b)
    out = []
    for name, rows in ta.items():
        if name not in tb:
            out.append(f"table {name!r}: missing after")
        else:
            out.append(f"table {name!r}: {'same' if rows == tb[name] else 'DIFFERENT'} ({len(rows)} rows)")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    args = parser.parse_args(argv)
    lines = [
        *compare_tables(args.before, args.after),
        *compare_datasets(args.before, args.after),
        *compare_models(args.before, args.after),
        *compare_figures(args.before, args.after),
    ]
    print("\n".join(lines))
    differing = [line for line in lines if "DIFFERENT" in line or "missing" in line]
    print(f"{len(lines) - len(differing)} of {len(lines)} the same")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
