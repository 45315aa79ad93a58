"""Models chosen by a tag kept in the model store (`vslab models tag NAME VERSION`): any command that takes a
version takes a tag; a bad tag or a tag to nothing is one error line; re-tagging moves the tag."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from test_bad_models import _card, _net
from typer.testing import CliRunner

from pipeline import model_store
from vslab.cli import app

runner = CliRunner()
FORWARD, INVERSE = "9f8e7d6c5b4a3f2e", "1a2b3c4d5e6f7a8b"


@pytest.fixture
def lab(tmp_path) -> Path:
    for (name, version), direction, seed in (
        (("inverse-tiny", INVERSE), "inverse", 1),
        (("forward-tiny", FORWARD), "forward", 2),
    ):
        model_store.save_model(tmp_path / "models", name, version, _net(direction, seed), _card(direction))
    return tmp_path


def _invoke(lab: Path, *args: str):
    return runner.invoke(app, ["--lab", str(lab), *args])


def test_a_tag_names_a_version_everywhere_a_version_is_taken(lab):
    result = _invoke(lab, "models", "tag", "inverse", INVERSE[:6])  # a unique prefix will do
    assert result.exit_code == 0, result.output
    assert f"inverse → {INVERSE}" in result.output
    assert model_store.tags(lab / "models") == {"inverse": INVERSE}
    assert model_store.find(lab / "models", "inverse").name == INVERSE
    shown = _invoke(lab, "models", "show", "inverse")
    assert shown.exit_code == 0 and f"inverse-tiny {INVERSE}" in shown.output
    listed = _invoke(lab, "models", "list")
    assert f"tags: inverse → {INVERSE}" in listed.output


def test_re_tagging_moves_the_tag(lab):
    model_store.tag(lab / "models", "best", INVERSE)
    assert _invoke(lab, "models", "tag", "best", FORWARD).exit_code == 0
    assert model_store.tags(lab / "models") == {"best": FORWARD}
    assert not list((lab / "models").glob(".*tmp"))  # written whole, nothing left behind


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (("Best", FORWARD), "'Best' is not a tag name"),
        (("a b", FORWARD), "'a b' is not a tag name"),
        (("best", "0000000000000000"), "no model version '0000000000000000'"),
        (("best", "nope/../x"), "is not a model version"),
    ],
)
def test_a_bad_tag_or_a_tag_to_nothing_is_one_line(lab, args, says):
    result = _invoke(lab, "models", "tag", *args)
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and says in lines[0], result.output
    assert model_store.tags(lab / "models") == {}


def test_a_damaged_model_cannot_be_tagged_and_a_damaged_tags_file_is_one_line(lab):
    weights = model_store.find(lab / "models", FORWARD) / "weights.safetensors"
    weights.write_bytes(weights.read_bytes()[:-8] + b"\x00" * 8)
    result = _invoke(lab, "models", "tag", "best", FORWARD)
    assert result.exit_code == 2 and "weights.safetensors" in result.output
    (lab / "models" / model_store.TAGS_FILE).write_text("{not json")
    result = _invoke(lab, "models", "list")
    assert result.exit_code == 2 and "tags.json: unreadable" in result.output, result.output
    shutil.rmtree(lab / "models")
