"""Device kinds: one contract over every registered kind on its emulator, and a kind from outside the project
(tests/toy_kind: a serial load cell) registered by an entry point, recorded on the rig and simulated."""

from __future__ import annotations

import os
import select
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import emulator_host

from acquisition.devices import kinds
from acquisition.recorder.source_base import make_source
from acquisition.schemas import topics as T
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.session_card import readable_parts
from models.robot import load_robot
from twin.ptyhost import send_control
from twin.topics import stream_rows
from twin.world import World

TOY = Path(__file__).resolve().parent / "toy_kind"
TOY_ROBOT = TOY / "vsl_loadcell.yaml"
ROBOTS = ("vsl", "popup")


# ------------------------------------------------------------------------------------ every kind's contract
def _device_of_kind(kind: str) -> tuple[str, str]:
    """(robot, device) of the first project robot with a device of ``kind``."""
    for robot_name in ROBOTS:
        robot = load_robot(robot_name)
        for name, spec in robot.devices.items():
            if spec.driver == kind:
                return robot_name, name
    raise AssertionError(f"no project robot has a device of kind {kind!r}")


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    """The VSL and POPUP rigs, one process each, for the module: {robot: ports}."""
    out = {}
    with (
        emulator_host(tmp_path_factory.mktemp("vsl-rig"), module="twin.rig", extra=("--robot", "vsl")) as vsl,
        emulator_host(
            tmp_path_factory.mktemp("popup-rig"), module="twin.rig", extra=("--robot", "popup")
        ) as pp,
    ):
        out["vsl"], out["popup"] = vsl, pp
        yield out


def _rows_of(source, topics: set[str], timeout_s: float = 10.0) -> dict[str, object]:
    """The first row of each of ``topics`` that ``source`` reads (polled once per slot, or as its port
    streams)."""
    seen: dict[str, object] = {}
    deadline, slot = time.monotonic() + timeout_s, 0
    while time.monotonic() < deadline and not topics <= set(seen):
        if source.polled:
            rows = source.read(slot)
            slot += 1
            time.sleep(1.0 / source.poll_hz)
        else:
            select.select([source.fileno()], [], [], 0.05)
            rows = source.read(0)
        for row in rows:
            seen.setdefault(row.topic, row)
    return seen


@pytest.mark.slow
@pytest.mark.parametrize("kind_name", kinds.registered())
def test_every_kind_keeps_its_contract_on_its_emulator(kind_name, rigs):
    """A kind resolves; on the rig its recording source (or its bus's) opens and reads samples of its
    topics, stamp fields included; the twin's streams of it become rows of its topics; its random stream is
    its own."""
    kind = kinds.get(kind_name)
    assert kind.name == kind_name
    robot_name, device = _device_of_kind(kind_name)
    robot = load_robot(robot_name)
    written = kind.topics_of(robot, device)
    assert written and set(written) <= set(T.session_topics(robot))
    for topic, field in kind.stamps.items():
        if topic in written:
            assert field in written[topic].dtype.names, (topic, field)
            assert kinds.stamp_fields(robot)[topic][1] == field
    for ref in (kind.source, kind.emulator, *(r for _, r in kind.streams), *(r for _, r in kind.rows)):
        if ref is not None:
            assert callable(kinds.resolve(ref)), ref

    # open on its emulator and read a sample (a board on a bus: through its bus's source)
    spec = robot.devices[device]
    recorded_by = spec.bus or device
    source = make_source(robot, recorded_by, rigs[robot_name][recorded_by])
    sampled = {t for t in written if t in source.sampled_topics}
    assert sampled, f"{kind_name}: no sampled topic of {device} is recorded by {recorded_by}"
    source.open()
    try:
        rows = _rows_of(source, sampled)
    finally:
        source.close()
    assert sampled <= set(rows), (kind_name, sorted(rows))
    for topic in sampled:
        assert len(rows[topic].data) == written[topic].dtype.itemsize

    # the twin's streams of it, as rows
    world = World(robot, seed=0)
    streams = world.read(world.run_for(0.5))
    valves = np.ones((1, robot.pneumatics.channels), bool)
    made = {}
    for _, ref in kind.rows:
        made.update(kinds.resolve(ref)(robot, device, T.session_topics(robot), streams, valves))
    assert set(made) == set(written) - {T.SERVO_GOAL, T.PRESSURE_COMMAND}, kind_name  # commands: not streamed
    for topic, (bench, host_ns, data) in made.items():
        assert len(data) > 0 and np.all(bench == 0) and np.all(np.diff(host_ns) > -5e6), topic
        stamp = kind.stamps.get(topic)
        if stamp is not None:
            assert stamp in data.dtype.names

    # its own random stream: reproducible, and not another device's
    other = next(n for n in robot.devices if n != device)
    a = World(robot, seed=0).device_rng(device).random(4)
    np.testing.assert_array_equal(a, World(robot, seed=0).device_rng(device).random(4))
    assert not np.array_equal(a, World(robot, seed=0).device_rng(other).random(4))
    assert not np.array_equal(a, World(robot, seed=1).device_rng(device).random(4))
    # and each bench's own in a batch: a bench named alike draws alike in any batch, other benches otherwise
    pair = World(robot, batch=2, seed=0, benches=["a", "b"]).noise(device).generators
    alone = World(robot, batch=1, seed=0, benches=["b"]).noise(device).generators
    np.testing.assert_array_equal(pair[1].random(4), alone[0].random(4))
    assert not np.array_equal(pair[0].random(4), pair[1].random(4))


def test_an_unknown_driver_is_one_error_that_names_the_known_kinds():
    with pytest.raises(kinds.DeviceKindError, match="dynamixel"):
        kinds.get("no_such_kind")
    with pytest.raises(kinds.DeviceKindError, match="cannot import"):
        kinds.get("no_such_module:KIND")


# ------------------------------------------------------------------------- a kind from outside the project
@pytest.fixture
def toy_kind(tmp_path, monkeypatch):
    """The load cell registered as an installed package would register it: an entry point ``loadcell`` in
    the ``vslab.device_kinds`` group (a dist-info folder on the path), visible to every process started
    from here (PYTHONPATH), the module importable from tests/toy_kind."""
    site = tmp_path / "site"
    info = site / "vslab_toy_loadcell-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: vslab-toy-loadcell\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{kinds.ENTRY_POINT_GROUP}]\nloadcell = loadcell:KIND\n")
    paths = [str(TOY), str(site)]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([*paths, os.environ.get("PYTHONPATH", "")]))
    for p in reversed(paths):
        monkeypatch.syspath_prepend(p)
    kinds.get.cache_clear()
    yield load_robot(TOY_ROBOT)
    kinds.get.cache_clear()
    sys.modules.pop("loadcell", None)


def test_a_kind_from_outside_the_project_is_found_by_its_entry_point_or_its_module_path(toy_kind):
    assert "loadcell" in kinds.registered() and "loadcell" not in kinds.KINDS
    assert kinds.get("loadcell") is kinds.get("loadcell:KIND")
    assert kinds.kind_of(toy_kind, "load_cell").name == "loadcell"
    assert "/loadcell/force" in T.session_topics(toy_kind)


@pytest.mark.slow
def test_a_kind_from_outside_the_project_is_recorded_on_the_rig(toy_kind, tmp_path):
    """The load cell's description extends the VSL robot; the rig serves it, the recorder's daemon (another
    process) records it: its topic is in the file, sampled at its rate, reading the payload's weight."""
    import loadcell

    from acquisition.recorder.recorder import Recorder

    seconds, payload_kg = 3.0, 0.2
    with emulator_host(tmp_path / "run", module="twin.rig", extra=("--robot", str(TOY_ROBOT))) as ports:
        assert "load_cell" in ports
        assert send_control(tmp_path / "run", {"op": "payload", "kg": payload_kg})["ok"]
        with Recorder(toy_kind, {"load_cell": ports["load_cell"]}, tmp_path / "s", "toy") as rec:
            time.sleep(seconds)
    assert rec.write_error is None
    (part,) = readable_parts(tmp_path / "s")
    data = read_fixed_topics(part)[loadcell.TOPIC]
    rows = data.rows
    assert len(rows) >= 100 * (seconds - 1.5), len(rows)
    assert np.all(np.diff(rows["seq"].astype(np.int64)) >= 1)
    weight = payload_kg * -toy_kind.gravity_m_s2[2]
    assert abs(np.median(rows["force"]) - weight) < 0.01
    np.testing.assert_allclose(rows["force"], rows["counts"] * loadcell.NEWTON_PER_COUNT)
    assert 0.5e-3 < np.std(rows["force"]) < 5e-3  # the cell's noise (2 mN rms), not a constant


def test_a_kind_from_outside_the_project_is_simulated(toy_kind):
    """The twin's world reads the load cell through its kind's stream, and its rows are the recorder's."""
    import loadcell

    world = World(toy_kind, seed=0)
    world.set_payload(0.1)
    streams = world.read(world.run_for(1.0))
    rows = stream_rows(toy_kind, T.session_topics(toy_kind), streams, np.ones((1, 2), bool))
    bench, host_ns, data = rows[loadcell.TOPIC]
    assert len(data) == 100 and np.all(bench == 0) and np.all(np.diff(host_ns) > 0)
    assert abs(np.mean(data["force"]) - 0.1 * 9.81) < 2e-3


def test_adding_a_device_changes_no_other_devices_draws(toy_kind, vsl):
    """Each device draws its clock and its noise from its own generator: the VSL devices report the same
    samples, to the bit, with the load cell added to the description."""
    worlds = [World(robot, seed=5) for robot in (vsl, toy_kind)]
    for w in worlds:
        w.set_payload(0.05)
    read = [w.read(w.run_for(1.0)) for w in worlds]
    assert set(read[1]) == {*read[0], "load_cell"}
    for key, stream in read[0].items():
        for column, values in stream.items():
            np.testing.assert_array_equal(values, read[1][key][column], err_msg=f"{key}.{column}")
