"""The `vslab` app, the options every command shares, and small helpers (commands: cli, recording)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from models.robot import RobotDescriptionError, load_robot

app = typer.Typer(
    help="vslab: log, train and plot for soft variable-stiffness-link robots.", no_args_is_help=True
)
robots_app = typer.Typer(help="Robot descriptions in configs/robots/.", no_args_is_help=True)
twin_app = typer.Typer(help="The digital twin.", no_args_is_help=True)
app.add_typer(robots_app, name="robots")
app.add_typer(twin_app, name="twin")
sessions_app = typer.Typer(help="Recorded sessions in <lab>/sessions/.", no_args_is_help=True)
app.add_typer(sessions_app, name="sessions")

console = Console()


class Settings:
    """Options every command shares (set by the top-level callback)."""

    lab: Path = Path("lab")
    quiet: bool = False


@app.callback()
def main(
    lab: Annotated[
        Path, typer.Option(help="Lab directory (sessions, datasets, models, figures).", envvar="VSLAB_LAB")
    ] = Path("lab"),
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
) -> None:
    """Options shared by every command."""
    Settings.lab = lab
    Settings.quiet = quiet
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(levelname)s %(message)s")


def _fail(message: str) -> None:
    console.print(f"[red]error:[/red] {message}", soft_wrap=True, highlight=False)
    raise typer.Exit(code=2)


def _robot(name: str):
    try:
        return load_robot(name)
    except RobotDescriptionError as exc:
        _fail(str(exc))


def _overrides(pairs: list[str]) -> dict:
    """``key=value`` pairs (values parsed as YAML: numbers, lists, booleans)."""
    import yaml

    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            _fail(f"--set takes key=value, got {pair!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out


def inverse_compensator(version: str, robot_name: str, lab: Path | None = None):
    """A registered inverse model of ``lab`` (default: the CLI's) as the runners' compensator for
    ``robot_name`` (fails clearly)."""
    from pipeline.in_loop import InverseModelCompensator
    from pipeline.registry import find, load_model

    try:
        model, _ = load_model(find(Path(lab or Settings.lab) / "models", version))
    except (FileNotFoundError, ValueError) as exc:
        _fail(str(exc))
    if model.config.direction != "inverse":
        _fail(f"model {version} is a {model.config.direction} model; hybrid commands need an inverse one")
    return InverseModelCompensator(model, _robot(robot_name))
