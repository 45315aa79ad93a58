"""The documentation site: it builds with --strict (a broken link or reference fails), its reference pages
are generated from the code, the tutorials' commands run, and the pages load in Chromium without console
errors."""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TUTORIALS, tutorial_blocks

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ("cli", "robot-description", "experiments", "training-grid", "topics", "dataset-columns",
             "model-card", "api")  # fmt: skip
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site as `make docs` builds it (≈ 10 s)."""
    out = tmp_path_factory.mktemp("site")
    mkdocs = Path(sys.executable).parent / "mkdocs"
    done = subprocess.run([str(mkdocs), "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{done.stderr}"
    return out


@pytest.mark.slow  # the site's build (≈ 10 s) is for `make test`; `make check` stays for the code
def test_site_builds_strict_with_the_generated_reference(site):
    for page in REFERENCE:
        assert (site / "reference" / f"{page}.html").is_file(), page
    cli = (site / "reference" / "cli.html").read_text()
    assert "vslab demo" in cli and "--quick" in cli and "VSLAB_LAB" in cli
    assert "length_mm" not in (site / "reference" / "dataset-columns.html").read_text()
    assert "/servo/state" in (site / "reference" / "topics.html").read_text()
    assert "card_sha256" in (site / "reference" / "model-card.html").read_text()
    assert "pipeline.lab.Lab" in (site / "reference" / "api.html").read_text()  # mkdocstrings ran
    assert not (site / "hooks").exists(), "the hooks are the build's code, not pages"
    home = (site / "index.html").read_text()  # links name files: the site opens from disk, no server
    assert 'href="tutorials/twin-end-to-end.html"' in home and "reference/cli.html" in home


def test_only_sh_blocks_are_commands(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("```sh\nvslab --help\n```\n\n```text\nUsage: vslab\n```\n\n!!! tip\n    ```sh\n    ls\n"
                    "    ```\n````markdown\n```sh\nnot run\n```\n````\n")  # fmt: skip
    assert tutorial_blocks(page) == ["vslab --help\n", "ls\n"]


# a `vslab …` command in a code block of any page (after a prompt, a pipe or `&&`), up to where the shell
# takes over again (a pipe, a redirection, a comment)
_COMMAND = re.compile(r"(?:^|[|;&(]\s*)vslab\s+(?P<args>.*)")
_SHELL = re.compile(r"\s(?:\|\||&&|\||>|2>|<|;|#)(?:\s|$)")


def documented_commands() -> list[tuple[str, list[str]]]:
    """Every `vslab …` command shown in the docs' code blocks (continued lines joined), as (page, argv);
    those with a placeholder (`<name>`, `…`) left out."""
    found = []
    for page in sorted((ROOT / "docs").rglob("*.md")):
        text = re.sub(r"\\\n\s*", " ", page.read_text())  # a command continued over lines
        in_block = False
        for line in text.splitlines():
            if line.strip().startswith("```"):
                in_block = not in_block
                continue
            if in_block and (m := _COMMAND.search(line.strip().removeprefix("$ "))):
                args = shlex.split(_SHELL.split(m["args"])[0], comments=True)
                if not any("…" in a or "<" in a for a in args):
                    found.append((str(page.relative_to(ROOT)), args))
    return found


def test_every_command_the_docs_show_is_one_vslab_has(tmp_path):
    """Each documented command names a real command and real options (typer parses them; `--help` stops it
    before it runs): a renamed option breaks this, not a reader. An s3:// lab is swapped for a folder."""
    from typer.testing import CliRunner

    from vslab.cli import app

    commands = documented_commands()
    assert len(commands) >= 50, commands  # the how-to guides and tutorials show dozens
    wrong = []
    for page, args in commands:
        args = [str(tmp_path) if a.startswith("s3://") else a for a in args]
        done = CliRunner().invoke(app, [*args, "--help"])
        if done.exit_code != 0:
            wrong.append(f"{page}: vslab {' '.join(args)}: {done.output.strip().splitlines()[-1:]}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.slow
def test_tutorials_commands_run_in_order_on_the_twin(tutorial_run):
    for page in TUTORIALS:
        assert tutorial_blocks(ROOT / "docs" / "tutorials" / f"{page}.md"), f"{page}: no sh block to run"
    assert tutorial_run.failure() is None, tutorial_run.failure()
    assert not tutorial_run.left_running, "a tutorial leaves these running (stop them in its last block)"


# ----------------------------------------------------------------------------------------------- Chromium
def _screens():
    """bench/docs_screens.py (its DevTools-protocol Browser) as a module."""
    spec = importlib.util.spec_from_file_location("docs_screens", ROOT / "bench" / "docs_screens.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """Headless Chromium whose console the test observes: a page's deliberate console.error must be seen
    first, or the test fails (it never passes for want of looking)."""
    if CHROMIUM is None:
        if os.environ.get("CI"):
            pytest.fail("Chromium is not installed (CI installs it: .ci/run)")
        pytest.skip("Chromium is not installed (apt-get install chromium); CI runs this test")
    screens = _screens()
    probe = tmp_path_factory.mktemp("probe") / "probe.html"
    probe.write_text('<html><body><script>console.error("deliberate-probe")</script></body></html>')
    with screens.Browser(CHROMIUM, tmp_path_factory.mktemp("chromium-profile")) as b:
        assert any("deliberate-probe" in e for e in b.load(probe.as_uri())), "the console is not observed"
        yield b


def _loads_cleanly(browser, page: Path) -> None:
    assert page.is_file(), page
    assert browser.load(page.as_uri()) == [], page
    title = browser.call("Runtime.evaluate", session=True, expression="document.title", returnByValue=True)
    assert title["result"]["value"], f"{page}: no title: not rendered"


@pytest.mark.slow
def test_home_tutorial_and_a_report_load_without_console_errors(site, browser, tmp_path):
    from analysis.report import Report

    _loads_cleanly(browser, site / "index.html")
    _loads_cleanly(browser, site / "tutorials" / "twin-end-to-end.html")
    header = "getComputedStyle(document.querySelector('.md-header')).position"
    styled = browser.call("Runtime.evaluate", session=True, returnByValue=True, expression=header)
    assert styled["result"]["value"] in ("sticky", "fixed"), "the theme's CSS is not loaded"
    page = Report("a report")
    page.section("a section", text="made in the test")
    _loads_cleanly(browser, Path(page.write(tmp_path / "report" / "index.html")))


@pytest.mark.slow
def test_the_tutorials_report_loads_without_console_errors(tutorial_run, browser):
    assert tutorial_run.failure() is None, tutorial_run.failure()
    _loads_cleanly(browser, tutorial_run.workdir / "lab" / "report" / "index.html")
