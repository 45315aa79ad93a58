"""The configuration files' reference: every field of a pydantic model's JSON Schema, with its type, unit,
default and description, one table per model (the root first, then the models it uses, as they appear)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator

from models.units import unit_of_name

NONE = "—"  # what the code does not say


def unit(name: str, prop: dict) -> str:
    """The field's unit: the schema's own ``unit`` key where the model sets one, else its name's suffix."""
    if prop.get("unit"):
        return str(prop["unit"])
    return unit_of_name(name) or NONE


def _ref_name(ref: str) -> str:
    return ref.rsplit("/", 1)[-1]


def _anchor(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def _bounds(prop: dict) -> str:
    marks = (("exclusiveMinimum", ">"), ("minimum", "≥"), ("exclusiveMaximum", "<"), ("maximum", "≤"))
    parts = [f"{sign} {prop[key]}" for key, sign in marks if key in prop]
    if "minItems" in prop and prop.get("minItems") == prop.get("maxItems"):
        parts.append(f"{prop['minItems']} items")
    elif "minItems" in prop:
        parts.append(f"≥ {prop['minItems']} items")
    return f" ({', '.join(parts)})" if parts else ""


def type_of(prop: dict) -> str:
    """A field's type in words, other models linked to their table."""
    if "$ref" in prop:
        name = _ref_name(prop["$ref"])
        return f"[{name}](#{_anchor(name)})"
    for key in ("oneOf", "anyOf", "allOf"):
        if key in prop:
            words = [type_of(p) for p in prop[key] if p.get("type") != "null"]
            optional = " or null" if any(p.get("type") == "null" for p in prop[key]) else ""
            return " or ".join(words) + optional + _bounds(prop)
    if "const" in prop:
        return f"`{json.dumps(prop['const'])}`"
    if "enum" in prop:
        return "one of " + ", ".join(f"`{json.dumps(v)}`" for v in prop["enum"])
    kind = prop.get("type", "any")
    if kind == "array":
        items = prop.get("prefixItems") or [prop.get("items", {})]
        inner = ", ".join(dict.fromkeys(type_of(p) for p in items))
        return f"list of {inner}{_bounds(prop)}"
    if kind == "object" and isinstance(prop.get("additionalProperties"), dict):
        return f"map of name → {type_of(prop['additionalProperties'])}"
    return f"{kind}{_bounds(prop)}"


def _cell(text: str) -> str:
    """Text fit for one table cell (one line, pipes escaped)."""
    return " ".join(str(text).split()).replace("|", "\\|") or NONE


def _prose(text: str) -> str:
    """A description as Markdown shows it: ``<name>`` is a placeholder, not an HTML tag."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _default(name: str, prop: dict, required: set[str]) -> str:
    """Required (with the shipped file's value where the schema gives one, as an experiment's does), the
    default, or — ."""
    if name in required:
        shipped = (
            f" (shipped: `{json.dumps(prop['default'], ensure_ascii=False)}`)" if "default" in prop else ""
        )
        return "required" + shipped
    if "default" not in prop:
        return NONE
    return f"`{json.dumps(prop['default'], ensure_ascii=False)}`"


def _models(schema: dict) -> Iterator[tuple[str, dict]]:
    """The root model, then every model it uses, each once, in the order the tables first refer to them."""
    defs = schema.get("$defs", {})
    seen: list[str] = []
    queue = [(schema.get("title", "root"), schema)]
    while queue:
        name, model = queue.pop(0)
        if name in seen:
            continue
        seen.append(name)
        yield name, model
        # a conditional root's ``then`` (the partial models of a description that ``extends`` another) is told
        # in a sentence (:func:`_partial`), not in tables of its own
        text = json.dumps({k: v for k, v in model.items() if k not in ("$defs", "if", "then")})
        for ref in sorted(set(_refs(text)), key=text.index):
            queue.append((_ref_name(ref), defs[_ref_name(ref)]))


def _refs(text: str) -> list[str]:
    return [part.split('"', 1)[0] for part in text.split('"$ref": "')[1:]]


def _partial(schema: dict) -> list[str]:
    """The sentence of a root ``if: {required: [key]}, then: partial, else: full`` and the partial's own
    fields (those the full model lacks)."""
    keys = schema["if"].get("required", [])
    defs = schema.get("$defs", {})
    full, partial = (defs[_ref_name(schema[k]["$ref"])] for k in ("else", "then"))
    extra = {k: v for k, v in partial.get("properties", {}).items() if k not in full.get("properties", {})}
    name = _ref_name(schema["else"]["$ref"])
    out = [f"A file is a [{name}](#{_anchor(name)}); "
           f"one with {', '.join(f'`{k}`' for k in keys)} gives only what it changes: the same fields, none "
           "required, and these:", "", "| Field | Type | Description |", "|---|---|---|"]  # fmt: skip
    out += ["| " + " | ".join(_cell(c) for c in (f"`{k}`", type_of(v), v.get("description", NONE))) + " |"
            for k, v in extra.items()]  # fmt: skip
    return [*out, ""]


def render(title: str, intro: str, schema: dict) -> str:
    """The page of one configuration file from its JSON Schema (pydantic's ``model_json_schema()``)."""
    out = [f"# {title}", "", intro, ""]
    for name, model in _models(schema):
        out += [f"## {name} {{#{_anchor(name)}}}", ""]
        if model.get("description"):
            out += [_prose(" ".join(model["description"].split())), ""]
        properties = model.get("properties", {})
        if "if" in model and "then" in model and "else" in model:
            out += _partial(model)
            continue
        if not properties:
            out += [f"Type: {type_of(model)}.", ""]
            continue
        required = set(model.get("required", []))
        out += ["| Field | Type | Unit | Default | Description |", "|---|---|---|---|---|"]
        for field, prop in properties.items():
            cells = (f"`{field}`", type_of(prop), unit(field, prop), _default(field, prop, required),
                     _prose(prop.get("description", NONE)))  # fmt: skip
            out.append("| " + " | ".join(_cell(c) for c in cells) + " |")
        out.append("")
    return "\n".join(out)
