"""The real-time runner: a plan executed on the devices (hardware or the rig) while a Recorder records.

Commands go through the recorder to the device daemons (each owns its port), which record them as sent:
servo goals on ``/servo/goal``, pressure set-points and valves on ``/pressure/command``. The plan's clock is
the host's monotonic clock, paused while the operator is busy (hanging a payload, tapping the link). Every
``1/check_hz`` the latest measured state is checked against the safety limits; a violation, a device silent
for longer than ``stale_s``, a fault a device reports (a drive's EMCY) or Ctrl-C makes a safe stop: the
servos (or CiA 402 drives) hold where they are, the stepper stops, the pressures stay (an inflatable arm must
not be vented under load), a SAFETY_STOP event says why, and the session stays valid. Every command passes
the command guard before it is sent (a compensator's output included): one outside the robot's limits, or
not a number, is a safe stop too, and nothing of it is sent. The daemons check again where the ports are; a
refusal there also stops the plan.

A plan's ``settle`` waits for the bench, not only for its time: the plan's clock stands at each SETTLED
event until the measured joints have been still and every regulated pressure at its set-point for
``SETTLE_WINDOW_S`` (the arm still moving to a test pose, a link still filling), or stops the plan when that
takes longer than ``settle_timeout_s``. A simulated run starts at the plan's first pose; the robot does not.

    with Recorder(robot, ports, directory, session_id) as rec:
        report = RealTimeRunner(rec, plan, on_payload=prompt).run()
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from acquisition.command_guard import CommandGuard, CommandRefused
from acquisition.devices.base import host_now_ns
from acquisition.devices.kinds import device_of
from acquisition.errors import AcquisitionError
from acquisition.plans.compensation import Compensator
from acquisition.plans.plan import Plan
from acquisition.recorder.recorder import Recorder
from acquisition.safety import SafetyChecker, Violation
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind

log = logging.getLogger(__name__)

# settled, over the last SETTLE_WINDOW_S: no joint drifted more than SETTLE_DRIFT_RAD (the mean of its first
# and of its last fifth: a slow creep to the goal counts, encoder noise averages out) nor spread more than
# SETTLE_SPREAD_RAD, and every regulated pressure stayed within SETTLE_PRESSURE_PA of its set-point (or
# SETTLE_PRESSURE_FRACTION of it, if more). ASSUMED: a drive creeping its last counts at 2 mrad/s moves the
# tip of an 0.3 m link by over 1 mm during a 2 s hold; 0.3 mrad in 0.4 s stops that
SETTLE_WINDOW_S, SETTLE_DRIFT_RAD, SETTLE_SPREAD_RAD = 0.5, 3e-4, 5e-3
SETTLE_PRESSURE_PA, SETTLE_PRESSURE_FRACTION = 2000.0, 0.03
# still joints are not a still arm: a soft link under a payload goes on bouncing (POPUP's link 2 under 2 kg
# at 60 kPa: ±4 mm at 1.6 Hz, 4 s after its joints stopped). Where the tracker sees the tip, its standard
# deviation over the window (per axis) must be within SETTLE_TIP_STD_M too: 3× the tracker's noise (0.25 mm
# SOURCE, Aurora class), a bounce of ≤ 1 mm amplitude. Frames without a pose do not count.
SETTLE_TIP_STD_M, SETTLE_TIP_MIN_FRAMES = 0.75e-3, 8


class RunnerError(AcquisitionError, RuntimeError):
    """The plan cannot start (a device the plan needs is missing or silent)."""


@dataclass
class RunReport:
    plan: str
    status: str  # "complete", "stopped" (a safety limit or a lost device), "interrupted" (operator)
    elapsed_s: float  # plan time reached
    reason: str = ""
    commands: int = 0
    violations: list[Violation] = field(default_factory=list)


class RealTimeRunner:
    def __init__(
        self,
        recorder: Recorder,
        plan: Plan,
        compensator: Compensator | None = None,
        on_payload: Callable[[float], None] | None = None,
        on_tap: Callable[[float], None] | None = None,
        tick_s: float = 0.002,
        check_hz: float = 20.0,
        stale_s: float = 0.5,
        settle_timeout_s: float = 30.0,
    ) -> None:
        self.rec, self.plan, self.robot = recorder, plan, recorder.robot
        if plan.robot != self.robot.name:
            raise ValueError(f"plan {plan.name} is for {plan.robot}, the recorder records {self.robot.name}")
        self.compensator = compensator
        self.on_payload, self.on_tap = on_payload, on_tap
        self.tick_s, self.check_period, self.stale_ns = tick_s, 1.0 / check_hz, int(stale_s * 1e9)
        self.settle_timeout_s = settle_timeout_s
        self._recent: deque[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = deque()  # (monotonic, q,
        # pressure, tip: the latest tracker position, NaN without one)
        self.safety = SafetyChecker(self.robot)
        self.guard = CommandGuard(self.robot)
        joints = self.robot.joints
        self.servo_joints = [i for i, j in enumerate(joints) if j.drive != "stepper"]
        self.stepper_joints = [i for i, j in enumerate(joints) if j.drive == "stepper"]
        joints_dev = device_of(self.robot, "joints")
        if joints_dev is not None:  # goals in the bus's id order (Dynamixel IDs, CANopen node ids)
            names = [j.name for j in joints]
            ids = self.robot.devices[joints_dev].ids
            self.servo_joints = [names.index(n) for n in ids if n in names]
        # the servos' Sync Reads (current in A) or the CiA 402 drives' answers to SYNC (torque, no current)
        self.joint_topic = T.joint_state_topic(self.robot) or T.SERVO_STATE
        self.commands = 0
        self._goal_seq = self._pressure_seq = 0
        self._refused = self._faults = 0  # refusals and device faults before this plan started

    # --------------------------------------------------------------------------------------- running
    def run(self) -> RunReport:
        """Run the plan to its end, a safety stop or Ctrl-C (a safe stop too); never raises on those."""
        plan = self.plan
        self.safety.require_safe(plan)
        self._require_devices()
        q, pressure = self._measured()[:2]
        if problems := self.safety.check_start(plan, q, pressure):
            raise RunnerError(f"plan {plan.name} cannot start on the bench as it is: "
                              + "; ".join(v.detail for v in problems))  # fmt: skip
        self._refused, self._faults = self.rec.refusals()[0], self.rec.faults()[0]
        self.rec.event(Event(EventKind.PLAN_STEP, 0, label="plan-start", text=plan.name))
        self._send_torque(True)
        cursor = {"goal": -1, "pressure": -1, "payload": -1, "tap": -1, "event": 0}
        payload = float(plan.payload_kg[0])
        settles = [at for at, e in plan.events if e.kind == EventKind.SETTLED]
        settling_since = None  # when the clock reached the next settle and stood still (time.monotonic)
        start, paused, next_check, t = time.monotonic(), 0.0, 0.0, 0.0
        try:
            while t <= plan.duration_s:
                now = time.monotonic()
                t = now - start - paused
                if settles and t >= settles[0] - SETTLE_WINDOW_S:  # the window before a settle, and at it
                    self._remember(*self._measured()[:2], self._tip())
                if settles and t >= settles[0]:  # the clock stands just before a settle until the bench is
                    settling_since = settling_since or now
                    # what the bench settles to: the commands in force up to the settle (those at its
                    # instant, such as the next link's valve opening, come after it)
                    before = max(float(np.nextafter(settles[0], 0.0)), 0.0)
                    if self._settled(plan.at(np.array([before]))):
                        settles.pop(0)
                        settling_since = None
                    elif now - settling_since > self.settle_timeout_s:
                        return self._safe_stop("stopped", settles[0], "settle", self._unsettled(before))
                    else:
                        paused, t = paused + t - settles[0] + 1e-9, settles[0] - 1e-9
                g = int(np.searchsorted(plan.goal_t, t, side="right")) - 1
                try:
                    if g != cursor["goal"]:
                        cursor["goal"] = g
                        self._send_goals(plan.goal_q[g], plan.goal_speed[g])
                    p = int(np.searchsorted(plan.pressure_t, t, side="right")) - 1
                    if p != cursor["pressure"]:
                        cursor["pressure"] = p
                        self._send_pressures(plan.pressure_pa[p], plan.valve_open[p])
                except CommandRefused as exc:
                    self.rec.event(Event(EventKind.COMMAND_REFUSED, label="runner", text=str(exc)))
                    return self._safe_stop("stopped", t, "command", f"refused: {exc}")
                m = int(np.searchsorted(plan.payload_t, t, side="right")) - 1
                if m != cursor["payload"]:
                    cursor["payload"], payload = m, float(plan.payload_kg[m])
                    paused += self._operator(self.on_payload, payload)
                k = int(np.searchsorted(plan.tap_t, t, side="right")) - 1
                if k != cursor["tap"] and k >= 0:
                    cursor["tap"] = k
                    paused += self._operator(self.on_tap, float(plan.tap_impulse_nms[k]))
                while cursor["event"] < len(plan.events) and plan.events[cursor["event"]][0] <= t:
                    # stamped at its plan time on the host's clock, not when this loop came to it: a hold
                    # (SETTLED, its length) then ends before the next goal goes out, however late the loop
                    # ran (stamped on pushing, a loop held up on a busy machine put the start of the next
                    # move inside the hold, and the build rejected it for motion)
                    at, event = plan.events[cursor["event"]]
                    self.rec.event(event, host_ns=round((start + paused + max(at, 0.0)) * 1e9))
                    cursor["event"] += 1
                if now >= next_check:  # on the host's clock: the checks go on while the plan's stands
                    next_check = now + self.check_period
                    problem = self._check(t, payload)
                    if problem is not None:
                        return self._safe_stop("stopped", t, *problem)
                time.sleep(self.tick_s)
        except KeyboardInterrupt:
            return self._safe_stop("interrupted", t, "operator", "Ctrl-C")
        self.rec.event(Event(EventKind.PLAN_STEP, 1, label="plan-end", text=plan.name))
        return RunReport(plan.name, "complete", plan.duration_s, commands=self.commands)

    def _operator(self, action: Callable[[float], None] | None, value: float) -> float:
        """Hand over to the operator (or the rig) and return how long the plan clock was paused."""
        if action is None:
            return 0.0
        before = time.monotonic()
        action(value)
        return time.monotonic() - before

    def _needed(self) -> list[str]:
        """The streams the plan commands by (and watches)."""
        needed = [self.joint_topic] if self.servo_joints else []
        needed.append(T.PRESSURE)
        return needed + ([T.STEPPER] if self.stepper_joints else [])

    def _require_devices(self, timeout_s: float = 5.0) -> None:
        """Every device the plan commands must be connected and streaming before the first command."""
        deadline = time.monotonic() + timeout_s
        for topic in self._needed():
            if not self.rec.has(topic):
                raise RunnerError(f"plan {self.plan.name} needs a {topic} device; the recorder has none")
            while self.rec.latest(topic) is None:
                if time.monotonic() > deadline:
                    raise RunnerError(f"no {topic} samples ({self.rec.error(topic) or 'silent'})")
                time.sleep(0.01)

    # -------------------------------------------------------------------------------------- settling
    def _settled(self, cmd: dict) -> bool:
        """Whether the joints have been still, and every pressure whose valves the plan holds open at its
        set-point ``cmd`` (``Plan.at``), over the last ``SETTLE_WINDOW_S`` (sampled every tick)."""
        recent = self._recent
        if not recent or recent[-1][0] - recent[0][0] < 0.9 * SETTLE_WINDOW_S:
            return False
        q = np.array([r[1] for r in recent])
        pressure = np.array([r[2] for r in recent])
        setpoint, regulated = cmd["pressure_pa"][0], cmd["valve_open"][0]
        allowance = np.maximum(SETTLE_PRESSURE_PA, SETTLE_PRESSURE_FRACTION * setpoint)
        off = np.abs(pressure - setpoint) > allowance
        return bool(_drift(q).max() <= SETTLE_DRIFT_RAD and np.ptp(q, axis=0).max() <= SETTLE_SPREAD_RAD
                    and not off[:, regulated].any() and self._tip_still())  # fmt: skip

    def _tip_spread(self) -> float:
        """The largest per-axis standard deviation (m) of the tracked tip's distinct frames in the window;
        NaN when the tracker saw it in fewer than SETTLE_TIP_MIN_FRAMES of them (none, or out of view)."""
        tips = np.array([r[3] for r in self._recent])
        tips = tips[np.isfinite(tips).all(axis=1)]
        frames = np.unique(tips, axis=0)  # sampled every tick: the same frame many times
        return float(frames.std(axis=0).max()) if len(frames) >= SETTLE_TIP_MIN_FRAMES else float("nan")

    def _tip_still(self) -> bool:
        spread = self._tip_spread()
        return not spread > SETTLE_TIP_STD_M  # no view of the tip: the joints and pressures decide

    def _tip(self) -> np.ndarray:
        """The latest tracked tip position (3,), NaN without a tracker or a pose."""
        s = self.rec.latest(T.TRACKER) if self.rec.has(T.TRACKER) else None
        if s is None or bool(s.values["missing"]):
            return np.full(3, np.nan)
        return np.asarray(s.values["position"], float)

    def _unsettled(self, at: float) -> str:
        """What kept the bench from settling to the commands in force at plan time ``at``, in words."""
        if not self._recent:
            return f"no measurements in {self.settle_timeout_s:g} s"
        q = np.array([r[1] for r in self._recent])
        moved, spread = _drift(q), np.ptp(q, axis=0)
        joint = self.robot.joints[int(moved.argmax())].name
        cmd = self.plan.at(np.array([at]))
        pressure, setpoint, regulated = self._recent[-1][2], cmd["pressure_pa"][0], cmd["valve_open"][0]
        links = ", ".join(
            f"{p / 1e3:.1f} kPa" + (f" (set {s / 1e3:g})" if r else " (held)")
            for p, s, r in zip(pressure, setpoint, regulated, strict=True)
        )
        tip = self._tip_spread()
        return (
            f"not settled in {self.settle_timeout_s:g} s: {joint} drifted {moved.max() * 1e3:.2f} mrad "
            f"(spread {spread.max() * 1e3:.2f} mrad) in {SETTLE_WINDOW_S:g} s; links at {links}"
            + (f"; the tip moved {tip * 1e3:.2f} mm (std)" if tip == tip else "")
        )

    def _remember(self, q: np.ndarray, pressure: np.ndarray, tip: np.ndarray) -> None:
        now = time.monotonic()
        self._recent.append((now, q, pressure, tip))
        while now - self._recent[0][0] > SETTLE_WINDOW_S:
            self._recent.popleft()

    # --------------------------------------------------------------------------------------- sending
    def _measured(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Latest joint angles (A,), link pressures (C,), joint currents (A,) and the oldest stamp used."""
        q = np.zeros(len(self.robot.joints))
        current = np.zeros(len(self.robot.joints))
        stamps = []
        if self.servo_joints:
            s = self.rec.latest(self.joint_topic)
            q[self.servo_joints] = s.values["position"]
            if self.joint_topic == T.SERVO_STATE:  # the CiA 402 drives report torque: no current to give
                current[self.servo_joints] = s.values["current"]
            stamps.append(s.host_ns)
        if self.stepper_joints:
            s = self.rec.latest(T.STEPPER)
            q[self.stepper_joints] = s.values["position"]
            stamps.append(s.host_ns)
        s = self.rec.latest(T.PRESSURE)
        stamps.append(s.host_ns)
        return q, np.asarray(s.values["pressure"], float), current, min(stamps)

    def _send_goals(self, q_goal: np.ndarray, speed: np.ndarray) -> None:
        """Send the goals (compensated where a compensator is set); CommandRefused before anything is sent
        when one is outside the limits or not a number."""
        q_cmd = np.asarray(q_goal, float)
        if self.compensator is not None:
            _, pressure, current, stamp_ns = self._measured()
            q_cmd = np.asarray(
                self.compensator(q_cmd[None], pressure[None], current[None], t_s=stamp_ns * 1e-9), float
            )
            if q_cmd.shape != (1, len(self.robot.joints)):
                raise CommandRefused(f"the compensator returned shape {q_cmd.shape} for one set of goals")
            q_cmd = q_cmd[0]
        q_cmd = self.guard.joint_goals(q_cmd)
        servo, stepper = None, None
        if self.servo_joints:
            joints = self.servo_joints
            speed_s = np.where(speed[joints] > 0, speed[joints], self.robot.servo.profile_velocity_rad_s)
            names = [self.robot.joints[i].name for i in joints]
            servo = self.guard.servo_goals(names, q_cmd[joints], speed_s)
        if self.stepper_joints:
            spec, j = self.robot.stepper, self.stepper_joints[0]
            steps = round(q_cmd[j] / spec.rad_per_microstep)
            rate = (speed[j] if speed[j] > 0 else spec.max_speed_rad_s) / spec.rad_per_microstep
            accel = spec.acceleration_rad_s2 / spec.rad_per_microstep
            stepper = self.guard.stepper_move(self.robot.joints[j].name, steps, min(max(rate, 1.0), 4000.0),
                                              min(max(accel, 1.0), 100_000.0))  # fmt: skip
        self._goal_seq += 1
        if servo is not None:
            position, velocity = servo[0].tolist(), servo[1].tolist()
            self.rec.command(T.SERVO_GOAL, {"op": "goals", "seq": self._goal_seq, "position": position,
                                            "profile_velocity": velocity})  # fmt: skip
        if stepper is not None:
            steps, rate, accel = stepper
            self.rec.command(T.STEPPER, {"op": "move", "steps": steps, "speed": rate, "accel": accel})
        self.commands += 1

    def _send_pressures(self, pressure_pa: np.ndarray, valves: np.ndarray) -> None:
        setpoint, valves = self.guard.pressures(pressure_pa, valves)
        self._pressure_seq += 1
        self.rec.command(T.PRESSURE_COMMAND, {"op": "pressures", "seq": self._pressure_seq,
                                              "setpoint": setpoint.tolist(),
                                              "valve_open": valves.tolist()})  # fmt: skip
        self.commands += 1

    def _send_torque(self, on: bool) -> None:
        if self.servo_joints:
            self.rec.command(T.SERVO_GOAL, {"op": "torque", "on": on})

    # ---------------------------------------------------------------------------------------- safety
    def _check(self, t: float, payload_kg: float) -> tuple[str, str] | None:
        """A reason to stop now: a safety limit on the latest measurements, or a lost or silent device."""
        # a device that drops out and reconnects within stale_s (a missed reply, a busy host) is not a stop;
        # one whose samples are older than that is
        if getattr(self.rec, "write_error", None):  # the session cannot be written (a full disk)
            return "recording", f"the session writer failed: {self.rec.write_error}"
        refused, why = self.rec.refusals()
        if refused > self._refused:
            return "command", f"refused by a device daemon: {why}"
        faults, fault = self.rec.faults()
        if faults > self._faults:
            return "device", f"fault: {fault}"
        q, pressure, _, oldest = self._measured()
        now = host_now_ns()
        if now - oldest > self.stale_ns:
            lost = [topic for topic in self._needed() if not self.rec.connected(topic)]
            silent = [topic for topic in self._needed() if topic not in lost
                      and now - self.rec.latest(topic).host_ns > self.stale_ns]  # fmt: skip
            why = "; ".join([*(f"{topic} lost: {self.rec.error(topic)}" for topic in lost),
                             *(f"{topic} silent, its device connected" for topic in silent)])  # fmt: skip
            return "device", f"no fresh samples for {(now - oldest) / 1e9:.2f} s ({why or 'devices silent'})"
        allow = bool(self.plan.parameters.get("allow_wrinkling"))
        violations = self.safety.check_state(
            np.array([t]), q[None], pressure[None], payload_kg, allow_wrinkling=allow,
            stowed=self.safety.stowed(self.plan, np.array([t])),
        )  # fmt: skip
        if violations:
            return violations[0].limit, violations[0].detail
        return None

    def _safe_stop(self, status: str, t: float, limit: str, why: str) -> RunReport:
        """Hold the servos where they are, stop the stepper, keep the pressures; mark why."""
        log.warning("plan %s: safe stop at %.2f s: %s: %s", self.plan.name, t, limit, why)
        self.rec.event(Event(EventKind.SAFETY_STOP, label=limit, text=why))
        if self.servo_joints:
            self.rec.command(T.SERVO_GOAL, {"op": "hold"})  # where its daemon last read them
        if self.stepper_joints:
            self.rec.command(T.STEPPER, {"op": "stop"})
        return RunReport(self.plan.name, status, t, f"{limit}: {why}", self.commands)


def _drift(q: np.ndarray) -> np.ndarray:
    """How far each joint moved over samples ``q`` (N, A): the mean of their last fifth less their first's."""
    fifth = max(len(q) // 5, 1)
    return np.abs(q[-fifth:].mean(axis=0) - q[:fifth].mean(axis=0))
