"""The command line's reference: every command and group of the typer app, with its help, its arguments and
its options (type, default, help), walked through the click command typer builds from it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

NONE = "—"
ROOT = str(Path(__file__).resolve().parents[2]) + "/"


def _cell(text: Any) -> str:
    return " ".join(str(text).split()).replace("|", "\\|") or NONE


def _prose(text: str) -> str:
    """Help text as Markdown shows it: ``<lab>`` is a placeholder, not an HTML tag."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _default(param: Any) -> str:
    if param.required:
        return "required"
    default = param.default
    if callable(default) or default is None:
        return NONE
    if getattr(param, "is_flag", False):
        return "on" if default else "off"
    if isinstance(default, list | tuple):
        return ", ".join(f"`{v}`" for v in default) or NONE
    return f"`{str(default).replace(ROOT, '')}`"  # a path in the checkout, as the reader's checkout has it


def _param_rows(command: Any, ctx: Any) -> list[str]:
    rows = []
    for param in command.params:
        if getattr(param, "hidden", False):
            continue
        if param.param_type_name == "argument":
            name = f"`{(param.metavar or param.name).upper()}`"
        else:
            name = ", ".join(f"`{o}`" for o in (*param.opts, *param.secondary_opts))
        kind = param.display_type(ctx).strip("<>") if hasattr(param, "display_type") else param.type.name
        help_text = _prose(getattr(param, "help", None) or NONE)
        if getattr(param, "envvar", None) and getattr(param, "show_envvar", False):
            help_text += f" (environment variable `{param.envvar}`)"
        cells = (name, param.param_type_name, kind, _default(param), help_text)
        rows.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return rows


def _command(command: Any, ctx: Any, level: int) -> list[str]:
    path = ctx.command_path
    out = [f"{'#' * level} `{path}`", ""]
    if command.help:
        out += [_prose(command.help.strip()), ""]
    usage = " ".join(command.collect_usage_pieces(ctx))
    out += ["```text", f"{path} {usage}".rstrip(), "```", ""]
    rows = _param_rows(command, ctx)
    if rows:
        out += ["| Name | Kind | Type | Default | Help |", "|---|---|---|---|---|", *rows, ""]
    if hasattr(command, "list_commands"):
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is None or sub.hidden:
                continue
            sub_ctx = sub.context_class(sub, info_name=name, parent=ctx)
            out += _command(sub, sub_ctx, min(level + 1, 4))
    return out


def render(app: Any, name: str) -> str:
    """The page of a typer ``app`` installed as the command ``name``."""
    import typer.main

    command = typer.main.get_command(app)
    ctx = command.context_class(command, info_name=name)
    intro = (
        f"Every command of `{name}`, generated from the code at each build (the text of `{name} --help`). "
        "Options of a group come before its command's name: `vslab --lab lab demo --quick`."
    )
    return "\n".join(["# Command line", "", intro, "", *_command(command, ctx, 2)])
