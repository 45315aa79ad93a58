"""Device kinds: one registration per kind of device, looked up by the driver name a robot description gives.

python-can's ``BACKENDS`` is the model: the registry maps a name to a ``"module:attribute"`` string and the
module is imported only when that kind is used, so recording a VSL session never imports POPUP's CAN stack.
A :class:`DeviceKind` says everything the rest of vslab needs to know about one kind of device: what it does
for the robot (its ``role``), the recorder's source, the topics it writes, the stamp and timeline fields the
pipeline reads, and, for the twin, its emulator, its twin streams and how a stream becomes topic rows. The
twin is a higher layer than acquisition, so those are ``"module:attribute"`` strings too, resolved only when
the twin asks (:func:`resolve`): acquisition never imports the twin.

Where a kind is found (:func:`get`), in order:

1. the built-in kinds (:data:`KINDS`);
2. the ``vslab.device_kinds`` entry point group (:data:`ENTRY_POINT_GROUP`): an installed package declares
   ``loadcell = "mylab.loadcell:KIND"`` in its ``[project.entry-points."vslab.device_kinds"]``. This is the
   field's standard plugin mechanism, and it reaches every process: the rig and the recorder's daemons run in
   OS processes of their own, so a registration made only in the caller's process would not;
3. a driver written ``"module:attribute"`` in the robot description itself (``driver: mylab.loadcell:KIND``):
   one line of YAML, nothing installed, for a kind that lives in a lab's own folder (on ``PYTHONPATH``).
"""

from __future__ import annotations

import hashlib
import importlib
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib.metadata import entry_points
from typing import Any

import numpy as np

from acquisition.errors import AcquisitionError
from models.robot import DeviceSpec, RobotDescription

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "vslab.device_kinds"

# the built-in kinds: driver name → "module:attribute" of its DeviceKind (imported when first used)
KINDS: dict[str, str] = {
    "dynamixel": "acquisition.devices.builtin_kinds:DYNAMIXEL",
    "vslab_pressure_board": "acquisition.devices.builtin_kinds:PRESSURE_BOARD",
    "vslab_stepper_board": "acquisition.devices.builtin_kinds:STEPPER_BOARD",
    "ndi_aurora": "acquisition.devices.builtin_kinds:AURORA",
    "popup_can": "acquisition.devices.builtin_kinds:POPUP_CAN",
    "popup_main_board": "acquisition.devices.builtin_kinds:POPUP_MAIN_BOARD",
    "popup_link_board": "acquisition.devices.builtin_kinds:POPUP_LINK_BOARD",
}

# A kind's topics: (robot, device name) → topic name → its message (acquisition.schemas.cdr.FixedMessage)
TopicsOf = Callable[[RobotDescription, str], Mapping[str, Any]]


class DeviceKindError(AcquisitionError, ValueError):
    """A driver name no kind is registered under, or a registration that does not name a DeviceKind."""


@dataclass(frozen=True)
class DeviceKind:
    """Everything about one kind of device, by name (the ``driver`` of a device in a robot description).

    ``source``, ``emulator``, ``streams`` and ``rows`` are ``"module:attribute"`` strings, resolved when used:
    - ``source``: the recorder's :class:`~acquisition.recorder.source_base.Source` subclass;
    - ``emulator``: ``(rig, name, spec) → Emulator`` (a device on another's bus: the node the bus attaches);
    - ``streams``: (order, ``(world, name, trace, servo_rate_hz) → {stream key: Stream}``) pairs: what
      the device reports during a trace of the twin, from its own generator (``World.device_rng``);
    - ``rows``: (order, ``(robot, name, topics, streams, valve_open) → {topic: TopicRows}``) pairs: the
      rows of its topics from those streams, as the recorder would have written them.
    ``stamps``: topic → the payload field holding the device's own clock (the pipeline fits it to host
    time); ``timeline``: topic → (column prefix, fields) the timeline interpolates at the tracker's frames;
    ``polled``: the topics the host polls (sampled on the host's clock); ``role``: what the device does for
    the robot ("joints", "pressure", "stepper", "tracker", "link"; None: nothing the models know of);
    ``ceiling``: ``"module:attribute"`` of ``(spec) → Hz``, the highest ``rate_hz`` the device's link
    carries (:mod:`acquisition.devices.bus_budget`; None: no ceiling below the device's own rate);
    ``resolution_rad``: the step of the joint positions it reports and is given (rad per count; None: it
    reports none), what a fit of its joints' goals against their readings rounds to.
    """

    name: str
    role: str | None = None
    source: str | None = None
    topics: TopicsOf | None = None
    stamps: Mapping[str, str] = field(default_factory=dict)
    timeline: Mapping[str, tuple[str, tuple[str, ...]]] = field(default_factory=dict)
    polled: frozenset[str] = frozenset()
    emulator: str | None = None
    streams: tuple[tuple[float, str], ...] = ()
    rows: tuple[tuple[float, str], ...] = ()
    check: Callable[[RobotDescription, str, DeviceSpec], None] | None = None
    ceiling: str | None = None
    resolution_rad: float | None = None

    def topics_of(self, robot: RobotDescription, name: str) -> dict[str, Any]:
        """The topics device ``name`` of ``robot`` writes (topic → message)."""
        return dict(self.topics(robot, name)) if self.topics is not None else {}


def resolve(ref: str) -> Any:
    """The object a ``"module:attribute"`` string names, importing its module."""
    module, sep, attr = ref.partition(":")
    if not sep or not module or not attr:
        raise DeviceKindError(f"{ref!r} is not 'module:attribute'")
    try:
        obj: Any = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as exc:
        raise DeviceKindError(f"cannot import {ref!r}: {exc}") from exc
    return obj


@cache
def get(driver: str) -> DeviceKind:
    """The kind registered as ``driver`` (built-in, entry point, or a ``"module:attribute"`` driver)."""
    if driver in KINDS:
        ref = KINDS[driver]
    elif (plugin := _entry_point(driver)) is not None:
        ref = plugin
    elif ":" in driver:
        ref = driver
    else:
        raise DeviceKindError(
            f"no device kind {driver!r} (known: {', '.join(sorted({*KINDS, *_plugin_names()}))}; or a "
            f"'module:attribute' naming a DeviceKind, or an entry point in {ENTRY_POINT_GROUP!r})"
        )
    kind = resolve(ref)
    if not isinstance(kind, DeviceKind):
        raise DeviceKindError(f"{ref!r} is a {type(kind).__name__}, not a DeviceKind")
    return kind


def _entry_point(name: str) -> str | None:
    found = entry_points(group=ENTRY_POINT_GROUP, name=name)
    return next((ep.value for ep in found), None)


def _plugin_names() -> list[str]:
    return [ep.name for ep in entry_points(group=ENTRY_POINT_GROUP)]


def registered() -> list[str]:
    """Every kind name known without a robot: the built-in ones and the entry points'."""
    return list(dict.fromkeys([*KINDS, *_plugin_names()]))


def kind_of(robot: RobotDescription, device: str) -> DeviceKind:
    """The kind of ``robot``'s device ``device``."""
    spec = robot.devices.get(device)
    if spec is None:
        raise DeviceKindError(f"{robot.name} has no device {device!r} ({', '.join(robot.devices)})")
    return get(spec.driver)


def device_kinds(robot: RobotDescription) -> dict[str, DeviceKind]:
    """Every device of ``robot`` with its kind, in the description's order (each kind's checks passed)."""
    out = {}
    for name, spec in robot.devices.items():
        kind = get(spec.driver)
        if kind.check is not None:
            kind.check(robot, name, spec)
        out[name] = kind
    return out


def device_of(robot: RobotDescription, role: str) -> str | None:
    """The name of ``robot``'s (first) device whose kind has ``role`` ("joints", "pressure", "stepper",
    "tracker", "link"; and "accelerometer": the device ``sensors.accelerometer`` names), None if it has none:
    how the twin, the topics and the pipeline find "the device that reads the link pressures" whatever a
    description calls it."""
    if role == "accelerometer":
        accel = robot.sensors.accelerometer
        return accel.device if accel is not None and accel.device in robot.devices else None
    return next((n for n, d in robot.devices.items() if get(d.driver).role == role), None)


def link_boards(robot: RobotDescription) -> dict[str, str]:
    """Link name → the name of the board (a device whose kind has role "link") on it."""
    return {d.link: n for n, d in robot.devices.items() if get(d.driver).role == "link" and d.link}


def stamp_fields(robot: RobotDescription) -> dict[str, tuple[str, str]]:
    """Topic → (the device whose clock stamps it, the stamp field), over ``robot``'s devices."""
    out: dict[str, tuple[str, str]] = {}
    for name, kind in device_kinds(robot).items():
        written = kind.topics_of(robot, name)
        for topic, stamp in kind.stamps.items():
            if topic in written:
                out.setdefault(topic, (name, stamp))
    return out


def spawned(seed: int | np.random.SeedSequence, name: str) -> np.random.SeedSequence:
    """``seed`` spawned by ``name``: the same sequence for the same two, whatever else is spawned from it."""
    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    key = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")
    return np.random.SeedSequence(root.entropy, spawn_key=(*root.spawn_key, key))


def device_rng(seed: int | np.random.SeedSequence, device: str) -> np.random.Generator:
    """A device's own random generator: the session's seed spawned by the device's name, so adding a device
    to a description changes no other device's noise."""
    return np.random.default_rng(spawned(seed, device))


def timeline_fields(robot: RobotDescription) -> dict[str, tuple[str, tuple[str, ...]]]:
    """Topic → (column prefix, fields) the timeline interpolates at the tracker's frames, over ``robot``'s
    devices in the description's order (the order of the timeline's columns)."""
    out: dict[str, tuple[str, tuple[str, ...]]] = {}
    for kind in device_kinds(robot).values():
        for topic, fields in kind.timeline.items():
            out.setdefault(topic, fields)
    return out


def polled_topics(robot: RobotDescription) -> frozenset[str]:
    """The topics of ``robot`` whose samples the host polls (Sync Read, SYNC): sampled on the host's clock."""
    return frozenset().union(*(kind.polled for kind in device_kinds(robot).values()))
