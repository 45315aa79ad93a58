"""The report reads like a results page: every section opens with an intro, every table header carries its
unit, numbers come in their quantity's format (never ``1e+03``), the versions table is name → version, and
the papers' values stand beside ours. Small hand-made tables and a tiny lab only (fast)."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest

from analysis import popup_tests
from analysis.lab_figures import Results, _unmodelled, experiment2_claims, registration_table
from analysis.lab_report import lab_report
from analysis.report import NA, Report, format_table, header, significant
from pipeline.lab import Lab

# headers that are names, words or plain counts: no unit expected
UNITLESS = {"model", "cell", "robot", "input", "version", "settings", "reason", "figure or table", "step",
            "finding: A beats B", "paper", "this twin", "command", "tip", "where", "session", "plan",
            "status", "topic", "messages", "ζ", "ζ, paper", "model corrected for deflection"}  # fmt: skip
COUNTS = ("points", "messages", "samples")  # a count's header says what it counts


class Tables(HTMLParser):
    """The page's tables: (title of the h3 before it, headers, rows of cell texts); and its h2 sections,
    each with whether the next element is an intro paragraph."""

    def __init__(self):
        super().__init__()
        self.tables, self.sections = [], []
        self._text, self._title, self._after_h2 = "", "", None

    def handle_starttag(self, tag, attrs):
        if self._after_h2 is not None:  # the first element after an h2
            self.sections.append((self._after_h2, tag == "p" and ("class", "intro") in attrs))
            self._after_h2 = None
        if tag == "table":
            self.tables.append((self._title, [], []))
        elif tag == "tr" and self.tables:
            self.tables[-1][2].append([])
        self._text = ""

    def handle_data(self, data):
        self._text += data

    def handle_endtag(self, tag):
        text = self._text.strip()
        if tag == "h3":
            self._title = text
        elif tag == "h2":
            self._after_h2 = text
        elif tag == "th" and self.tables:
            self.tables[-1][1].append(text)
        elif tag == "td" and self.tables:
            self.tables[-1][2][-1].append(text)
        self._text = ""


def parse(page: str) -> Tables:
    tables = Tables()
    tables.feed(page)
    tables.tables = [(title, headers, [r for r in rows if r]) for title, headers, rows in tables.tables]
    return tables


def test_numbers_in_their_quantitys_format():
    df = pd.DataFrame(
        {"rate (Hz)": [1000.26, 99.7], "mean_mm": [0.12345, np.nan], "test points": [17568, 3],
         "damping ratio": [0.123456, 2.5], "x": [1.2e-5, 123456.7], "ok": [True, False]},
        index=pd.Index(["a", "b"], name="robot"),
    )  # fmt: skip
    shown = format_table(df)
    assert list(shown.columns) == [
        "robot",
        "rate (Hz)",
        "mean (mm)",
        "test points",
        "damping ratio",
        "x",
        "ok",
    ]
    assert shown["rate (Hz)"].tolist() == ["1,000", "100"]  # rates as whole numbers
    assert format_table(pd.DataFrame({"rate (Hz)": [392.4, 0.3, 0.0]}))["rate (Hz)"].tolist() == [
        "392.4", "0.3", "0.0",
    ]  # fmt: skip  # a slow stream's rate is not 0
    assert format_table(pd.DataFrame({"e (mm)": [38.98, 0.95]}))["e (mm)"].tolist() == ["39.0", "0.9"]
    assert shown["mean (mm)"].tolist() == ["0.12", NA]  # mm to 0.01; NaN as a dash
    assert shown["test points"].tolist() == ["17,568", "3"]  # counts with thousands separators
    assert shown["damping ratio"].tolist() == ["0.12", "2.50"]
    assert shown["x"].tolist() == ["0.0000120", "123,457"]  # three significant digits, never 1e-05
    assert shown["ok"].tolist() == ["yes", "no"]
    assert not shown.apply(lambda c: c.str.contains("e+0|e-0", regex=True)).any().any()


def test_a_tables_maker_names_a_columns_format():
    df = pd.DataFrame({"ζ": [0.031234], "k (N·m/rad)": [321.4]})
    df.attrs["formats"] = {"ζ": ".4f"}
    assert format_table(df).iloc[0].tolist() == ["0.0312", "321"]  # the maker's, then the unit's


@pytest.mark.parametrize(
    ("name", "shown"),
    [("mean_mm", "mean (mm)"), ("payload_g", "payload (g)"), ("pressure_bar", "pressure (bar)"),
     ("f_s_hz", "f s (Hz)"), ("rms, selected (mm)", "rms, selected (mm)"), ("n", "n"), ("mode", "mode")],
)  # fmt: skip
def test_headers_carry_the_unit_of_a_code_name(name, shown):
    assert header(name) == shown


def test_significant_digits_never_scientific():
    assert [significant(v) for v in (1234567.0, 0.000123456, 12.345, 0.0)] == [
        "1,234,567", "0.000123", "12.3", "0",
    ]  # fmt: skip


def test_every_section_opens_with_an_intro_and_tables_stay_plain_html(tmp_path):
    page = Report("t")
    page.section("A", intro="What A shows.", tables={"x": pd.DataFrame({"v (mm)": [1.0]})})
    page.section("B", intro="What B shows.", text="More.")
    html = page.write(tmp_path / "index.html").read_text()
    assert parse(html).sections == [("A", True), ("B", True)]
    assert "<td>1.00</td>" in html and "http" not in html


def _tiny_lab(tmp_path) -> tuple[Lab, Results]:
    """A lab with only the main job's comparison (its JSON settings among its versions), and results
    tables made by the report's own table makers from hand-made numbers."""
    from pipeline.comparison import UNMODELLED, save_comparison

    lab = Lab(tmp_path)
    table = pd.DataFrame([{"direction": d, "model": m, "cell": "all", "n": 1200, "tip_mm_mean": 0.5}
                          for d in ("forward", "inverse") for m in ("gbr", "floor")])  # fmt: skip
    paths = [{"session": f"s{k}", "robot": robot, "payload_g": 75, "pressure_bar": 0.5, "mode": mode,
              "mean_mm": e, "median_mm": e, "p95_mm": 2 * e, "max_mm": 3 * e, "n": 4000}
             for k, (robot, mode, e) in enumerate([("vsl", "ik", 9.0), ("vsl", "hybrid", 2.0),
                                                   ("vsl_rigid", "ik", 4.0)])]  # fmt: skip
    made_from = {"campaign (drawn)": "v1", "training": "{}", "paths": '{"repetitions": 2}'}
    save_comparison(lab.comparisons.path(UNMODELLED), table, made_from, "split_group", {"experiment2": paths})
    res = Results(versions={"dataset campaign": "abc123"})
    _unmodelled(lab, res)
    registration = {"vsl": {"points": 300, "selected": 150, "trimmed": 12, "deflection": True,
                            "residuals": {"rms_m": 3e-4}, "residuals_selected": {"rms_m": 2e-4, "p95_m": 4e-4,
                                                                                 "max_m": 6e-4}}}  # fmt: skip
    res.tables["registration (tracker → base), campaign"] = registration_table(registration)
    errors = pd.DataFrame(paths)
    res.tables["Experiment 2: the paper's findings (Fig. 7b) beside ours"] = experiment2_claims(errors)
    impact = pd.DataFrame({"pressure_pa": [10e3, 90e3], "f_s_hz": [15.0, 16.9], "zeta": [0.03, 0.02],
                           "f_s_std_hz": [0.01, 0.01], "zeta_std": [0.001, 0.001]})  # fmt: skip
    static = pd.DataFrame({"pressure_pa": [10e3], "k": [300.0]})
    res.tables["POPUP Table 1: ours (twin) beside the paper's"] = popup_tests.table1_report(
        popup_tests.table1(static, impact)
    )
    res.missing["dataset experiment1"] = "no dataset"
    return lab, res


def test_the_report_of_a_tiny_lab_reads_like_a_results_page(tmp_path):
    lab, res = _tiny_lab(tmp_path)
    html = lab_report(lab, res, timings={"campaign": 12345.678}).read_text()
    assert not re.search(r"<script|<link|https?:", html)  # one offline file
    page = parse(html)
    assert page.sections and all(intro for _, intro in page.sections), page.sections
    for title, headers, rows in page.tables:
        cells = [c for row in rows for c in row]
        assert not [c for c in cells if re.search(r"\de[+-]\d", c)], title  # no 1e+03 style number
        for k, name in enumerate(headers):
            numeric = [row[k] for row in rows if len(row) > k and re.fullmatch(r"-?[\d,]+(\.\d+)?", row[k])]
            if numeric and name not in UNITLESS and not name.endswith(COUNTS):
                assert re.search(r"\(.+\)$", name), (title, name)  # a number's header names its unit
    tables = {title: (headers, rows) for title, headers, rows in page.tables}
    headers, rows = tables["what the figures were made from"]
    assert headers == ["input", "version", "settings"]
    assert not any("{" in c for row in rows for c in row)
    assert ["settings paths, vsl_unmodelled", NA, "repetitions=2"] in rows
    assert ["settings training, vsl_unmodelled", NA, "defaults"] in rows
    assert ["dataset campaign", "abc123", ""] in rows
    assert tables["main job steps"] == (["step", "time (s)"], [["campaign", "12,345.7"]])
    headers, rows = tables["unmodelled effects: forward models, mean tip error"]
    assert headers == ["cell", "test points", "gbr (mm)", "floor (mm)"] and rows[0][1] == "1,200"
    headers, _ = tables["unmodelled effects: Experiment 2, distance to the desired path"]
    assert {"payload (g)", "pressure (bar)", "mean (mm)", "tracked points", "command"} <= set(headers)


def test_popup_table1_shows_the_papers_values_beside_ours(tmp_path):
    lab, res = _tiny_lab(tmp_path)
    page = parse(lab_report(lab, res).read_text())
    headers, rows = next((h, r) for t, h, r in page.tables if t.startswith("POPUP Table 1"))
    for name, _, _, _ in popup_tests.TABLE1_COLUMNS:
        assert name in headers
    assert {"f_s, paper (Hz)", "k̂, paper (N·m/rad)", "ĉ, paper (N·m·s/rad)", "ζ, paper"} <= set(headers)
    at = {row[0]: dict(zip(headers, row, strict=True)) for row in rows}
    assert at["10"]["k̂, paper (N·m/rad)"] == "321" and at["90"]["f_s, paper (Hz)"] == "16.93"
    assert at["90"]["k (N·m/rad)"] == NA and at["90"]["k, paper (N·m/rad)"] == NA  # no static test there


def test_the_papers_zeta_is_the_one_its_table_implies():
    """ζ from the paper's ĉ, k̂, f_s gives back its ĉ through the paper's own procedure."""
    paper = popup_tests.PAPER_TABLE1.add_prefix("paper_")
    zeta = popup_tests.paper_zeta(paper)
    w_n = 2 * np.pi * paper["paper_f_s_hz"] / np.sqrt(1 - zeta**2)
    inertia = paper["paper_k_hat"] / w_n**2
    np.testing.assert_allclose(2 * zeta * np.sqrt(paper["paper_k_hat"] * inertia), paper["paper_c_hat"])
    assert 0.05 < zeta.min() and zeta.max() < 0.1


def test_experiment2_claims_are_the_papers_beside_ours():
    errors = pd.DataFrame({"robot": ["vsl", "vsl", "vsl_rigid"], "mode": ["ik", "hybrid", "ik"],
                           "mean_mm": [9.0, 5.0, 4.0]})  # fmt: skip
    claims = experiment2_claims(errors)
    assert claims["paper"].eq("yes").all()
    assert claims["this twin"].tolist() == ["yes", "no"]  # no static sessions: that finding is left out
