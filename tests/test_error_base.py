"""One exception base: every exception class vslab defines derives from ``VslabError`` through its layer's
base, so the CLI can turn any of them into one line (models/errors.py)."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

from acquisition.errors import AcquisitionError
from models.errors import ModelError, VslabError
from pipeline.errors import PipelineError

PACKAGES = ("models", "acquisition", "twin", "pipeline", "analysis", "vslab")
LAYER_BASE = {"models": ModelError, "acquisition": AcquisitionError, "pipeline": PipelineError}


def _modules():
    for name in PACKAGES:
        package = importlib.import_module(name)
        yield package
        for info in pkgutil.walk_packages(package.__path__, f"{name}."):
            yield importlib.import_module(info.name)


def _exception_classes():
    seen = set()
    for module in _modules():
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__ == module.__name__ and cls not in seen:
                seen.add(cls)
                yield cls


CLASSES = sorted(_exception_classes(), key=lambda c: f"{c.__module__}.{c.__qualname__}")


def test_the_scan_finds_the_project_s_errors():
    names = {c.__name__ for c in CLASSES}
    assert {"DeviceTimeoutError", "SessionError", "ModelIntegrityError", "RobotDescriptionError"} <= names


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: f"{c.__module__}.{c.__qualname__}")
def test_every_error_derives_from_the_base_of_its_layer(cls):
    if cls.__name__.startswith("_"):  # private control flow (an emulator's reject), never raised out
        return
    assert issubclass(cls, VslabError), f"{cls.__module__}.{cls.__qualname__} is not a VslabError"
    layer = cls.__module__.split(".")[0]
    if layer in LAYER_BASE and cls not in (VslabError, *LAYER_BASE.values()):
        assert issubclass(cls, LAYER_BASE[layer]), f"{cls.__qualname__} is not a {LAYER_BASE[layer].__name__}"
