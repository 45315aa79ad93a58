"""The HTML report: one self-contained page (figures inlined, tables, cards) that opens offline."""

from __future__ import annotations

import base64

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd

from analysis.report import Report


def test_report_inlines_figures_tables_and_cards(tmp_path):
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1], [0, 1])
    png = tmp_path / "figures" / "line.png"
    png.parent.mkdir()
    fig.savefig(png)
    fig.savefig(png.with_suffix(".pdf"))
    plt.close(fig)
    page = Report("vslab <test>")
    page.section("Errors", text="First paragraph.\n\nSecond & last.", figures=[png, tmp_path / "gone.png"],
                 tables={"error": pd.DataFrame({"rigid (mm)": [2.1], "hybrid (mm)": [0.2]}, index=["a"])},
                 cards={"model card": {"version": "abc", "metrics": {"mean_mm": 0.2}}})  # fmt: skip
    out = page.write(tmp_path / "report" / "index.html")
    text = out.read_text()
    assert "vslab &lt;test&gt;" in text and "Second &amp; last." in text
    assert base64.b64encode(png.read_bytes()).decode() in text  # inlined: no file needed beside the page
    assert 'href="../figures/line.pdf"' in text and "missing figure gone.png" in text
    assert "<td>2.10</td>" in text and "&quot;version&quot;: &quot;abc&quot;" in text
    assert "http" not in text.replace("http-equiv", "")  # nothing fetched from the network
