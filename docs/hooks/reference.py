"""MkDocs hook: the reference pages, generated from the code at every build so that they cannot drift from it.

Each page of ``PAGES`` is rendered by a function of the modules beside this one and added to the site as a
generated file; a page the code cannot render stops the build with a message naming it."""

from __future__ import annotations

import importlib
from collections.abc import Callable

import ref_cli
import ref_data
import ref_schemas
from mkdocs.config.defaults import MkDocsConfig
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

# The modules a lab's programmer calls, in the order they meet them (api.md renders them with mkdocstrings).
API_MODULES = (
    "pipeline.lab", "twin.runner", "acquisition.recorder.recorder", "pipeline.build",
    "pipeline.dataset_store",
    "pipeline.train", "pipeline.grid", "pipeline.model_store", "analysis.lab_figures", "analysis.lab_report",
    "analysis.report",
    "models.robot",
)  # fmt: skip

SCHEMAS = {  # page → (vslab.schemas name, title, what the file is)
    "reference/robot-description.md": ("robot", "Robot description", "`configs/robots/<name>.yaml`"),
    "reference/experiments.md": ("experiment", "Experiments", "`configs/experiments/<name>.yaml`"),
    "reference/training-grid.md": ("grid", "Training grid", "`configs/train/<name>.yaml`"),
}


def _schema(name: str) -> dict:
    """The JSON Schema ``vslab.schemas.schema(name)`` gives (what `vslab schema` writes and editors check)."""
    try:
        schemas = importlib.import_module("vslab.schemas")
    except ModuleNotFoundError as exc:
        raise PluginError(
            f"the configuration reference needs vslab/schemas.py (schema('{name}') → JSON Schema): {exc}"
        ) from exc
    return schemas.schema(name)


def _schema_page(uri: str) -> str:
    name, title, where = SCHEMAS[uri]
    intro = (f"Every field of {where}, from its JSON Schema (`vslab.schemas.schema(\"{name}\")`, the "
             "pydantic models'), generated at each build. Units come from the field's name (`_m`, `_hz`, "
             "`_pa`, …) where the schema names none; `—`: the code says nothing.\n\n"
             "**In your editor:** the schemas ship in `configs/schemas/` (`vslab schema NAME` prints one), "
             "and every YAML of `configs/` names its own on its first line, "
             "`# yaml-language-server: $schema=../schemas/<name>.schema.json`: with VS Code's YAML extension "
             "(or any client of the YAML language server) a file completes its keys, shows each one's "
             "description and unit, and marks a wrong key or value as you type. Give a file of your own the "
             "same first line, with the path to the schema.")  # fmt: skip
    return ref_schemas.render(title, intro, _schema(name))


def api_page() -> str:
    intro = ("The Python API a lab's programmer calls, from the docstrings (mkdocstrings). The command line "
             "([CLI](cli.md)) is a thin layer over these.")  # fmt: skip
    return "\n".join(["# Python API", "", intro, "", *(f"::: {m}\n" for m in API_MODULES)])


def _cli_page() -> str:
    from vslab.cli import app

    return ref_cli.render(app, "vslab")


PAGES: dict[str, Callable[[], str]] = {
    "reference/cli.md": _cli_page,
    **{uri: (lambda uri=uri: _schema_page(uri)) for uri in SCHEMAS},
    "reference/topics.md": ref_data.topics,
    "reference/dataset-columns.md": ref_data.dataset_columns,
    "reference/model-card.md": ref_data.model_card,
    "reference/api.md": api_page,
}


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add every generated reference page; a file of the same name in docs/ would hide one: refused."""
    for uri, render in PAGES.items():
        if files.get_file_from_path(uri) is not None:
            raise PluginError(f"docs/{uri} is generated from the code: remove the file")
        try:
            content = render()
        except PluginError:
            raise
        except Exception as exc:
            raise PluginError(f"docs/{uri}: cannot be generated from the code: {exc!r}") from exc
        files.append(File.generated(config, uri, content=content))
    return files
