"""JSON Schemas of the lab's YAML files, generated from the pydantic models that describe them, so editors
(VS Code's YAML extension and any other client of the YAML language server) complete and check those files.

- ``robot``: a robot description (``configs/robots/``, :class:`models.robot.RobotDescription`). A description
  that ``extends`` another gives only what it changes: with ``extends`` present the schema asks for no key, in
  any mapping the loader merges into the base's, and still refuses unknown keys and wrong types.
- ``experiment``: any experiment file (``configs/experiments/``), one definition per experiment kind
  (``anyOf``); ``experiment-<kind>`` is one kind's schema alone, which that kind's file names in its header
  (an experiment file is named after its kind: ``campaign.yaml`` → ``experiment-campaign``).
- ``grid``: a training grid (``configs/train/``, :class:`pipeline.grid_file.GridFile`).

The shipped copies are ``configs/schemas/<name>.schema.json``; ``vslab schema NAME --out FILE`` writes one.
Units are in each field's ``description``, defaults in its ``default``.
"""

from __future__ import annotations

import copy
import json
from typing import Any

from pydantic import BaseModel

DIALECT = "https://json-schema.org/draft/2020-12/schema"  # the draft pydantic emits
SCHEMAS = ("robot", "experiment", "grid")


def experiment_kinds() -> tuple[str, ...]:
    """The experiment kinds, each with its own schema ``experiment-<kind>``."""
    from acquisition.plans.experiment_files import EXPERIMENT_FILES

    return tuple(EXPERIMENT_FILES)


def schema_names() -> tuple[str, ...]:
    """Every name :func:`schema` knows: :data:`SCHEMAS`, then one ``experiment-<kind>`` per experiment kind
    (the files shipped in ``configs/schemas/``)."""
    return (*SCHEMAS, *(f"experiment-{kind}" for kind in experiment_kinds()))


def schema(name: str) -> dict:
    """The JSON Schema (draft 2020-12) called ``name`` (one of :func:`schema_names`); KeyError naming the
    known ones for any other."""
    if name == "robot":
        return robot_schema()
    if name == "grid":
        from pipeline.grid_file import GridFile

        return _document(GridFile)
    if name == "experiment":
        return experiment_schema()
    kind = name.removeprefix("experiment-")
    if name.startswith("experiment-") and kind in experiment_kinds():
        from acquisition.plans.experiment_files import EXPERIMENT_FILES

        return _document(EXPERIMENT_FILES[kind])
    raise KeyError(f"no schema {name!r} (known: {', '.join(schema_names())})")


def schema_text(name: str) -> str:
    """:func:`schema` as the text of its shipped file: indented JSON, keys in the models' order, a newline."""
    return json.dumps(schema(name), indent=2, ensure_ascii=False) + "\n"


def _document(model: type[BaseModel]) -> dict:
    """``model``'s JSON Schema as a document of its own: the dialect first."""
    return {"$schema": DIALECT, **model.model_json_schema()}


def experiment_schema() -> dict:
    """Any experiment file: one definition per kind (named after the kind's model), the file one of them."""
    from acquisition.plans.experiment_files import EXPERIMENT_FILES

    defs: dict[str, Any] = {}
    for model in EXPERIMENT_FILES.values():
        one = model.model_json_schema()
        defs |= one.pop("$defs", {})
        defs[model.__name__] = one
    return {
        "$schema": DIALECT,
        "title": "Experiment",
        "description": "An experiment file of configs/experiments/, named after its kind "
        f"({', '.join(f'{kind}.yaml' for kind in EXPERIMENT_FILES)}); experiment-<kind>.schema.json is one "
        "kind alone.",
        "anyOf": [{"$ref": f"#/$defs/{model.__name__}"} for model in EXPERIMENT_FILES.values()],
        "$defs": defs,
    }


# ------------------------------------------------------------------------------------------------- robot
PARTIAL = "Partial"  # suffix of a definition's copy that requires nothing (inside a description that extends)


def robot_schema() -> dict:
    """A robot description: a whole one, or (with ``extends``) only what differs from its base. In the latter
    every mapping the loader merges key by key into the base's requires nothing; a list replaces the base's
    whole, so its items stay whole."""
    from models.robot import RobotDescription

    whole = RobotDescription.model_json_schema()
    defs: dict[str, Any] = whole.pop("$defs")
    root = "RobotDescription"
    defs[root] = whole
    partial_root = _partial(copy.deepcopy(whole), defs)
    partial_root["properties"] = {
        "extends": {
            "type": "string",
            "minLength": 1,
            "description": "The description this one starts from: a robot name in configs/robots/ or a YAML "
            "file's path beside this one. Its mappings are merged key by key; any other value replaces the "
            "base's.",
        },
        **partial_root["properties"],
    }
    partial_root["description"] = "A description that extends another: only what differs, every key optional."
    defs[root + PARTIAL] = partial_root
    return {
        "$schema": DIALECT,
        "title": "Robot description",
        "description": whole.get("description", ""),
        # the whole description first (readers and the reference pages meet it first), then the partial one
        "if": {"required": ["extends"]},
        "else": {"$ref": f"#/$defs/{root}"},
        "then": {"$ref": f"#/$defs/{root}{PARTIAL}"},
        "$defs": dict(sorted(defs.items())),
    }


def _partial(node: Any, defs: dict[str, Any]) -> Any:
    """``node`` as a description that extends another may give it: no key required in it or in any mapping
    below it, a ``$ref`` to a definition's partial copy (made on first use), a ``oneOf`` relaxed to ``anyOf``
    (two partial mappings may both fit). Lists (``items``, ``prefixItems``) are kept whole."""
    if isinstance(node, list):
        return [_partial(item, defs) for item in node]
    if not isinstance(node, dict):
        return node
    node.pop("required", None)
    node.pop("discriminator", None)  # an annotation; the partial members need not carry the tag
    if "oneOf" in node:
        node["anyOf"] = node.pop("oneOf")
    ref = node.get("$ref", "")
    if ref.startswith("#/$defs/") and not ref.endswith(PARTIAL):
        name = ref.removeprefix("#/$defs/")
        if name + PARTIAL not in defs:
            defs[name + PARTIAL] = {}  # reserved first: a definition may refer to itself
            defs[name + PARTIAL] = _partial(copy.deepcopy(defs[name]), defs) | {
                "title": name + PARTIAL,
                "description": f"{name} in a description that extends another: every key optional.",
            }
        node["$ref"] = ref + PARTIAL
    for key, value in node.items():
        if key in ("properties", "$defs"):
            node[key] = {name: _partial(sub, defs) for name, sub in value.items()}
        elif key in ("anyOf", "allOf", "additionalProperties") and isinstance(value, dict | list):
            node[key] = _partial(value, defs)
    return node
