"""The `vslab` app, the options every command shares, and small helpers (commands: cli, recording)."""

from __future__ import annotations

import logging
import re
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer
import yaml
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup

from acquisition.storage import StoreError
from models.errors import VslabError
from models.robot import RobotDescriptionError, load_robot
from pipeline.lab import Lab

if TYPE_CHECKING:  # torch: imported by the commands that use models
    import pandas as pd

    from pipeline.model_store import ModelStore

try:  # typer ≥ 0.2x carries its own click, whose exceptions derive from TyperException
    from typer import TyperException as _ClickError
    from typer._click.globals import get_current_context  # its context stack, not click's
except ImportError:  # pragma: no cover - older typer on click
    from click import ClickException as _ClickError
    from click import get_current_context


class _Group(TyperGroup):
    """The top-level command group: a usage error (an unknown option, a value of the wrong type, a missing
    argument) ends in one `error:` line like every other user error, not in a panel."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except _ClickError as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":  # `vslab models`: the group's help is shown
                sys.exit(exc.exit_code)
            ctx = getattr(exc, "ctx", None)
            hint = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
            _print_error(f"{exc.format_message()}{hint}")
            sys.exit(getattr(exc, "exit_code", 2))
        except typer.Abort:
            console.print("aborted")
            sys.exit(1)
        except VslabError as exc:  # an error no command caught: still one line, never a traceback
            _print_error(str(exc))
            sys.exit(2)
        sys.exit(code if isinstance(code, int) else 0)


HELP = "vslab: log, train and plot for soft variable-stiffness-link robots."
app = typer.Typer(help=HELP, no_args_is_help=True, cls=_Group)
robots_app = typer.Typer(help="Robot descriptions in configs/robots/.", no_args_is_help=True)
twin_app = typer.Typer(help="The digital twin.", no_args_is_help=True)
app.add_typer(robots_app, name="robots")
app.add_typer(twin_app, name="twin")
sessions_app = typer.Typer(help="Recorded sessions in <lab>/sessions/.", no_args_is_help=True)
app.add_typer(sessions_app, name="sessions")

console = Console()


@dataclass(frozen=True)
class Options:
    """Options every command shares: the top-level callback opens the lab once and puts these in the typer
    context, where each command finds them (:func:`options`)."""

    lab: Lab
    quiet: bool = False


def options() -> Options:
    """The shared options of the command that runs now (the context object the top-level callback set)."""
    found = get_current_context().find_object(Options)
    if found is None:  # a command run without the app's callback: a programming error, not a user's
        raise RuntimeError("no vslab options in this command's context: run it through `vslab.app.app`")
    return found


LAB_HELP = ("The lab: a folder, or an fsspec URL such as s3://bucket/prefix (credentials from the store's "
            "own environment: AWS_* variables, ~/.aws).")  # fmt: skip


@app.callback()
def main(
    ctx: typer.Context,
    lab: Annotated[str, typer.Option(help=LAB_HELP, envvar="VSLAB_LAB")] = "lab",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
) -> None:
    """Options shared by every command."""
    try:
        ctx.obj = Options(Lab.open(lab), quiet)
    except StoreError as exc:
        _error(f"--lab {exc}")
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(levelname)s %(message)s")


def local_lab(command: str) -> Lab:
    """The lab for a command that records (or runs a rig): a local folder, or one error line. A recording is
    never written to a store directly (a network stall must not cost a sample): record into a local lab,
    then publish with `vslab --lab URL sessions upload`."""
    lab = options().lab
    if not lab.is_local:
        _error(f"{command} records into a local lab, not {lab}: give --lab FOLDER, then publish "
               f"with `vslab --lab {lab} sessions upload FOLDER/sessions/ID`")  # fmt: skip
    return lab


def _print_error(message: str) -> None:
    console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True, highlight=False)


def _fail(message: str) -> NoReturn:
    """One `error:` line (``message`` is rich markup: escape what the user typed) and exit status 2."""
    console.print(f"[red]error:[/red] {message}", soft_wrap=True, highlight=False)
    raise typer.Exit(code=2)


def _error(message: str) -> NoReturn:
    """One `error:` line with ``message`` shown as it is (no markup) and exit status 2."""
    _print_error(message)
    raise typer.Exit(code=2)


def _robot(name: str):
    try:
        return load_robot(name)
    except RobotDescriptionError as exc:
        _error(str(exc))


def pretraining_twin(option: str, robot: str):
    """The description ``robot`` a command was given as ``option`` to pretrain the hybrid nets on (its
    campaign is simulated into the lab: ``pipeline.pretrain``), or one error line: not a description, not the
    VSL arm, a lab on a store."""
    from pipeline.pretrain import PretrainError, twin_robot

    try:
        description = twin_robot(_robot(robot))
    except PretrainError as exc:
        _error(f"{option} {robot}: {exc}")
    if not options().lab.is_local:
        _error(f"{option}: the twin's campaign is simulated into the lab, and {options().lab} is on a store")
    return description


def load_dataset(option: str, reference: str) -> tuple[pd.DataFrame, str]:
    """The dataset a command was given as ``option`` (``NAME`` or ``NAME@VERSION``) from the lab: its rows (D)
    and ``name@version``, or one error line that names the option."""
    name, _, version = reference.partition("@")
    try:
        data, card = options().lab.datasets.load(name, version or None)
    except FileNotFoundError as exc:  # the store's DatasetNotFound says what is there and how to build it
        _error(f"{option} {reference}: {exc}")
    except (OSError, ValueError) as exc:
        _error(f"{option} {reference}: cannot be read ({type(exc).__name__}: {exc}); build it again")
    return data, f"{name}@{card['version']}"


# ------------------------------------------------------------------------------------------------ --set
class CommandLineError(VslabError, ValueError):
    """Base of the command line's own errors (what a user typed)."""


class SetError(CommandLineError):
    """A ``--set`` pair that cannot be used: no ``=``, a key that is not a name, a key given twice, a value
    that is not YAML or not a plain value. The message starts with ``--set`` and the pair."""


_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")
_FLOAT_TAG, _TIMESTAMP_TAG = "tag:yaml.org,2002:float", "tag:yaml.org,2002:timestamp"


class _SetLoader(yaml.SafeLoader):
    """YAML for ``--set`` values: floats as YAML 1.2 writes them (``1e-4``, not only ``1.0e-4``), dates kept
    as text (a protocol or grid takes no date)."""


_SetLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (_FLOAT_TAG, _TIMESTAMP_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_SetLoader.add_implicit_resolver(
    _FLOAT_TAG,
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9][0-9_]*(?:\.[0-9_]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+0123456789."),
)


def _plain(value) -> bool:
    """Is ``value`` made of what JSON holds (null, booleans, numbers, text, lists, text-keyed mappings)?"""
    if value is None or isinstance(value, bool | int | float | str):
        return True
    if isinstance(value, list):
        return all(_plain(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _plain(v) for k, v in value.items())
    return False


def _shown(pair: str, width: int = 60) -> str:
    """A pair as an error line shows it: on one line (control characters escaped), cut to ``width``."""
    pair = pair if pair.isprintable() else repr(pair)[1:-1]
    return pair if len(pair) <= width else pair[: width - 1] + "…"


def parse_set(pairs: list[str]) -> dict:
    """``key=value`` pairs → {key: value}; values are YAML (numbers, true/false, text, [lists], {mappings}).
    Raises :class:`SetError` (and nothing else) for a pair that cannot be used, naming it."""
    out: dict = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        key, shown = key.strip(), _shown(pair)
        if not sep:
            raise SetError(f"--set {shown!r}: expected key=value (e.g. --set points=2000)")
        if not _KEY.fullmatch(key):
            name = _shown(key, 30)
            raise SetError(f"--set {shown!r}: {name!r} is not a parameter name (letters, digits, _ and .)")
        if key in out:
            raise SetError(f"--set {key} is given twice: give each parameter once")
        try:
            value = yaml.load(text, Loader=_SetLoader)  # a SafeLoader: builds no objects
        except yaml.YAMLError as exc:
            problem = _shown(getattr(exc, "problem", None) or str(exc).splitlines()[0], 80)
            raise SetError(f"--set {shown}: the value is not YAML ({problem}; quote text: k='a b')") from None
        except (ValueError, OverflowError, RecursionError) as exc:  # too many digits, nested too deep
            raise SetError(f"--set {shown}: the value cannot be read ({type(exc).__name__})") from None
        if not _plain(value):
            raise SetError(f"--set {shown}: the value must be a number, text, true/false, a [list] or a "
                           "{mapping}")  # fmt: skip
        out[key] = value
    return out


def _overrides(pairs: list[str]) -> dict:
    """``key=value`` pairs (values parsed as YAML: numbers, lists, booleans); a bad one is one error line."""
    try:
        return parse_set(pairs)
    except SetError as exc:
        _error(str(exc))


# ------------------------------------------------------------------------------------------------ models
HISTORY_NOT_STORED = (
    "history commands need a history-aware inverse model, which the model store does not keep (it keeps "
    "networks): the main job trains one in process (`vslab demo`); run without them: "
    "--set 'commands=[ik,static,hybrid]'"
)


def load_inverse_model(version: str, models: ModelStore | None = None):
    """The saved inverse network ``version`` of ``models`` (default: the CLI's lab's) as the control
    loop runs it: its ONNX export on ONNX Runtime (``predict``), every file checked against its card first. An
    unknown, ambiguous, damaged or forward model, or one saved without an ONNX export, is one error line."""
    try:
        return (models or options().lab.models).inverse_onnx(version)[0]
    except (FileNotFoundError, ValueError) as exc:  # unknown, ambiguous, damaged, forward
        _error(f"--inverse-model {version}: {exc}")


def inverse_compensators(version: str, models: ModelStore | None = None):
    """A saved inverse model of ``models`` (default: the CLI's lab's) as the runners' hybrid commands
    (``pipeline.in_loop.learned_compensators``); an unusable model is one error line."""
    from pipeline.in_loop import learned_compensators

    try:
        model, identity = (models or options().lab.models).inverse_onnx(version)
        return learned_compensators({"hybrid": model}, identities={"hybrid": identity})
    except (FileNotFoundError, ValueError) as exc:  # unknown, ambiguous, damaged, forward
        _error(f"--inverse-model {version}: {exc}")


def inverse_model_version(version: str, models: ModelStore | None = None) -> str:
    """The full version id of the saved model ``version`` (a tag or a unique prefix) of ``models``
    (default: the CLI's lab's)."""
    return (models or options().lab.models).find(version).name
