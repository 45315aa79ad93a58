"""The runners' library code (issue 30): a plan chosen, checked and given its compensator in one place, a
recording set up from a port map, a rig's devices found; each refusal is the project's error, one line,
raised before anything starts (the command line turns it into `error: …`)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import numpy as np
import pandas as pd
import pytest

from acquisition.errors import AcquisitionError
from acquisition.plans.compensation import CompensationError, StaticModelCompensator, compensator_for
from acquisition.plans.plan_run import PlanRunError, choose_plan, operator_prompts, ready_plan
from acquisition.recorder.recorder import Recorder, RecorderError
from acquisition.recorder.setup import SetupError, checked_ports, ports_file, session_id
from models.hybrid import INVERSE_INPUTS
from models.robot import load_robot
from pipeline.baselines import RigidModel
from pipeline.in_loop import InverseModelCompensator, learned_compensators
from twin.rig_process import RigError, rig_ports, session_devices

CASE = "experiment2/curve/vsl-1.5bar/25g"


@pytest.fixture(scope="module")
def plans():
    """Experiment 2's three plans of one case (ik, static, hybrid) and the robot they run on."""
    chosen = {c: choose_plan("experiment2", f"{CASE}/{c}") for c in ("ik", "static", "hybrid")}
    return {c: p for c, (p, _) in chosen.items()}, chosen["ik"][1]


def _rigid_inverse() -> RigidModel:
    """A real inverse model with nothing learned: it commands the IK it is given."""
    return RigidModel("inverse").fit(pd.DataFrame(columns=list(INVERSE_INPUTS), dtype=float))


def test_the_compensator_is_chosen_by_the_plan_s_commands(plans):
    by_commands, desc = plans
    assert compensator_for(by_commands["ik"], desc) is None
    assert isinstance(compensator_for(by_commands["static"], desc), StaticModelCompensator)
    with pytest.raises(CompensationError, match="hybrid commands need a trained inverse model"):
        compensator_for(by_commands["hybrid"], desc)
    learned = learned_compensators({"hybrid": _rigid_inverse()}, desc, {"hybrid": "rigid@test"})
    first, second = (compensator_for(by_commands["hybrid"], desc, learned) for _ in range(2))
    assert isinstance(first, InverseModelCompensator) and first is not second  # one per session
    assert first.identity == "rigid@test"
    q_ik = np.array([[0.1, 0.5, -0.9]])
    np.testing.assert_allclose(first(q_ik, np.full((1, 2), 1.5e5), np.zeros((1, 3))), q_ik)


def test_learned_compensators_refuse_commands_they_have_no_model_for(plans):
    by_commands, desc = plans
    history = by_commands["hybrid"].parameters | {"commands": "history"}
    plan = dataclasses.replace(by_commands["hybrid"], parameters=history)
    with pytest.raises(CompensationError, match="history commands need a trained inverse model"):
        compensator_for(plan, desc, learned_compensators({"hybrid": _rigid_inverse()}, desc))


def test_a_plan_is_refused_before_anything_starts(plans):
    by_commands, desc = plans
    with pytest.raises(PlanRunError, match="experiment1 has no plan '99999'; its plans"):
        choose_plan("experiment1", "99999")
    with pytest.raises(PlanRunError, match="hybrid commands need a trained inverse model"):
        ready_plan(by_commands["hybrid"], desc)
    with pytest.raises(PlanRunError, match=r"^not from this lab$"):
        ready_plan(by_commands["static"], desc, refused={"static": "not from this lab"})
    assert isinstance(ready_plan(by_commands["static"], desc), StaticModelCompensator)
    assert issubclass(PlanRunError, AcquisitionError)


def test_an_unsafe_plan_is_refused_naming_the_limit():
    plan, desc = choose_plan("experiment1", "0", {"pressures_bar": [5]})  # above the links' 2 bar
    with pytest.raises(PlanRunError, match=r"safety limit\(s\): refused, nothing was started:\n") as refused:
        ready_plan(plan, desc)
    assert "channel 0 set to 500000 Pa > 200000 Pa" in str(refused.value)


def test_operator_prompts_say_what_to_do():
    asked: list[str] = []
    payload, tap = operator_prompts(asked.append)
    payload(0.025)
    tap(0.004)
    assert asked == ["hang 25 g at the end-effector, then press Enter",
                     "tap the link (≈ 4 mN·m·s), then press Enter"]  # fmt: skip


def test_session_ids_ports_and_sessions_are_checked(tmp_path):
    vsl = load_robot("vsl")
    assert session_id(None, "20260101-rig") == "20260101-rig"
    with pytest.raises(SetupError, match=r"^--session '\.\./x': a session id is a folder name"):
        session_id("../x", "unused")
    broken = tmp_path / "ports.json"
    broken.write_text("{not json")
    with pytest.raises(SetupError, match="not a ports file"):
        ports_file(broken)
    broken.write_text(json.dumps({"ports": {"servo_bus": str(broken)}}))
    assert ports_file(broken) == {"servo_bus": str(broken)}
    with pytest.raises(SetupError, match=r"servo_bus: .*a regular file, not a serial port"):
        checked_ports(vsl, ports_file(broken), "here")
    with pytest.raises(SetupError, match="gripper: vsl has no such device"):
        checked_ports(vsl, {"gripper": "/dev/null"}, "here")
    (tmp_path / "sessions" / "s1").mkdir(parents=True)
    (tmp_path / "sessions" / "s1" / "s1_000.mcap").write_bytes(b"")
    with pytest.raises(RecorderError, match="session s1 exists already"):
        Recorder(vsl, {"servo_bus": "/dev/null"}, tmp_path / "sessions" / "s1", "s1")
    with pytest.raises(RecorderError, match=r"none of vsl's devices \(.*\) is in the port map \(gripper\)"):
        Recorder(vsl, {"gripper": "/dev/null"}, tmp_path / "sessions" / "s2", "s2")


def test_a_rig_s_devices_are_found_or_refused_in_one_line(tmp_path):
    vsl = load_robot("vsl")
    with pytest.raises(RigError, match=r"no ports\.json in this folder"):
        rig_ports(tmp_path)
    refusals = [(tmp_path, tmp_path, "with --rig: --rig starts a rig"),
                (tmp_path / "nothing", None, "no ports file or rig directory there")]  # fmt: skip
    for ports, rig_dir, says in refusals:
        with pytest.raises(SetupError, match=says), session_devices(vsl, ports, rig_dir):
            pass
    assert not (tmp_path / "robot.yaml").exists()  # refused before a rig was started


def test_session_devices_stop_a_session_on_sigterm_as_on_ctrl_c(tmp_path):
    vsl = load_robot("vsl")
    master, slave = os.openpty()  # a serial port (nothing answers; nothing opens it here)
    try:
        ports = tmp_path / "ports.json"
        ports.write_text(json.dumps({"servo_bus": os.ttyname(slave)}))
        before = signal.getsignal(signal.SIGTERM)
        with session_devices(vsl, ports) as (port_map, rig_dir):
            assert port_map == {"servo_bus": os.ttyname(slave)} and rig_dir is None
            assert signal.getsignal(signal.SIGTERM) is signal.default_int_handler
        assert signal.getsignal(signal.SIGTERM) is before
    finally:
        os.close(master)
        os.close(slave)
