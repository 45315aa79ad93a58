"""The one way a figure is saved: PDF + PNG beside a JSON record of what it was made from.

Every figure function of ``analysis/`` ends in :func:`save_figure`, so every figure of a lab directory can say
which datasets, models or sessions it shows and which code drew it (the figure stage's code version).
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.pyplot as plt

from pipeline.cache import stage_version

PNG_DPI = 150


def save_figure(fig, out_dir: Path, stem: str, made_from: dict | None = None, tight: bool = False,
                **details) -> Path:  # fmt: skip
    """``<out_dir>/<stem>.pdf``, ``.png`` (150 dpi) and ``.json`` (``figure``, ``made_from``: the versions or
    sessions shown, ``code_version``, and any ``details``); ``tight`` crops to the drawn area. A pyplot figure
    is closed afterwards. Returns the PNG's path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    extra = {"bbox_inches": "tight"} if tight else {}
    fig.savefig(out_dir / f"{stem}.pdf", **extra)
    fig.savefig(out_dir / f"{stem}.png", dpi=PNG_DPI, **extra)
    plt.close(fig)
    record = {
        "figure": stem,
        "made_from": dict(made_from or {}),
        "code_version": stage_version("figure"),
        **details,
    }
    (out_dir / f"{stem}.json").write_text(json.dumps(record, indent=1, default=str))
    return out_dir / f"{stem}.png"
