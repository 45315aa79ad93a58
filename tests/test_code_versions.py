"""Versions change when behaviour changes (pipeline/cache.py): a stage's code version hashes the syntax of the
modules it runs, docstrings and comments left out, so editing prose re-versions no dataset and no model.
Every edit here is made in a copy of the checkout's packages, never in the real files."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from pipeline import cache, datasets, model_store
from pipeline.cache import STAGE_MODULES, stage_version

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def tree(tmp_path, monkeypatch):
    """A copy of the packages' Python files, made the code the versions are read from."""
    for package in cache.PACKAGES:
        shutil.copytree(
            ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("*.pyc", "__pycache__")
        )
    monkeypatch.setattr(cache, "ROOT", tmp_path)
    _forget()
    yield tmp_path
    _forget()


def _forget() -> None:
    cache._tree_version.cache_clear()
    cache._normalised.cache_clear()


def _versions() -> dict[str, str]:
    _forget()
    return {stage: stage_version(stage) for stage in STAGE_MODULES}


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{path.name} no longer has {old!r}: pick another line to edit"
    path.write_text(text.replace(old, new, 1))


def test_a_copy_has_the_versions_of_the_checkout(tree):
    copied = _versions()
    cache.ROOT = ROOT
    assert _versions() == copied


def test_docstring_and_comment_edits_leave_every_version_as_it_was(tree):
    before = _versions()
    clean = tree / "pipeline" / "clean.py"
    text = original = clean.read_text()
    # every function's docstring reworded, and comments added
    text = re.sub(r'(\ndef [^\n]*:\n\s+)"""', r'\1"""Reworded. ', text)
    text = text.replace(") -> SessionTables:\n", ") -> SessionTables:  # a comment\n")
    assert text.count("Reworded.") >= 3 and "# a comment" in text and text != original
    clean.write_text(text)
    _edit(tree / "models" / "kinematics.py", '"""', '"""An edited module docstring.\n\n')
    assert _versions() == before


def test_a_code_edit_re_versions_the_stages_that_run_it_and_no_other(tree):
    before = _versions()
    _edit(tree / "pipeline" / "clean.py", "hampel_sigmas: float = 4.0", "hampel_sigmas: float = 4.5")
    after = _versions()
    assert after["session"] != before["session"] and after["dataset"] != before["dataset"]
    assert after["model"] == before["model"]  # training does not run the cleaning


def test_an_edit_in_a_module_imported_on_the_way_re_versions_the_stage(tree):
    before = _versions()
    _edit(tree / "models" / "errors.py", "class NotFittedError(", "X = 1\n\n\nclass NotFittedError(")
    assert _versions()["session"] != before["session"]


def test_a_package_runs_its_init_before_its_modules(tree):
    before = _versions()
    (tree / "pipeline" / "__init__.py").write_text("X = 1\n")
    after = _versions()
    assert all(after[stage] != before[stage] for stage in ("session", "dataset", "model"))


def test_the_root_read_is_a_parameter(tree):
    copied = cache.code_version("pipeline.clean")
    _edit(tree / "pipeline" / "clean.py", "hampel_sigmas: float = 4.0", "hampel_sigmas: float = 4.5")
    _forget()
    assert cache.code_version("pipeline.clean", root=ROOT) == copied != cache.code_version("pipeline.clean")


def test_an_edit_in_code_no_stage_runs_changes_no_version(tree):
    before = _versions()
    (tree / "twin" / "kernel.py").write_text("X = 1\n")  # the twin: not the pipeline's code
    assert _versions() == before


def test_dataset_and_model_ids_survive_a_docstring_edit(tree):
    sources = {"sim-campaign-000": "ab" * 32}
    parameters = {"clean": {"hampel_window": 7}}
    config = {"net": {"hidden": [64]}, "seed": 0}
    ids = datasets.dataset_version(sources, parameters), model_store.model_version("v1", config)
    _edit(tree / "pipeline" / "train.py", '"""', '"""Edited. ')
    _edit(tree / "pipeline" / "datasets.py", '"""', '"""Edited. ')
    _forget()
    assert (datasets.dataset_version(sources, parameters), model_store.model_version("v1", config)) == ids
    _edit(tree / "pipeline" / "datasets.py", "FRACTIONS = ", "FRACTIONS = 1 and ")
    _forget()
    assert datasets.dataset_version(sources, parameters) != ids[0]


def test_the_normal_forms_kept_on_disk_give_the_versions_made_afresh(tmp_path, monkeypatch):
    """Each module's normal form is kept under the hash of its source (acquisition/code_version.py): a kept
    one gives the same versions as one made afresh, a torn or foreign file is made again, and a cache folder
    that cannot be written only costs the time."""
    from acquisition import code_version as cv

    kept = tmp_path / "kept"
    monkeypatch.setattr(cv, "NORMAL_FORMS", kept)
    _forget()
    made = _versions()
    files = sorted(kept.glob("*.json"))
    assert len(files) > 20 and not list(kept.glob("*.tmp"))
    assert _versions() == made  # read back

    files[0].write_text('["torn')
    files[1].write_text("{}")
    assert _versions() == made
    assert json.loads(files[0].read_text())[0] != "torn"  # made again, and kept

    unwritable = tmp_path / "a-file"
    unwritable.write_text("")
    monkeypatch.setattr(cv, "NORMAL_FORMS", unwritable / "forms")  # its parent is a file: nothing is kept
    assert _versions() == made


def test_an_edit_is_a_new_normal_form_not_a_stale_one(tree, tmp_path, monkeypatch):
    from acquisition import code_version as cv

    monkeypatch.setattr(cv, "NORMAL_FORMS", tmp_path / "kept")
    before = _versions()
    _edit(tree / "pipeline" / "clean.py", "hampel_sigmas: float = 4.0", "hampel_sigmas: float = 4.5")
    assert _versions()["session"] != before["session"]
    _edit(tree / "pipeline" / "clean.py", "hampel_sigmas: float = 4.5", "hampel_sigmas: float = 4.0")
    assert _versions() == before
