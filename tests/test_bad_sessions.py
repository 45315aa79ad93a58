"""Bad sessions meet every command that reads session folders with one clear line, never a traceback.

The matrix: `vslab sessions list / info / recover` and `vslab build` × a damaged session beside good ones
(session.json corrupt, truncated, empty, random bytes, missing, without its protocol; an MCAP part corrupt,
truncated, empty, random bytes, without the session metadata; a folder without parts). Each cell checks the
exit status, the one `error:` line (or one `warning:` line for the bad session where the command goes on
with the rest), that nothing says "Traceback", that every file of the sessions folder is unchanged (a new
recovered copy of a torn part is what `recover` is for), and that nothing half-written is left in the lab.

Outcomes (what docs/how-to/record.md documents): `sessions list` marks a bad folder bad with a warning line
and lists the rest (exit 0); `sessions info` and `sessions recover` refuse a bad folder with one error line
(exit 2); `vslab build` skips a bad session with a warning line and builds the good ones (exit 0), or says no
session was usable (exit 2). A torn part (truncated) is not bad: it is listed as torn, recovered, or read up
to the tear. A part whose summary is whole is only read through by `build`, which finds its damage."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from typer.testing import CliRunner

from acquisition.recorder.sessions import SessionStore
from twin.runner import simulate_experiment
from vslab.cli import app

runner = CliRunner()
GOOD = 2  # good sessions beside the bad one
BAD = "broken"  # the bad one's folder


# ------------------------------------------------------------------------------------------ the damage
def _part(session: Path) -> Path:
    return sorted(session.glob("*.mcap"))[0]


def _random(n: int) -> bytes:
    return np.random.default_rng(7).bytes(max(n, 64))


def _card(s: Path) -> Path:
    return s / "session.json"


def _halve(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


DAMAGE = {
    "card-corrupt": lambda s: _card(s).write_text(_card(s).read_text().replace('"robot":', '"robot"')),
    "card-truncated": lambda s: _halve(_card(s)),
    "card-empty": lambda s: _card(s).write_bytes(b""),
    "card-random": lambda s: _card(s).write_bytes(_random(len(_card(s).read_bytes()))),
    "card-missing": lambda s: _card(s).unlink(),
    "card-no-protocol": lambda s: _card(s).write_text('{"robot": "vsl", "status": "complete"}\n'),
    "card-future": lambda s: _card(s).write_text(
        _card(s).read_text().replace('"schema_version": 2', '"schema_version": 9')
    ),
    "part-corrupt": lambda s: _garble_middle(_part(s)),
    "part-truncated": lambda s: _halve(_part(s)),
    "part-empty": lambda s: _part(s).write_bytes(b""),
    "part-random": lambda s: _part(s).write_bytes(_random(len(_part(s).read_bytes()))),
    "part-no-metadata": lambda s: _foreign_part(_part(s)),
    "no-parts": lambda s: _part(s).unlink(),
}


def _garble_middle(part: Path) -> None:
    """Random bytes over the middle third of the first chunk's data; the summary and indexes stay whole."""
    with open(part, "rb") as f:
        chunk = min(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = bytearray(part.read_bytes())
    lo = chunk.chunk_start_offset + chunk.chunk_length // 3
    hi = chunk.chunk_start_offset + 2 * chunk.chunk_length // 3
    data[lo:hi] = _random(hi - lo)[: hi - lo]
    part.write_bytes(bytes(data))


def _foreign_part(part: Path) -> None:
    """A whole MCAP file, but not a vslab recording: no ``vslab.session`` metadata record."""
    with open(part, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="another tool")
        sid = w.register_schema("lab_msgs/msg/Level", "ros2msg", b"float64 level\n")
        cid = w.register_channel("/level", "cdr", sid)
        for k in range(3):
            w.add_message(cid, 10 + k, b"\x00\x01\x00\x00" + np.float64(k).tobytes(), 10 + k)
        w.finish()


# Expected outcome per class: sessions list, info, recover, build (with the good ones).
# "warn": exit 0 and one warning line naming the bad session; "error": exit 2 and one error line;
# "ok": exit 0, no error or warning line (the folder is a readable session).
BAD_FOLDER = ("warn", "error", "error", "warn")
OUTCOMES = {
    "card-corrupt": BAD_FOLDER,
    "card-truncated": BAD_FOLDER,
    "card-empty": BAD_FOLDER,
    "card-random": BAD_FOLDER,
    "card-missing": BAD_FOLDER,
    "card-no-protocol": BAD_FOLDER,
    "card-future": BAD_FOLDER,  # a newer vslab's session: "update vslab"
    # a chunk fails its CRC (summary whole): list/info say so, recover cannot mend it, build leaves it out
    "part-corrupt": ("warn", "warn", "error", "warn"),
    "part-truncated": ("ok", "ok", "ok", "ok"),  # torn: listed as such, recovered, read to the tear
    "part-empty": BAD_FOLDER,
    "part-random": BAD_FOLDER,
    "part-no-metadata": ("ok", "ok", "ok", "warn"),  # whole MCAP, but not a vslab session: build says so
    "no-parts": BAD_FOLDER,
}
COMMANDS = ("list", "info", "recover", "build")


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """Two small twin campaign sessions (enough settled points to register the tracker)."""
    root = tmp_path_factory.mktemp("good")
    simulate_experiment(
        "campaign", SessionStore(root / "sessions"), seed=5, benches=GOOD, overrides={"points": 40}
    )
    return root / "sessions"


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> Path:
    """Cache and datasets every cell's lab shares: the good sessions' stages run once for the module."""
    return tmp_path_factory.mktemp("shared")


def _lab(tmp_path: Path, good: Path, shared: Path, damage: str | None) -> Path:
    lab = tmp_path / "lab"
    for s in sorted(good.iterdir()):
        shutil.copytree(s, lab / "sessions" / s.name)
    if damage:
        bad = lab / "sessions" / BAD
        shutil.copytree(sorted(good.iterdir())[0], bad)
        DAMAGE[damage](bad)
    for name in ("cache", "datasets"):
        (shared / name).mkdir(exist_ok=True)
        (lab / name).symlink_to(shared / name, target_is_directory=True)
    return lab


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def _invoke(lab: Path, *args: str):
    return runner.invoke(app, ["--lab", str(lab), "--quiet", *args])


def _lines(output: str, prefix: str) -> list[str]:
    return [ln for ln in output.splitlines() if ln.startswith(prefix)]


def _nothing_half_written(lab: Path) -> None:
    stray = [p for p in lab.rglob("*") if p.name.startswith(".") or p.name.endswith((".partial", ".tmp"))]
    stray += [p for p in (lab / "datasets").rglob(".*")]
    assert not stray, stray


# ------------------------------------------------------------------------------------------ the matrix
@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_bad_session_gets_one_clear_line(good, shared, tmp_path, damage, command):
    lab = _lab(tmp_path, good, shared, damage)
    before = _hashes(lab / "sessions")
    args = {"list": ["sessions", "list"], "info": ["sessions", "info", BAD],
            "recover": ["sessions", "recover", BAD], "build": ["build", "--name", "campaign"]}  # fmt: skip
    result = _invoke(lab, *args[command])
    out = result.output
    expected = OUTCOMES[damage][COMMANDS.index(command)]
    assert "Traceback" not in out, out
    assert result.exception is None or isinstance(result.exception, SystemExit), (result.exception, out)
    errors, warnings = _lines(out, "error:"), _lines(out, "warning:")
    if expected == "error":
        assert result.exit_code == 2, out
        assert len(errors) == 1 and not warnings, out
        assert BAD in errors[0], out  # names the file or folder
    elif expected == "warn":
        assert result.exit_code == 0, out
        assert not errors and len(warnings) == 1 and BAD in warnings[0], out
    else:
        assert result.exit_code == 0 and not errors and not warnings, out
    after = _hashes(lab / "sessions")
    if command == "recover" and damage == "part-truncated":
        added = set(after) - set(before)
        assert len(added) == 1 and added.pop().endswith(".recovered.mcap"), out
        after = {k: v for k, v in after.items() if k in before}
    assert after == before, f"{command} changed the user's files"
    _nothing_half_written(lab)
    if command == "build" and damage == "part-corrupt":
        assert f"from {GOOD + 1} sessions" in out and "damaged chunk at byte" in out, out  # less that chunk
    elif command == "build" and expected == "warn":
        assert f"from {GOOD} sessions" in out, out  # the good ones, never the bad one
    if command == "list":
        assert all(s.name in out for s in good.iterdir()), out  # the good sessions are listed too


def test_a_build_without_a_usable_session_says_so_and_writes_nothing(good, tmp_path):
    lab = tmp_path / "lab"
    for k, damage in enumerate(("card-corrupt", "card-missing", "part-random", "part-no-metadata")):
        bad = lab / "sessions" / f"bad{k}"
        shutil.copytree(sorted(good.iterdir())[0], bad)
        DAMAGE[damage](bad)
    before = _hashes(lab / "sessions")
    result = _invoke(lab, "build", "--name", "campaign")
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    assert len(_lines(result.output, "error:")) == 1, result.output
    assert len(_lines(result.output, "warning:")) == 4, result.output  # each bad session, with its reason
    assert _hashes(lab / "sessions") == before
    assert not (lab / "datasets").exists() or not any((lab / "datasets").rglob("*.parquet"))


def test_sessions_list_marks_each_bad_folder_and_lists_the_rest(good, shared, tmp_path):
    lab = _lab(tmp_path, good, shared, None)
    for damage in ("card-corrupt", "part-empty", "card-missing"):
        shutil.copytree(sorted(good.iterdir())[0], lab / "sessions" / damage)
        DAMAGE[damage](lab / "sessions" / damage)
    result = _invoke(lab, "sessions", "list")
    assert result.exit_code == 0 and "Traceback" not in result.output, result.output
    warnings = _lines(result.output, "warning:")
    assert len(warnings) == 3, result.output
    assert any("card-corrupt" in w and "not valid JSON" in w for w in warnings), result.output
    assert any("part-empty" in w and "empty file" in w for w in warnings), result.output
    assert any("card-missing" in w and "no session.json" in w for w in warnings), result.output
    assert all(s.name in result.output for s in good.iterdir()), result.output  # and the good ones


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--set", "clean.window=3"], "clean.window: no such parameter (those of clean: hampel_window"),
        (["--set", "cleaning.hampel_window=3"], "unknown stage 'cleaning'"),
        (["--set", "hampel_window=3"], "stage.key=value (stages: clean, segment, registration, splits)"),
        (["--set", "clean.hampel_window=wide"], "clean.hampel_window='wide': expected an integer"),
        (["--set", "clean.hampel_window=[7"], "--set clean.hampel_window=[7: the value is not YAML"),
        (["--set", "splits.seed=0.5"], "splits.seed=0.5: expected an integer"),
        (["--set", "registration.deflection=3"], "registration.deflection=3: expected true or false"),
        (["--set", "registration.from_dataset=nothing"], "from_dataset=nothing: no dataset 'nothing' under"),
        (["--set", "registration.from_dataset=nothing@0123"], "no dataset nothing@0123 under"),
    ],
)
def test_bad_stage_parameters_and_missing_registrations_are_one_line(good, tmp_path, args, says):
    lab = tmp_path / "lab"
    shutil.copytree(sorted(good.iterdir())[0], lab / "sessions" / "s")
    result = _invoke(lab, "build", "--name", "campaign", *args)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    (error,) = _lines(result.output, "error:")
    assert says in error, result.output
    assert not (lab / "datasets").exists() and not (lab / "cache").exists()  # checked before any work


def test_the_registration_stage_under_its_former_name_is_read_with_a_warning(good, tmp_path):
    """`--set register.…` (the stage's name before it was `registration`) still reaches the registration:
    one warning line naming the new name, then the same checks as under the new name."""
    lab = tmp_path / "lab"
    shutil.copytree(sorted(good.iterdir())[0], lab / "sessions" / "s")
    result = _invoke(lab, "build", "--name", "campaign", "--set", "register.from_dataset=nothing")
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    (warning,) = _lines(result.output, "warning:")
    assert "'register' is now 'registration'" in warning, result.output
    (error,) = _lines(result.output, "error:")
    assert "registration.from_dataset=nothing: no dataset 'nothing'" in error, result.output


def test_an_unknown_session_and_an_empty_lab(tmp_path):
    result = _invoke(tmp_path / "lab", "sessions", "info", "nope")
    assert result.exit_code == 2 and len(_lines(result.output, "error:")) == 1, result.output
    result = _invoke(tmp_path / "lab", "sessions", "list")
    assert result.exit_code == 0 and "Traceback" not in result.output, result.output
    result = _invoke(tmp_path / "lab", "build")
    assert result.exit_code == 2 and len(_lines(result.output, "error:")) == 1, result.output
