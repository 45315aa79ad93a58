"""The live view against a real WebSocket client speaking the Foxglove WebSocket protocol (stdlib only)."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time

import numpy as np
import pytest

from acquisition.recorder.live import LiveServer
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from models.robot import load_robot

SUBPROTOCOL = "foxglove.sdk.v1"  # 0.30 speaks only this; "foxglove.websocket.v1" gets 400
MESSAGE_DATA = 1  # binary opcode of a messageData frame


class FoxgloveClient:
    """The least a Foxglove viewer does: handshake, read JSON ops, subscribe, read messageData frames."""

    def __init__(self, port: int, timeout_s: float = 5.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                f"Sec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            assert chunk, "server closed during the handshake"
            head += chunk
        assert head.startswith(b"HTTP/1.1 101"), head
        assert SUBPROTOCOL.encode() in head, head

    def close(self) -> None:
        self.sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))  # a masked, empty close frame
        self.sock.close()

    def _exact(self, n: int) -> bytes:
        out = bytearray()
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            assert chunk, "server closed the connection"
            out += chunk
        return bytes(out)

    def frame(self) -> tuple[int, bytes]:
        """One whole frame from the server (unmasked): (opcode, payload)."""
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            (n,) = struct.unpack(">H", self._exact(2))
        elif n == 127:
            (n,) = struct.unpack(">Q", self._exact(8))
        assert b0 & 0x80, "fragmented frames are not expected here"
        return b0 & 0x0F, self._exact(n)

    def send_json(self, obj: dict) -> None:
        data = json.dumps(obj).encode()
        mask = os.urandom(4)
        head = bytes([0x81]) + (
            bytes([0x80 | len(data)])
            if len(data) < 126
            else bytes([0x80 | 126]) + struct.pack(">H", len(data))
        )
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        self.sock.sendall(head + mask + masked)

    def ops_until(self, op: str) -> list[dict]:
        """JSON messages read until one of ``op`` (inclusive)."""
        seen = []
        while True:
            opcode, payload = self.frame()
            if opcode == 1:
                seen.append(json.loads(payload))
                if seen[-1]["op"] == op:
                    return seen

    def messages(self, count: int, deadline_s: float = 5.0) -> list[tuple[int, int, bytes]]:
        """``count`` messageData frames: (subscription id, log time ns, payload)."""
        out, end = [], time.monotonic() + deadline_s
        while len(out) < count and time.monotonic() < end:
            opcode, payload = self.frame()
            if opcode == 2 and payload[0] == MESSAGE_DATA:
                sub, t = struct.unpack_from("<IQ", payload, 1)
                out.append((sub, t, payload[13:]))
        return out


@pytest.fixture
def robot():
    return load_robot("vsl")


@pytest.fixture
def live(robot):
    with LiveServer(T.session_topics(robot), port=0, max_rate_hz=None) as server:
        yield server


def _subscribe(client: FoxgloveClient, channels: dict[str, dict], topics: dict[str, int]) -> None:
    subs = [{"id": sub, "channelId": channels[topic]["id"]} for topic, sub in topics.items()]
    client.send_json({"op": "subscribe", "subscriptions": subs})


def _wait_subscribed(live: LiveServer, topic: str) -> None:
    end = time.monotonic() + 5
    while not live._channels[topic].has_sinks() and time.monotonic() < end:
        time.sleep(0.01)


def _advertised(client: FoxgloveClient) -> dict[str, dict]:
    channels: dict[str, dict] = {}
    for msg in client.ops_until("advertise"):
        if msg["op"] == "advertise":
            channels.update({c["topic"]: c for c in msg["channels"]})
    return channels


def test_every_topic_is_advertised_with_its_ros2msg_schema(live, robot):
    assert live.port != 0 and live.url == f"ws://127.0.0.1:{live.port}"
    client = FoxgloveClient(live.port)
    try:
        channels = _advertised(client)
    finally:
        client.close()
    topics = T.session_topics(robot)
    assert set(channels) == set(topics)
    for name, topic in topics.items():
        c = channels[name]
        assert (c["encoding"], c["schemaName"], c["schemaEncoding"]) == ("cdr", topic.schema_name, "ros2msg")
        assert c["schema"] == topic.schema_text


def test_published_messages_arrive_with_the_file_bytes_and_log_times(live, robot):
    message = T.session_topics(robot)[T.SERVO_STATE].message
    n = 50
    rows = message.pack({"seq": np.arange(n), "tick_ms": np.arange(n) * 2, "position": np.full((n, 2), 0.5)})
    log_time = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 2_000_000
    event = Event(EventKind.NOTE, label="live", text="hello")
    client = FoxgloveClient(live.port)
    try:
        channels = _advertised(client)
        _subscribe(client, channels, {T.SERVO_STATE: 7, T.EVENTS: 8})
        _wait_subscribed(live, T.SERVO_STATE)
        _wait_subscribed(live, T.EVENTS)
        assert live.publish(T.SERVO_STATE, log_time, rows) == n
        assert live.publish(T.EVENTS, [123], [event.encode()]) == 1
        got = client.messages(n + 1)
    finally:
        client.close()
    servo = [(t, p) for sub, t, p in got if sub == 7]
    assert [t for t, _ in servo] == log_time.tolist()
    expected = message.canonical_bytes(rows)
    assert [p for _, p in servo] == [row.tobytes() for row in expected]
    assert [(t, p) for sub, t, p in got if sub == 8] == [(123, event.encode())]


def test_decimation_caps_each_topic_at_max_rate(robot):
    message = T.session_topics(robot)[T.PRESSURE].message
    with LiveServer(T.session_topics(robot), port=0, max_rate_hz=100.0) as live:
        client = FoxgloveClient(live.port)
        try:
            channels = _advertised(client)
            _subscribe(client, channels, {T.PRESSURE: 1})
            _wait_subscribed(live, T.PRESSURE)
            # 2 s at 550 Hz in batches of 0.1 s, as the recorder's writer hands them over
            t = np.arange(1100, dtype=np.int64) * int(1e9 / 550) + 1_700_000_000_000_000_000
            sent = sum(live.publish(T.PRESSURE, b, message.pack({}, n=len(b))) for b in np.array_split(t, 20))
            got = client.messages(sent)
        finally:
            client.close()
    assert 195 <= sent <= 201  # 100 Hz over 2 s
    assert live.decimated[T.PRESSURE] == 1100 - sent
    times = np.array([t for _, t, _ in got])
    assert len(times) == sent and np.all(np.diff(times) >= 1e9 / 550)
    assert np.max(np.bincount((times - times[0]) // 10_000_000)) == 1  # never two in one 10 ms bucket


@pytest.mark.slow
def test_a_recording_shown_live_keeps_the_file_whole(host_factory, tmp_path, robot, real_time):
    """The rig recorded with a viewer subscribed: the view gets the file's bytes at ≤ 100 Hz, the file all."""
    from acquisition.recorder.recorder import Recorder
    from acquisition.schemas.fast_read import read_fixed_topics
    from acquisition.schemas.session_card import readable_parts

    with (
        host_factory(module="twin.rig", extra=("--robot", "vsl")) as ports,
        LiveServer(T.session_topics(robot), port=0) as live,
    ):
        client = FoxgloveClient(live.port)
        try:
            _subscribe(client, _advertised(client), {T.SERVO_STATE: 1})
            _wait_subscribed(live, T.SERVO_STATE)
            with Recorder(robot, ports, tmp_path / "s", "live", live=live) as rec:
                time.sleep(2.0)
            got = client.messages(live.published[T.SERVO_STATE])
        finally:
            client.close()
    assert rec.live_errors == 0 and rec.write_error is None
    (part,) = readable_parts(tmp_path / "s")
    servo = read_fixed_topics(part)[T.SERVO_STATE]
    seconds = (servo.log_time[-1] - servo.log_time[0]) / 1e9
    assert 0 < len(got) <= 100 * seconds + 2  # the view is decimated, whatever the host did
    by_time = dict(zip(servo.log_time.tolist(), servo.message.canonical_bytes(servo.rows), strict=True))
    for _, t, payload in got:
        assert payload == by_time[t].tobytes()  # the file's bytes
    real_time(rec)
    # the file is never decimated: every poll of the servo bus is in it (its rate, less a device clock's drift
    # and a few polls a busy host may miss; at exactly the rate, 1,398 samples in 3.495 s failed it in CI)
    assert len(servo) > 0.95 * robot.devices["servo_bus"].rate_hz * seconds


def test_the_live_view_shows_the_arm_from_the_joint_streams(robot):
    """With the robot's scene: /tf from each servo batch (the stepper's angle held), composed to the tool
    it is the FK of those joints; /robot_description and /tf_static reach a viewer that subscribed late."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory
    from scipy.spatial.transform import Rotation

    from acquisition.schemas import scene as S
    from models.urdf import BASE, TOOL, robot_urdf

    topics = T.session_topics(robot)
    with LiveServer(topics, port=0, max_rate_hz=None, scene=S.Scene(robot)) as live:
        client = FoxgloveClient(live.port)
        try:
            channels = _advertised(client)
            assert {S.TF, S.TF_STATIC, S.JOINT_STATES, S.TIP_POSE, S.ROBOT_DESCRIPTION} <= set(channels)
            _subscribe(client, channels, {S.TF: 1, S.TF_STATIC: 2, S.ROBOT_DESCRIPTION: 3})
            for topic in (S.TF, S.TF_STATIC, S.ROBOT_DESCRIPTION):
                _wait_subscribed(live, topic)
            t0 = 1_700_000_000_000_000_000
            stepper = topics[T.STEPPER].message.pack({"position": np.array([[0.3]])})
            live.publish(T.STEPPER, [t0], stepper)
            n = 5
            q23 = np.column_stack([np.linspace(0.1, 0.5, n), np.linspace(-0.4, 0.2, n)])
            servo = topics[T.SERVO_STATE].message.pack({"seq": np.arange(n), "position": q23})
            log_time = t0 + 1_000_000 + np.arange(n, dtype=np.int64) * 10_000_000
            live.publish(T.SERVO_STATE, log_time, servo)
            got = client.messages(n + 2)
        finally:
            client.close()

    def decode(topic, payload):
        c = channels[topic]
        schema = Schema(id=1, name=c["schemaName"], encoding="ros2msg", data=c["schema"].encode())
        return DecoderFactory().decoder_for("cdr", schema)(payload)

    def matrix(x):
        out = np.eye(4)
        r = x.transform.rotation
        out[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
        out[:3, 3] = [x.transform.translation.x, x.transform.translation.y, x.transform.translation.z]
        return out

    by_sub = {}
    for sub, t, payload in got:
        by_sub.setdefault(sub, []).append((t, payload))
    assert decode(S.ROBOT_DESCRIPTION, by_sub[3][0][1]).data == robot_urdf(robot)
    (tool,) = [x for x in decode(S.TF_STATIC, by_sub[2][0][1]).transforms if x.child_frame_id == TOOL]
    assert [t for t, _ in by_sub[1]] == log_time.tolist()
    for (_, payload), q in zip(by_sub[1], q23, strict=True):
        parents = {x.child_frame_id: x for x in decode(S.TF, payload).transforms}
        pose, frame = matrix(tool), tool.header.frame_id
        while frame != BASE:
            pose, frame = matrix(parents[frame]) @ pose, parents[frame].header.frame_id
        np.testing.assert_allclose(pose, robot.chain().fk(np.array([0.3, *q])), atol=1e-9)
