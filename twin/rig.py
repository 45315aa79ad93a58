"""The rig: the digital twin run in real time behind emulators of the robot's devices, one pty each.

    python -m twin.rig --robot vsl --run-dir lab/rig      (or: vslab rig --robot vsl)

Drivers (and the recorder) find the ports in ``<run-dir>/ports.json``. The arm starts at its home pose with
its links at their operating pressure, or as ``--start`` sets the bench up (``vslab run --rig`` passes the
plan's first pose, pressures and valves, as an operator sets the bench up for it: a deployment starts with
its links deflated). The control socket takes the
operator's inputs ({"op": "payload", "kg": 0.05}), test faults of the twin ({"op": "coil", "inside": false}:
the tracker coil leaves the field volume) and queries ({"op": "state"}) besides the port faults.

The twin is stepped lazily, in whole 1 ms steps up to the rig time, by whichever emulator needs it (a read, a
command, a streamed line is due) and by the host's ``tick`` before each control command and on its slow
housekeeping wake-up (see ``PtyHost``): an idle rig costs almost nothing, a busy one steps once per ms.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
from pathlib import Path

import numba
import numpy as np

from acquisition.devices.bus_budget import FTDI_DEFAULT_LATENCY_S
from acquisition.devices.kinds import device_kinds, resolve
from acquisition.processes import RT_PRIORITY, die_with_parent, elevate, settle_heap
from models.robot import RobotDescription, load_robot
from twin.can_bus import CanBus
from twin.clocks import _TICK_EPS as TICK_EPS
from twin.devices import RecentSteps, TwinTrackerSource
from twin.emulators.base import Emulator
from twin.emulators.cia402_drive import FAULTS, Cia402Drive
from twin.emulators.popup_boards import BoardNode
from twin.ptyhost import PtyHost
from twin.world import World

log = logging.getLogger(__name__)


class Rig:
    """One simulated bench, advanced to the wall clock whenever a device is touched or the host ticks."""

    def __init__(
        self,
        robot: RobotDescription,
        seed: int = 0,
        q0: np.ndarray | None = None,
        pressure_pa: np.ndarray | None = None,
        valve_open: np.ndarray | None = None,
        factory: bool = False,
    ) -> None:
        """The arm at ``q0`` (rad; default the home pose), its links at ``pressure_pa`` (default the operating
        maximum) with the valves ``valve_open`` (default open: regulated); its devices as the description
        configures them, or as they come out of the box (``factory``)."""
        self.robot = robot
        self.factory = factory
        home = np.deg2rad([0.0, 30.0, -60.0]) if q0 is None else q0
        self.world = World(robot, batch=1, seed=seed, q0=home, pressure_pa=pressure_pa)
        if valve_open is not None:
            self.world.set_valves(np.asarray(valve_open, bool))
        self.recent = RecentSteps(self.world.dt)  # the last steps, for samples due a little in the past
        self.recent.append(self.world.step(1))
        self.steps = 1
        self.emulators: dict[str, Emulator] = {}
        self.can_bus: CanBus | None = None
        self.drives: dict[int, Cia402Drive] = {}
        self.boards: dict[str, BoardNode] = {}  # the boards on a CAN bus, by device name
        self.coil = TwinTrackerSource(self)
        for name, kind in device_kinds(robot).items():  # each device's kind builds its emulator
            spec = robot.devices[name]
            if spec.bus is not None or kind.emulator is None:  # on another's bus: that bus attaches it
                continue
            emulator = resolve(kind.emulator)(self, name, spec)
            if emulator is not None:
                self.emulators[name] = emulator
        # a hammer tap's first call loads four compiled kernel functions (~20 ms here, seconds where numba
        # has no cache yet): done now, not mid-session, where it stalled every stream of the rig at once
        self.world.virtual_joint_inertia()

    def advance(self, now_s: float) -> None:
        """Step the twin up to ``now_s`` (rig time): it has then taken ``int(now_s / dt)`` steps."""
        n = int(now_s / self.world.dt) - self.steps
        if n > 0:
            self.recent.append(self.world.step(n))
            self.steps += n

    def step_due_s(self, steps: int) -> float:
        """The rig time from which ``advance`` has taken ``steps`` steps (a hair after ``steps · dt``)."""
        return (steps + 1e-3) * self.world.dt

    def ticks(self, device: str) -> int:
        """``device``'s own counter at the twin's current time: ``SimulatedClocks.ticks_at`` in Python floats
        (the same IEEE operations in the same order, so the same count, without numpy's per-call cost)."""
        clocks = self.world.clocks[device]
        seconds = (1.0 + float(clocks.drift_ppm[0]) * 1e-6) * self.world.t + float(clocks.offset_s[0])
        count = math.floor(seconds / clocks.spec.tick_s + TICK_EPS)
        return count % clocks.spec.wrap if clocks.spec.wrap is not None else count

    def control(self, cmd: dict) -> dict:
        """Operator inputs and queries from the control socket."""
        op = cmd["op"]
        if op == "payload":
            self.world.set_payload(float(cmd["kg"]))
            return {"ok": True}
        if op == "tap":  # a hammer tap on the last link (angular impulse, N·m·s)
            self.world.tap(float(cmd["nms"]))
            return {"ok": True}
        if op == "coil":  # the tracker coil leaves (inside=false) or re-enters the field volume
            self.coil.force_out = not _flag(cmd, "inside")
            return {"ok": True}
        if op == "servos":  # only these joints' servos connected to their bus (new servos, one at a time)
            return self._plug_servos(cmd)
        if op == "can":  # the CAN bus's faults and counters
            return self._can_control(cmd)
        if op == "state":
            st = self.world.state
            cmd = self.world.commands  # what the emulators passed on to the twin (what the devices took)
            return {"ok": True, "t": st.t, "q": st.out_pos[0].tolist(), "delta": st.delta[0].tolist(),
                    "pressure_pa": st.p_link[0].tolist(), "goal_q": cmd.goal[0].tolist(),
                    "pressure_set_pa": cmd.pressure_set[0].tolist()}  # fmt: skip
        raise ValueError(f"unknown command {op!r}")

    def _plug_servos(self, cmd: dict) -> dict:
        """``{"op": "servos", "connected": ["q3", ...]}``: the servos of these joints on the bus, the others'
        cables out (a servo is known to its bus by its described ID, whatever ID it has been given)."""
        joints = cmd.get("connected")
        for name, spec in self.robot.devices.items():
            bus = self.emulators.get(name)
            if not spec.ids or not hasattr(bus, "plug"):
                continue
            if not isinstance(joints, list) or not set(joints) <= set(spec.ids):
                raise ValueError(f"servos: 'connected' lists joints of {sorted(spec.ids)}, got {joints!r}")
            bus.plug({spec.ids[j] for j in joints})
            return {"ok": True}
        raise ValueError(f"{self.robot.name} has no servo bus")

    def _can_control(self, cmd: dict) -> dict:
        """``{"op": "can", "bus_off": bool}``, ``{"op": "can", "node": id, "power": bool}`` (a drive loses its
        supply: silent, no heartbeat), ``{"op": "can", "node": id, "fault": code}`` (a drive fault: EMCY),
        ``{"op": "can", "board": name, "power": bool}`` (a board's frames stop or resume),
        ``{"op": "can"}`` alone: the bus's counters."""
        if self.can_bus is None:
            raise ValueError(f"{self.robot.name} has no CAN bus")
        now = self.world.t
        if "bus_off" in cmd:
            self.can_bus.set_bus_off(_flag(cmd, "bus_off"))
        if "board" in cmd:
            board = self.boards.get(str(cmd["board"]))
            if board is None:
                raise ValueError(f"no board {cmd['board']!r} on the bus (boards: {sorted(self.boards)})")
            board.power(_flag(cmd, "power"), now)
        if "node" in cmd:
            drive = self.drives.get(int(cmd["node"]))
            if drive is None:
                raise ValueError(f"no drive {cmd['node']} on the bus (drives: {sorted(self.drives)})")
            if "power" in cmd:
                drive.power(_flag(cmd, "power"), now)
            if "fault" in cmd:
                code = int(cmd["fault"])
                if code not in FAULTS:
                    raise ValueError(f"fault code {code:#06x} not one of {[hex(c) for c in FAULTS]}")
                drive.fault(code, now)
        counters = dataclasses.asdict(self.can_bus.counters)  # frames, bits, busy_s, lost, delayed, …
        dropped = dict(self.can_bus.dropped)  # per node: frames lost on its full transmit queue
        return {"ok": True, "bitrate": self.can_bus.bitrate, **counters, "dropped": dropped, "t": now,
                "bus_off": self.can_bus.bus_off}  # fmt: skip


def _flag(cmd: dict, key: str) -> bool:
    """A control command's true/false field; anything else (a string, a number, missing) is refused."""
    value = cmd.get(key)
    if not isinstance(value, bool):
        raise ValueError(f"{cmd.get('op')}: {key!r} must be true or false, got {value!r}")
    return value


def serve_rig(robot: RobotDescription, run_dir: Path, seed: int = 0, start: dict | None = None,
              factory: bool = False) -> None:  # fmt: skip
    """Run the rig until SIGTERM/SIGINT; ``start``: Rig's ``q0``, ``pressure_pa``, ``valve_open`` (see
    :func:`bench_start`); ``factory``: the devices as they come out of the box, behind adapters at the
    driver's latency timer (16 ms), rather than as the description configures them."""
    numba.set_num_threads(1)  # one robot: worker threads would only steal the client's core
    rig = Rig(robot, seed=seed, factory=factory, **(start or {}))
    timers = {name: robot.devices[name].host_link.latency_timer_s for name in rig.emulators}
    if factory:  # an FTDI adapter at its driver's timer (a USB CDC device, at 0, has none)
        timers = {name: FTDI_DEFAULT_LATENCY_S if s > 0 else 0.0 for name, s in timers.items()}
    host = PtyHost(run_dir, rig.emulators, tick=rig.advance, control=rig.control, latency_timers=timers)
    settle_heap()
    log.info("rig for %s serving %s in %s", robot.name, ", ".join(rig.emulators), run_dir)
    host.serve_forever()


def bench_start(robot: RobotDescription, start: dict) -> dict:
    """``start`` ({"q_rad": [...], "pressure_pa": [...], "valve_open": [...]}, any of them) checked against
    the robot: Rig's keyword arguments. A value of the wrong size or kind is a ValueError."""
    channels = robot.pneumatics.channels
    sizes = {"q_rad": len(robot.actuated_joints), "pressure_pa": channels, "valve_open": channels}
    if not isinstance(start, dict):
        raise ValueError(f"start must be a JSON object, got {type(start).__name__}")
    out = {}
    for key, value in start.items():
        if key not in sizes:
            raise ValueError(f"start: unknown key {key!r} (known: {', '.join(sizes)})")
        flags = key == "valve_open"
        valid = isinstance(value, list) and all(
            type(v) is bool
            if flags
            else isinstance(v, int | float) and type(v) is not bool and math.isfinite(v)
            for v in value
        )
        if not valid or len(value) != sizes[key]:
            kind = "booleans" if flags else "finite numbers"
            raise ValueError(f"start: {key} must be {sizes[key]} {kind}, got {value!r}")
        out["q0" if key == "q_rad" else key] = np.array(value, bool if flags else float)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="vsl")
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--parent-pid", type=int, help="end (in order) when this process dies")
    parser.add_argument(
        "--start", type=Path, help="the bench's start: JSON with q_rad, pressure_pa, valve_open"
    )
    parser.add_argument("--factory", action="store_true", help="the devices as they come out of the box")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.parent_pid is not None:  # a rig started for one recording dies with it, even by SIGKILL
        die_with_parent(args.parent_pid)
    # the rig stands in for hardware, which a busy computer does not slow down: a real-time priority above
    # the daemons' where the OS allows it (below them, two busy daemons on a 2-core machine kept it from
    # answering a 1 kHz servo bus in time: the losses were the twin's, not the recorder's)
    log.info("rig priority: %s", elevate(fifo_priority=RT_PRIORITY + 1))
    robot = load_robot(args.robot)
    start = None
    if args.start is not None:
        try:
            start = bench_start(robot, json.loads(args.start.read_text()))
        except (OSError, ValueError) as exc:
            parser.error(f"--start {args.start}: {exc}")
    serve_rig(robot, args.run_dir, args.seed, start, factory=args.factory)


if __name__ == "__main__":
    main()
