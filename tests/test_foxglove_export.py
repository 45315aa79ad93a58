"""Sessions ready-made for Foxglove: the standard messages, checked against the reference ROS 2 decoder, and
``vslab sessions export --foxglove``: /tf composed to the tip is the FK of the recorded joints."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from acquisition.recorder.sessions import SessionStore
from acquisition.schemas import scene as S
from acquisition.schemas import topics as T
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.session_card import readable_parts
from acquisition.schemas.standard import (
    fill_transforms,
    joint_state_message,
    pose_stamped_message,
    string_payload,
    transforms_message,
)
from models.urdf import BASE, TOOL, link_name, robot_urdf
from twin.runner import simulate_experiment


def _decode(message, payload: bytes):
    schema = Schema(id=1, name=message.schema_name, encoding="ros2msg", data=message.schema_text.encode())
    return DecoderFactory().decoder_for("cdr", schema)(payload)


def _matrix(transform) -> np.ndarray:
    out = np.eye(4)
    r = transform.rotation
    out[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
    out[:3, 3] = [transform.translation.x, transform.translation.y, transform.translation.z]
    return out


def test_the_standard_messages_decode_as_the_reference_decoder_reads_them():
    rng = np.random.default_rng(1)
    t = np.array([1_700_000_000_123_456_789, 1_700_000_001_000_000_001])
    tf = transforms_message([("base_link", "q1_link"), ("q1_link", "a_long_frame_name_of_odd_length")])
    rows = tf.empty(t)
    transforms = np.tile(np.eye(4), (2, 2, 1, 1))
    transforms[..., :3, :3] = Rotation.random(4, random_state=2).as_matrix().reshape(2, 2, 3, 3)
    transforms[..., :3, 3] = rng.normal(size=(2, 2, 3))
    fill_transforms(rows, transforms)
    for k, payload in enumerate(tf.payloads(rows)):
        decoded = _decode(tf, payload.tobytes())
        assert [(x.header.frame_id, x.child_frame_id) for x in decoded.transforms] == [
            ("base_link", "q1_link"), ("q1_link", "a_long_frame_name_of_odd_length")]  # fmt: skip
        for i, x in enumerate(decoded.transforms):
            assert (x.header.stamp.sec, x.header.stamp.nanosec) == divmod(int(t[k]), 1_000_000_000)
            np.testing.assert_allclose(_matrix(x.transform), transforms[k, i], atol=1e-12)
    pose = pose_stamped_message("tracker")
    rows = pose.empty(t[:1])
    rows["p_x"], rows["q_w"] = 0.25, 1.0
    decoded = _decode(pose, pose.payloads(rows)[0].tobytes())
    assert decoded.header.frame_id == "tracker" and decoded.pose.position.x == 0.25
    assert decoded.pose.orientation.w == 1.0
    for effort in (True, False):
        js = joint_state_message(["q1", "q2", "q3"], effort=effort)
        rows = js.empty(t[:1])
        for i in range(3):
            rows[f"position{i}"], rows[f"velocity{i}"] = i + 0.5, -i
            if effort:
                rows[f"effort{i}"] = 2 * i
        decoded = _decode(js, js.payloads(rows)[0].tobytes())
        assert list(decoded.name) == ["q1", "q2", "q3"]
        assert list(decoded.position) == [0.5, 1.5, 2.5] and list(decoded.velocity) == [0, -1, -2]
        assert list(decoded.effort) == ([0, 2, 4] if effort else [])
    text = "<robot name='é'/>"
    decoded = DecoderFactory().decoder_for(
        "cdr", Schema(id=1, name="std_msgs/msg/String", encoding="ros2msg", data=b"string data\n")
    )(string_payload(text))
    assert decoded.data == text


def _cli(lab, *args):
    command = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


def _exported(path):
    """Every message of the file through the reference decoder: {topic: [(log_time, decoded)]}, and its
    attachments by name."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
        f.seek(0)
        attachments = {a.name: a for a in make_reader(f).iter_attachments()}
    return out, attachments


def _check_export(session, exported, robot):
    """The export holds the session's fixed topics unchanged, and the arm (:func:`_check_arm`)."""
    (part,) = readable_parts(session)
    source, copy = read_fixed_topics(part), read_fixed_topics(exported)
    assert set(source) == set(copy)
    for topic, data in source.items():
        np.testing.assert_array_equal(copy[topic].log_time, data.log_time)
        assert copy[topic].rows.tobytes() == data.rows.tobytes()
    return _check_arm(exported, source, robot)


def _check_arm(path, source, robot):
    """Every message of ``path`` decodes with the reference decoder; the URDF is attached and on
    /robot_description; /tf composed to the tool is the FK of the recorded joints (``source``: the measured
    topics) at every /tf message; /joint_states and /tracker/tip hold the measured values."""
    messages, attachments = _exported(path)
    assert attachments[S.URDF_ATTACHMENT].data.decode() == robot_urdf(robot)
    ((_, description),) = messages[S.ROBOT_DESCRIPTION]
    assert description.data == robot_urdf(robot)
    ((_, static),) = messages[S.TF_STATIC]
    tool = {x.child_frame_id: x for x in static.transforms}[TOOL]
    joints = source[T.joint_state_topic(robot)]
    chain = robot.chain()
    tf = messages[S.TF]
    assert 0.9 * 50 * (joints.log_time[-1] - joints.log_time[0]) / 1e9 <= len(tf)  # decimated to 50 Hz
    for log_time, message in tf:
        parents = {x.child_frame_id: x for x in message.transforms}
        pose, frame = _matrix(tool.transform), tool.header.frame_id
        while frame != BASE:  # walk up the tree from the tool, as a tf listener does
            x = parents[frame]
            pose, frame = _matrix(x.transform) @ pose, x.header.frame_id
        i = int(np.searchsorted(joints.log_time, log_time))
        assert joints.log_time[i] == log_time
        q = joints.rows["position"][i]
        if robot.name == "vsl":  # the stepper's angle held from its latest report
            step = source[T.STEPPER]
            k = int(np.searchsorted(step.log_time, log_time, side="right")) - 1
            q = np.array([step.rows["position"][k][0], *q])
        np.testing.assert_allclose(pose[:3, 3], chain.position(q), atol=1e-9, rtol=0)
        np.testing.assert_allclose(pose, chain.fk(q), atol=1e-9)
    states = messages[S.JOINT_STATES]
    assert len(states) == len(tf) and list(states[0][1].name) == robot.actuated_joints
    tracker = source[T.TRACKER]
    seen = ~tracker.rows["missing"]
    tips = messages[S.TIP_POSE]
    assert len(tips) == seen.sum() and {m.header.frame_id for _, m in tips} == {S.TRACKER_FRAME}
    first = tracker.rows[seen][0]
    pose = tips[0][1].pose
    assert [pose.position.x, pose.orientation.w] == [first["position"][0], first["quaternion"][0]]
    return messages


@pytest.mark.slow
def test_a_popup_session_exports_with_the_arm_for_foxglove(tmp_path, popup):
    lab = tmp_path / "lab"
    simulate_experiment("popup_reach", SessionStore(lab / "sessions"), seed=1)
    (session,) = sorted((lab / "sessions").iterdir())
    done = _cli(lab, "sessions", "export", session.name, "--foxglove")
    assert done.returncode == 0, done.stdout + done.stderr
    exported = lab / "exports" / f"{session.name}.foxglove.mcap"
    messages = _check_export(session, exported, popup)
    # the drives' torques are the joints' effort
    assert np.isfinite(messages[S.JOINT_STATES][0][1].effort).all()
    assert [x.child_frame_id for x in messages[S.TF][0][1].transforms] == [
        link_name(r.joint) for r in popup.dh_rows()
    ]


@pytest.mark.slow
def test_a_vsl_session_exports_with_the_tracker_placed_by_a_dataset(tmp_path, campaign_dataset, vsl):
    lab, version, _ = campaign_dataset
    session = sorted((lab / "sessions").iterdir())[0]
    out = tmp_path / "s.mcap"
    done = _cli(lab, "sessions", "export", str(session), "--foxglove", "--out", str(out),
                "--registration", f"campaign@{version}")  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    messages = _check_export(session, out, vsl)
    ((_, static),) = messages[S.TF_STATIC]
    tracker = {x.child_frame_id: x for x in static.transforms}[BASE]
    assert tracker.header.frame_id == S.TRACKER_FRAME
    card = json.loads((lab / "datasets" / "campaign" / version / "card.json").read_text())
    placement = np.array(card["registration"]["vsl"]["base_to_tracker"])
    np.testing.assert_allclose(_matrix(tracker.transform), placement, atol=1e-12)


@pytest.mark.slow
def test_export_refuses_what_it_cannot_export_in_one_line(tmp_path, campaign_dataset):
    lab, _, _ = campaign_dataset
    session = sorted((lab / "sessions").iterdir())[0].name
    not_a_session = tmp_path / "empty"
    not_a_session.mkdir()
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    cases = [
        ("sessions", "export", session),  # no format
        ("sessions", "export", "no-such-session", "--foxglove"),
        ("sessions", "export", str(not_a_session), "--foxglove"),
        ("sessions", "export", session, "--foxglove", "--registration", "nope"),
        ("sessions", "export", session, "--foxglove", "--out", str(blocker / "x.mcap")),  # under a file
    ]
    for args in cases:
        done = _cli(lab, *args)
        said = (done.stdout + done.stderr).strip().splitlines()
        assert done.returncode == 2 and len(said) == 1 and said[0].startswith("error:"), (args, said)


def test_the_foxglove_layout_shows_topics_sessions_have():
    """configs/foxglove/vslab.json: the arm from /robot_description and /tf, followed from the base; every
    plotted path a field of a session topic or of the standard ones."""
    from models.robot import CONFIG_DIR, load_robot

    layout = json.loads((CONFIG_DIR.parent / "foxglove" / "vslab.json").read_text())
    panels = layout["configById"]

    def leaves(node):
        return [node] if isinstance(node, str) else [*leaves(node["first"]), *leaves(node["second"])]

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    arm = panels["3D!arm"]
    assert arm["followTf"] == BASE
    (urdf,) = [v for v in arm["layers"].values() if v["layerId"] == "foxglove.Urdf"]
    assert (urdf["sourceType"], urdf["topic"]) == ("topic", S.ROBOT_DESCRIPTION)
    fields = {}
    for name in ("vsl", "popup"):
        for topic, t in T.session_topics(load_robot(name)).items():
            if t.message is not None:
                fields[topic] = {f.name for f in t.message.fields}
    fields[S.JOINT_STATES] = {"position", "velocity", "effort"}
    for panel in panels.values():
        for path in panel.get("paths", []):
            topic, _, field = path["value"].partition(".")
            assert field.split("[")[0] in fields[topic], path["value"]
    assert set(arm["topics"]) <= {S.TF, S.TIP_POSE}


@pytest.mark.slow
def test_recorded_sessions_carry_the_arm_themselves(tmp_path, campaign_dataset, popup, vsl):
    """What the session writer writes beside the measured topics (the twin's sessions here, the real-time
    recorder's through the same writer): a VSL campaign session (its stepper's angle held at each /tf as the
    file holds it) and a POPUP reach; the pipeline reads neither's standard topics."""
    from pipeline.ingest import ingest_session

    lab, _, _ = campaign_dataset
    vsl_session = sorted((lab / "sessions").iterdir())[0]
    simulate_experiment("popup_reach", SessionStore(tmp_path / "sessions"), seed=1)
    (popup_session,) = sorted((tmp_path / "sessions").iterdir())
    for session, robot in ((vsl_session, vsl), (popup_session, popup)):
        (part,) = readable_parts(session)
        messages = _check_arm(part, read_fixed_topics(part), robot)
        assert S.TF in messages and S.TIP_POSE in messages
        assert not set(ingest_session(session).streams) & S.STANDARD_TOPICS


def test_quaternions_of_rotations_are_scipy_s():
    from acquisition.schemas.standard import quaternions

    rotations = Rotation.random(20000, random_state=4)
    turns = np.stack([np.diag(d) for d in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])])  # 0°, 180°
    for matrices in (rotations.as_matrix(), turns, rotations.as_matrix().reshape(100, 200, 3, 3)):
        q = quaternions(matrices)
        reference = Rotation.from_matrix(matrices.reshape(-1, 3, 3)).as_quat().reshape(q.shape)
        same_sign = np.sign(np.sum(q * reference, axis=-1, keepdims=True))  # q and −q: the same rotation
        np.testing.assert_allclose(q, same_sign * reference, atol=1e-14)
