"""The Lab: one handle on a lab directory that owns its stores. It pickles whole (a cluster job receives it),
opening a place that cannot be a lab is one StoreError, no code below the Lab module joins a store's name to
a path or re-opens a root with ``lab_path``, and no module keeps settings in mutable module-level state."""

from __future__ import annotations

import ast
import pickle
import re
from pathlib import Path

import pytest
from conftest import absent_service_ports

from acquisition.recorder.sessions import SessionStore
from acquisition.storage import StoreError
from pipeline.lab import Lab

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("acquisition", "twin", "pipeline", "analysis", "models", "vslab")
LAB_MODULE = ROOT / "pipeline" / "lab.py"  # the one module that knows the lab's layout (no other is exempt)
STORES = ("sessions", "datasets", "models", "cache", "figures", "report", "comparisons", "unmodelled", "rig",
          "twin", "exports", "mlflow")  # fmt: skip
_NAME = "|".join(STORES)
# a store's name joined to a path: `/ "models"`, joinpath(…, "models"), Path("models"), f"{x}/models"
JOINS = [
    re.compile(rf"/\s*[\"']({_NAME})[\"']"),
    re.compile(rf"joinpath\([^)]*[\"']({_NAME})[\"']"),
    re.compile(rf"Path\(\s*[\"']({_NAME})[\"']"),
    re.compile(rf"f[\"'][^\"']*\}}/({_NAME})\b"),
]


def _package_files() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_only_the_lab_module_joins_store_names_or_opens_roots():
    found = []
    for path in _package_files():
        if path == LAB_MODULE:
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            where = f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
            if "lab_path(" in line and not line.lstrip().startswith("def lab_path("):
                found.append(where)
            elif any(j.search(line) for j in JOINS):
                found.append(where)
    assert not found, "store paths derived outside pipeline/lab.py:\n" + "\n".join(found)


def test_the_grep_sees_what_it_forbids():
    """The patterns above catch each way of joining a store's name (so the test above can fail)."""
    lines = [
        'root / "models"',
        "lab.joinpath('x', 'datasets')",
        'Path("comparisons") / x',
        'f"{lab}/cache/x"',
    ]
    assert all(any(j.search(line) for j in JOINS) for line in lines)
    assert not any(j.search('lab.report / "index.html"') for j in JOINS)


def test_settings_are_gone_and_no_module_keeps_mutable_settings():
    """No `Settings` holder in the CLI, and nowhere a function that assigns to an attribute of a class of its
    own module (a class used as a global holder) or rebinds a module global."""
    import vslab.app

    assert not hasattr(vslab.app, "Settings")
    found = []
    for path in _package_files():
        tree = ast.parse(path.read_text())
        classes = {node.name for node in tree.body if isinstance(node, ast.ClassDef)}
        for func in (n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)):
            for node in ast.walk(func):
                if isinstance(node, ast.Global):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: global {', '.join(node.names)}")
                targets = node.targets if isinstance(node, ast.Assign) else (
                    [node.target] if isinstance(node, ast.AugAssign | ast.AnnAssign) else [])  # fmt: skip
                for t in targets:
                    if (
                        isinstance(t, ast.Attribute)
                        and isinstance(t.value, ast.Name)
                        and t.value.id in classes
                    ):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {t.value.id}.{t.attr} = …")
    assert not found, "module-level mutable settings:\n" + "\n".join(found)


def test_a_lab_pickles_whole_with_its_stores(tmp_path):
    lab = Lab.open(tmp_path / "lab")
    again = pickle.loads(pickle.dumps(lab))
    assert again == lab and again.root == tmp_path / "lab"
    assert pickle.loads(pickle.dumps(lab.datasets)) == lab.datasets
    assert (
        pickle.loads(pickle.dumps(lab.sessions))
        == lab.sessions
        == SessionStore(tmp_path / "lab" / "sessions")
    )
    assert lab.study("unmodelled").models.root == tmp_path / "lab" / "unmodelled" / "models"


def test_a_lab_on_a_store_pickles_to_the_same_url():
    lab = Lab.open("memory://bucket/lab")
    again = pickle.loads(pickle.dumps(lab))
    assert again == lab and str(again.models.root) == str(lab.models.root)


def test_opening_a_file_as_a_lab_is_one_store_error(tmp_path):
    file = tmp_path / "notes.txt"
    file.write_text("not a lab")
    with pytest.raises(StoreError, match="not a directory"):
        Lab.open(file)
    with pytest.raises(StoreError, match="cannot open this store"):
        Lab.open("nosuch://bucket/lab")


def test_opening_an_unreachable_store_is_one_store_error(monkeypatch):
    s3fs = pytest.importorskip("s3fs", reason="the [s3] extra (dev installs it)")
    with absent_service_ports() as (closed, _):
        monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{closed}")
        for name, value in (("AWS_ACCESS_KEY_ID", "k"), ("AWS_SECRET_ACCESS_KEY", "s"),
                            ("AWS_DEFAULT_REGION", "us-east-1")):  # fmt: skip
            monkeypatch.setenv(name, value)
        s3fs.S3FileSystem.clear_instance_cache()
        try:
            with pytest.raises(StoreError, match="does not answer"):
                Lab.open("s3://lab/x")
        finally:
            s3fs.S3FileSystem.clear_instance_cache()
