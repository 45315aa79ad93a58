"""The live view: a Foxglove WebSocket server that shows a recording's streams while they are written.

    with LiveServer(session_topics(robot), port=0) as live, Recorder(..., live=live):
        print(live.url)             # open it in Foxglove (Open connection → Foxglove WebSocket)

Each session topic becomes one channel with its ros2msg schema and CDR encoding, and gets the very bytes the
MCAP file gets (no re-encoding). The view may decimate: at most ``max_rate_hz`` messages per topic per second
(events are never decimated); the file never is. The server speaks to anyone who can reach ``host``, without
authentication: keep the default loopback address unless the network is the lab's own.

Given the robot's ``Scene``, the view also shows the arm: ``/tf`` and ``/joint_states`` from the joint
streams (decimated as any topic), ``/tracker/tip`` from the tracker, and every second ``/robot_description``
and ``/tf_static`` (a viewer that connects late still gets them).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence

import foxglove
import numpy as np

from acquisition.schemas import scene as S
from acquisition.schemas.topics import EVENTS, MESSAGE_ENCODING, SCHEMA_ENCODING, Topic

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


class LiveServer:
    """One Foxglove WebSocket server with one channel per session topic; ``publish`` forwards CDR messages."""

    def __init__(
        self,
        topics: Mapping[str, Topic],
        host: str = LOOPBACK,
        port: int = 8765,  # Foxglove's default; 0 = any free port (see ``port`` after start)
        max_rate_hz: float | None = 100.0,  # per topic; None = forward everything
        name: str = "vslab",
        scene: S.Scene | None = None,  # the robot's standard topics: the arm in the 3D panel
    ) -> None:
        self.topics = dict(topics)
        self.scene = scene
        self._scene_schemas = scene.schemas() if scene is not None else {}
        # decimated as the view decimates any topic; nothing waits for the stepper (its latest angle holds)
        self._stream = (
            S.SceneStream(scene, max_rate_hz or 1e9, max_wait_s=0.0, batch_s=0.0)
            if scene is not None
            else None
        )
        self._static_at = 0.0
        self.host = host
        self.port = port
        self.max_rate_hz = max_rate_hz
        self.name = name
        shown = [*self.topics, *self._scene_schemas]
        self.published: dict[str, int] = dict.fromkeys(shown, 0)  # forwarded to the server
        self.decimated: dict[str, int] = dict.fromkeys(shown, 0)  # left out of the view
        self._last_bucket: dict[str, int] = {}
        self._context: foxglove.Context | None = None
        self._server: foxglove.WebSocketServer | None = None
        self._channels: dict[str, foxglove.Channel] = {}

    @property
    def url(self) -> str:
        """What to open in Foxglove."""
        return f"ws://{self.host}:{self.port}"

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> LiveServer:
        """Bind the server and advertise every topic; ``port`` becomes the one actually bound. Idempotent."""
        if self._server is not None:
            return self
        # our own context (channels of other servers stay apart), kept alive: once it is collected the
        # server advertises nothing
        self._context = context = foxglove.Context()
        self._server = foxglove.start_server(name=self.name, host=self.host, port=self.port, context=context)
        self.port = self._server.port
        for name, topic in self.topics.items():
            schema = foxglove.Schema(
                name=topic.schema_name, encoding=SCHEMA_ENCODING, data=topic.schema_text.encode()
            )
            self._channels[name] = foxglove.Channel(
                name, schema=schema, message_encoding=MESSAGE_ENCODING, context=context
            )
        for name, (schema_name, text) in self._scene_schemas.items():
            schema = foxglove.Schema(name=schema_name, encoding=SCHEMA_ENCODING, data=text.encode())
            self._channels[name] = foxglove.Channel(
                name, schema=schema, message_encoding=MESSAGE_ENCODING, context=context
            )
        log.info("live view at %s (%d topics)", self.url, len(self._channels))
        return self

    def close(self) -> None:
        """Stop the server; idempotent."""
        if self._server is None:
            return
        for channel in self._channels.values():
            channel.close()
        self._server.stop()
        self._server = self._context = None

    def publish(self, topic: str, log_time_ns: Sequence[int] | np.ndarray,
                messages: np.ndarray | Sequence[bytes]) -> int:  # fmt: skip
        """Forward one topic's batch: ``messages`` its packed rows (``FixedMessage.pack``) or encoded
        messages; ``log_time_ns`` their UNIX ns log times. Returns how many went to the view."""
        channel = self._channels.get(topic)
        if channel is None:
            raise KeyError(f"the live view has no topic {topic!r}")
        log_time = np.asarray(log_time_ns, dtype=np.int64)
        if len(log_time) != len(messages):
            raise ValueError(f"{topic}: {len(log_time)} log times for {len(messages)} messages")
        if self.scene is not None and isinstance(messages, np.ndarray) and len(log_time):
            self._show_arm(topic, log_time, messages)
        if not channel.has_sinks():
            return 0  # nobody is watching: no work
        keep = self._keep(topic, log_time)
        payloads = self._payloads(topic, messages, keep)
        for payload, t in zip(payloads, log_time[keep].tolist(), strict=True):
            channel.log(payload, log_time=t)
        self.published[topic] += len(payloads)
        self.decimated[topic] += len(log_time) - len(payloads)
        return len(payloads)

    def _keep(self, topic: str, log_time: np.ndarray) -> np.ndarray:
        """Indices to forward: the first message of each 1/max_rate_hz time bucket not yet forwarded."""
        if topic == EVENTS or not self.max_rate_hz or len(log_time) == 0:
            return np.arange(len(log_time))
        bucket = log_time // int(1e9 / self.max_rate_hz)
        first = np.ones(len(bucket), dtype=bool)
        first[1:] = bucket[1:] != bucket[:-1]
        first &= bucket > self._last_bucket.get(topic, np.iinfo(np.int64).min)
        self._last_bucket[topic] = max(int(bucket.max()), self._last_bucket.get(topic, int(bucket.max())))
        return np.flatnonzero(first)

    def _payloads(self, topic: str, messages: np.ndarray | Sequence[bytes], keep: np.ndarray) -> list[bytes]:
        """The bytes the MCAP file gets: fixed messages with zeroed padding, one ``tobytes`` per batch."""
        if isinstance(messages, np.ndarray):
            message = self.topics[topic].message
            if message is None or messages.dtype != message.dtype:
                raise ValueError(f"{topic}: rows are not {self.topics[topic].schema_name} messages")
            raw = message.canonical_bytes(messages[keep]).tobytes()
            size = message.size
            return [raw[i : i + size] for i in range(0, len(raw), size)]
        return [bytes(messages[i]) for i in keep.tolist()]

    # --------------------------------------------------------------------------------- the arm
    def _show_arm(self, topic: str, log_time: np.ndarray, rows: np.ndarray) -> None:
        """The standard topics these rows make (``scene``), forwarded as any topic is."""
        if not self._wanted(*self._scene_schemas):
            return
        batches = self._stream.feed(topic, log_time, rows)
        now = time.monotonic()
        if now - self._static_at >= 1.0:
            self._static_at = now
            batches += self.scene.static(int(log_time[-1]))
        for batch in batches:
            channel = self._channels[batch.topic]
            for payload, t in zip(batch.payloads, batch.log_time.tolist(), strict=True):
                channel.log(bytes(payload), log_time=t)
            self.published[batch.topic] += len(batch)

    def _wanted(self, *topics: str) -> bool:
        return any(self._channels[t].has_sinks() for t in topics)
