"""A simulated session records what made it (robot description, plan and parameters, twin code) and is reused
only by a run that would make it the same: a lab's sessions of another robot, other parameters or an older
vslab are refused in one line, never silently taken for this run's. A description given by path works for
every experiment."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquisition.recorder.sessions import SessionStore, list_sessions, read_card, session_info
from acquisition.schemas.session_card import SESSION_CARD
from models.robot import CONFIG_DIR, load_robot
from twin.identity import IDENTITY, StaleSessionsError, robot_sha256
from twin.runner import simulate_experiment
from vslab.cli import app

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()
# popup_impact cut to one pressure and one tap: two seconds of simulated time per session
SMALL = {"pressures_kpa": [50], "taps": 1, "settle_s": 0.5, "record_s": 0.5}
SETS = [a for k, v in SMALL.items() for a in ("--set", f"{k}={json.dumps(v)}")]


def _perturbed(path: Path, torque_constant: float = 9.0) -> Path:
    """A description named like the shipped POPUP arm but not the same robot (its drives' torque constant)."""
    path.write_text(f"extends: popup\nservo: {{torque_constant_nm_per_a: {torque_constant}}}\n")
    return path


def _files(sessions: Path) -> dict[str, str]:
    """Every file of a sessions folder by its bytes' hash: what a refused run must leave as it was."""
    return {str(p.relative_to(sessions)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(sessions.rglob("*")) if p.is_file()}  # fmt: skip


def _simulate(lab: Path, *args: str):
    return runner.invoke(app, ["--lab", str(lab), "--quiet", "simulate", "popup_impact", *SETS, *args])


def _refused(result, *says: str) -> str:
    assert result.exit_code == 2, result.output
    (line,) = [x for x in result.output.splitlines() if x.strip()]  # one line, no traceback
    joined = " ".join(result.output.split())
    assert line.startswith("error:") and all(s in joined for s in says), result.output
    return joined


@pytest.fixture(scope="module")
def popup_lab(tmp_path_factory) -> Path:
    """A lab with the nominal POPUP arm's popup_impact sessions (the shipped description)."""
    lab = tmp_path_factory.mktemp("lab")
    (report,) = simulate_experiment("popup_impact", SessionStore(lab / "sessions"), overrides=SMALL)
    assert len(report.sessions) == 1 and not report.skipped
    return lab


def _only_session(lab: Path) -> Path:
    (session,) = sorted((lab / "sessions").iterdir())
    return session


def test_a_session_records_what_made_it(popup_lab):
    identity = json.loads(read_card(_only_session(popup_lab))[IDENTITY])
    assert set(identity) == {"robot_sha256", "plan_sha256", "model", "code_version"}
    assert identity["model"] is None  # no learned model drove it
    from acquisition.plans.experiments import load_experiment
    from acquisition.plans.popup_experiments import bench_robot

    params = load_experiment("popup_impact", **SMALL)
    assert identity["robot_sha256"] == robot_sha256(bench_robot(load_robot("popup"), params))


def test_the_same_run_again_reuses_its_sessions(popup_lab):
    before = _files(popup_lab / "sessions")
    result = _simulate(popup_lab)
    assert result.exit_code == 0 and "0 sessions written, 1 already complete" in result.output, result.output
    assert _files(popup_lab / "sessions") == before


def test_a_perturbed_robot_is_refused_not_reused(popup_lab, tmp_path):
    """The finding: --set robot=<a perturbed description> into a lab of the nominal arm's sessions printed
    "0 sessions written, 1 already complete" and exit 0; Table 1 from them "recovered" the nominal values."""
    before = _files(popup_lab / "sessions")
    robot = _perturbed(tmp_path / "popup_perturbed.yaml")
    said = _refused(_simulate(popup_lab, "--set", f"robot={robot}"),
                    "sim-popup_impact-50kPa", "differs: robot description", "move them out of")  # fmt: skip
    assert "parameters" not in said and "code" not in said
    assert _files(popup_lab / "sessions") == before  # not reused, not overwritten


def test_changed_parameters_are_refused(popup_lab):
    before = _files(popup_lab / "sessions")
    said = _refused(_simulate(popup_lab, "--set", "tap_impulse_nms=0.03"), "differs: parameters")
    assert "robot description" not in said
    _refused(_simulate(popup_lab, "--seed", "3"), "differs: parameters")  # another seed: other noise
    assert _files(popup_lab / "sessions") == before


def test_an_edited_description_is_refused(tmp_path):
    """The same path, its file edited after the sessions were made (an ``extends:`` chain's file counts
    as the description's: the hash is of the description as resolved)."""
    robot = _perturbed(tmp_path / "mine.yaml", torque_constant=9.0)
    lab = tmp_path / "lab"
    made = _simulate(lab, "--set", f"robot={robot}")
    assert made.exit_code == 0 and "1 sessions written" in made.output, made.output
    again = _simulate(lab, "--set", f"robot={robot}")
    assert again.exit_code == 0 and "1 already complete" in again.output, again.output
    _perturbed(robot, torque_constant=9.5)
    _refused(_simulate(lab, "--set", f"robot={robot}"), "differs: robot description")
    # an edit one file up the extends chain counts too: the sessions moved away, made again from a chain
    shutil.rmtree(lab / "sessions")
    base = Path(shutil.copy(CONFIG_DIR / "popup.yaml", tmp_path / "base.yaml"))
    robot.write_text("extends: base.yaml\nservo: {torque_constant_nm_per_a: 9.5}\n")
    made = _simulate(lab, "--set", f"robot={robot}")
    assert made.exit_code == 0 and "1 sessions written" in made.output, made.output
    base.write_text(base.read_text().replace("mass_kg: 0.8, frame: q1", "mass_kg: 0.9, frame: q1"))
    _refused(_simulate(lab, "--set", f"robot={robot}"), "differs: robot description")


def test_a_session_of_an_older_vslab_is_read_and_built_but_not_reused(popup_lab, tmp_path):
    """A session made before identities were recorded: it lists, and `vslab build` selects it as before;
    rerunning over it is refused (what made it cannot be known), not reused."""
    lab = tmp_path / "lab"
    shutil.copytree(popup_lab, lab)
    session = _only_session(lab)
    card = json.loads((session / SESSION_CARD).read_text())
    del card[IDENTITY]
    (session / SESSION_CARD).write_text(json.dumps(card, indent=2) + "\n")
    assert session_info(session).status == "complete" and len(list_sessions(lab / "sessions")) == 1
    selected, bad = SessionStore(lab / "sessions").select("popup_impact")
    assert selected == [session] and not bad
    before = _files(lab / "sessions")
    _refused(_simulate(lab), "differs: unknown (no identity recorded: an older vslab)")
    assert _files(lab / "sessions") == before
    with pytest.raises(StaleSessionsError, match="1 complete session"):
        simulate_experiment("popup_impact", SessionStore(lab / "sessions"), overrides=SMALL)


def test_campaign_with_a_robot_path_writes_sessions(tmp_path):
    """The finding: `simulate campaign --set robot=PATH` wrote nothing ("0 sessions written, 0 already
    complete", exit 0): the plans named the robot "vsl", the batches looked for the path."""
    robot = shutil.copy(CONFIG_DIR / "vsl.yaml", tmp_path / "my_vsl.yaml")
    lab = tmp_path / "lab"
    sets = {"robot": robot, "points": 2, "settle_s": 0.3, "hold_s": 0.1}
    args = ["--lab", str(lab), "--quiet", "simulate", "campaign", "--benches", "1"]
    args += [a for k, v in sets.items() for a in ("--set", f"{k}={v}")]
    result = runner.invoke(app, args)
    assert result.exit_code == 0 and "1 sessions written" in result.output, result.output
    (session,) = sorted((lab / "sessions").iterdir())
    assert session_info(session).status == "complete"
    identity = json.loads(read_card(session)[IDENTITY])
    assert identity["robot_sha256"] == robot_sha256(load_robot("vsl"))  # a copy: the same robot


@pytest.mark.slow
def test_run_on_the_rig_with_a_robot_path(tmp_path):
    """`vslab run campaign --set robot=PATH --rig`: the plan's robot is found (it was a KeyError traceback)
    and the plan runs to its end on the rig, recorded as one complete session."""
    robot = shutil.copy(CONFIG_DIR / "vsl.yaml", tmp_path / "my_vsl.yaml")
    lab = tmp_path / "lab"
    proc = subprocess.run(
        [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "--quiet", "run", "campaign", "--set",
         f"robot={robot}", "--set", "points=1", "--set", "settle_s=0.3", "--set", "hold_s=0.1", "--rig",
         "--session", "by-path"],
        cwd=ROOT, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "complete" in proc.stdout
    assert session_info(lab / "sessions" / "by-path").status == "complete"


class _RigidInverse:
    """The simplest inverse model there is: the rigid IK's own joints (the first three inputs), unchanged."""

    def predict(self, inputs):
        return inputs[:, :3]


def test_a_session_is_never_reused_for_another_learned_model(tmp_path):
    """Experiment 2's hybrid sessions record which model drove them: the same model again reuses them,
    another model is refused, and a model that names no version is never taken for the one recorded."""
    from pipeline.in_loop import InverseModelCompensator
    from twin.identity import UNKNOWN_MODEL

    vsl = load_robot("vsl")
    small = {"commands": ["hybrid"], "rigid_arm": False, "repetitions": 1, "points_per_segment": 5,
             "settle_s": 0.2, "rest_s": 0.2, "cases": [{"payload_g": 25, "pressure_bar": 1.5}]}  # fmt: skip

    def run(identity):
        def compensator(plan):
            return InverseModelCompensator(_RigidInverse(), vsl, identity=identity)

        reports = simulate_experiment(
            "experiment2", SessionStore(tmp_path), overrides=small, inverse_model=compensator
        )
        return sum(len(r.sessions) for r in reports), sum(len(r.skipped) for r in reports)

    assert run("model-a") == (1, 0)
    (card,) = [read_card(p.parent) for p in tmp_path.glob(f"*/{SESSION_CARD}")]
    recorded = card[IDENTITY] if isinstance(card[IDENTITY], dict) else json.loads(card[IDENTITY])
    assert recorded["model"] == "model-a"
    assert run("model-a") == (0, 1)
    with pytest.raises(StaleSessionsError, match="learned model"):
        run("model-b")
    with pytest.raises(StaleSessionsError, match="learned model"):
        run(None)
    assert UNKNOWN_MODEL not in json.dumps(recorded)
