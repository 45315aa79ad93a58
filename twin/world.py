"""The digital twin: a batch of simulated lab benches you can command, step and query.

``World`` wraps the compiled kernel (true physics) with the operator's inputs (goals, pressures, valves,
payload), the device clocks and the sensor models. It is deterministic for a given seed: each device of
each bench draws its clock and its noise from a generator of its own, the seed spawned by the bench's name and
the device's (:meth:`World.noise`, ``twin.noise``), in the order the caller asks for readings; adding a device
to a description changes no other device's draws, and a bench's draws do not depend on its batch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from acquisition.devices.kinds import device_kinds, resolve
from models.effects import creep_rest
from models.prbm import interp_table
from models.robot import TIP_FRAME, RobotDescription
from twin import kernel, streams
from twin.clocks import SimulatedClocks, SimulatedClockSpec
from twin.noise import BenchNoise

DEFAULT_DT = 1e-3  # 1 kHz


@dataclass(frozen=True)
class Layout:
    """Names of the batch arrays' last axes, in order."""

    actuated: tuple[str, ...]
    virtual: tuple[str, ...]
    channels: int


def build_params(robot: RobotDescription, dt: float = DEFAULT_DT) -> kernel.KernelParams:
    """Translate a validated description into the kernel's plain arrays."""
    rows = robot.dh_rows()
    actuated = robot.actuated_joints
    virtual = robot.virtual_joints
    row_names = [r.joint for r in rows]
    row_virtual = np.array([not r.joint.startswith("q") for r in rows])
    row_var = np.array(
        [virtual.index(n) if v else actuated.index(n) for n, v in zip(row_names, row_virtual, strict=True)]
    )

    masses = robot.masses
    tool = np.array(robot.tool_offset_m, dtype=float)
    mass_frame = np.array(
        [len(rows) - 1 if m.frame == TIP_FRAME else row_names.index(m.frame) for m in masses]
    )
    mass_pos = np.array(
        [np.add(m.position_m, tool) if m.frame == TIP_FRAME else m.position_m for m in masses], dtype=float
    ).reshape(-1, 3)

    links = robot.links
    row_channel, row_strain = robot.elongating_rows()  # effects.elongation (models.robot)
    tables = [robot.link_table(link.name) for link in links]
    width = max(len(t.pressure_pa) for t in tables)

    def padded(values: list[float]) -> np.ndarray:
        return np.pad(np.asarray(values, dtype=float), (0, width - len(values)), mode="edge")

    link_index = {link.name: i for i, link in enumerate(links)}
    drives = {j.name: j.drive for j in robot.joints}
    servo, stepper, pn = robot.servo, robot.stepper, robot.pneumatics
    is_stepper = np.array([drives[a] == "stepper" for a in actuated])
    creep = robot.effects.creep
    hoses = robot.effects.hoses.joints if robot.effects.hoses else {}
    return kernel.KernelParams(
        dt=dt,
        gravity=np.array(robot.gravity_m_s2, dtype=float),
        row_a=np.array([r.a_m for r in rows]),
        row_alpha_cs=np.array([[math.cos(r.alpha_rad), math.sin(r.alpha_rad)] for r in rows]),
        row_d=np.array([r.d_m for r in rows]),
        row_offset=np.array([r.offset_rad for r in rows]),
        row_virtual=row_virtual,
        row_var=row_var,
        row_channel=row_channel,
        row_strain=row_strain,
        tool_offset=tool,
        mass_frame=mass_frame,
        mass_pos=mass_pos,
        mass_kg=np.array([m.mass_kg for m in masses], dtype=float),
        mass_inertia=np.array([m.inertia_kgm2 for m in masses], dtype=float),
        vj_link=np.array([link_index[robot.link_of(v).name] for v in virtual], dtype=np.int64),
        vj_delta_h=np.array([robot.link_of(v).hysteresis.delta_h_rad for v in virtual]),
        vj_tau_y=np.array([robot.link_of(v).hysteresis.tau_y_nm for v in virtual]),
        vj_radius=np.array([robot.link_of(v).radius_m or 0.0 for v in virtual]),
        link_channel=np.array([-1 if ln.pressure_channel is None else ln.pressure_channel for ln in links]),
        table_n=np.array([len(t.pressure_pa) for t in tables], dtype=np.int64),
        table_p=np.array([padded(t.pressure_pa) for t in tables]),
        table_k=np.array([padded(t.stiffness_nm_per_rad) for t in tables]),
        table_c=np.array([padded(t.damping_nms_per_rad) for t in tables]),
        drive_kind=np.where(is_stepper, kernel.DRIVE_STEPPER, kernel.DRIVE_POSITION_LOOP).astype(np.int64),
        drive_stiffness=np.full(len(actuated), servo.stiffness_nm_per_rad if servo else 1.0),
        drive_tau=np.full(len(actuated), servo.loop_time_constant_s if servo else 1.0),
        drive_backlash_half=np.full(len(actuated), servo.backlash_rad / 2 if servo else 0.0),
        drive_quantum=np.where(is_stepper, stepper.rad_per_microstep if stepper else 0.0, 0.0),
        drive_max_torque=np.where(is_stepper, np.inf, servo.max_torque_nm if servo else np.inf),
        drive_max_speed=np.where(
            is_stepper,
            stepper.max_speed_rad_s if stepper else np.inf,
            servo.max_speed_rad_s if servo else np.inf,
        ),
        reg_alpha=1.0 - math.exp(-dt / pn.regulator_time_constant_s),
        reg_max=pn.regulator_max_pa,
        leak_factor=math.exp(-dt / pn.leak_time_constant_s),
        creep_a=np.array(creep.fractions if creep else (), dtype=float),
        creep_alpha=np.array([-math.expm1(-dt / tc) for tc in (creep.time_constants_s if creep else ())]),
        hose_k=np.array([hoses[a].stiffness_nm_per_rad if a in hoses else 0.0 for a in actuated]),
        hose_slack=np.array([hoses[a].slack_rad if a in hoses else 0.0 for a in actuated]),
    )


class World:
    """A batch of ``batch`` independent robots of one description, stepped together at ``dt``.

    Commands are per robot (arrays with a leading batch axis, or scalars broadcast to all). ``step(n)``
    returns the true trace of those steps; ``state`` is the latest true state. ``benches``: the benches'
    names, by which each draws its noise (the simulated runner names them by their sessions). ``devices``
    False: the physics alone, without the devices' clocks (nothing to read; a fit making moves again).
    """

    def __init__(
        self,
        robot: RobotDescription,
        batch: int = 1,
        seed: int = 0,
        dt: float = DEFAULT_DT,
        q0: np.ndarray | None = None,
        pressure_pa: float | np.ndarray | None = None,
        payload_kg: float | np.ndarray = 0.0,
        benches: Sequence[str] | None = None,
        devices: bool = True,
    ) -> None:
        if batch < 1:
            raise ValueError(f"batch must be ≥ 1, got {batch}")
        self.robot = robot
        self.batch = batch
        self.dt = dt
        self.seed, self.benches = seed, None if benches is None else list(benches)
        self._noise: dict[str, BenchNoise] = {}
        self.params = build_params(robot, dt)
        self.layout = Layout(
            tuple(robot.actuated_joints), tuple(robot.virtual_joints), robot.pneumatics.channels
        )
        a, v, c = len(self.layout.actuated), len(self.layout.virtual), self.layout.channels
        q_init = np.broadcast_to(np.zeros(a) if q0 is None else np.asarray(q0, float), (batch, a)).copy()
        p_init = robot.pneumatics.max_operating_pa if pressure_pa is None else pressure_pa
        p_init = np.broadcast_to(np.asarray(p_init, float), (batch, c)).copy()
        depth = max(1, round(robot.pneumatics.regulator_dead_time_s / dt)) + 1
        self.state = kernel.KernelState(
            t=0.0,
            ref_pos=q_init.copy(),
            ref_vel=np.zeros((batch, a)),
            loop_pos=q_init.copy(),
            loop_vel=np.zeros((batch, a)),
            loop_acc=np.zeros((batch, a)),
            out_pos=q_init.copy(),
            out_vel=np.zeros((batch, a)),
            torque=np.zeros((batch, a)),
            delta=np.zeros((batch, v)),
            delta_dot=np.zeros((batch, v)),
            hyst_z=np.zeros((batch, v)),
            creep=np.zeros((batch, v, len(self.params.creep_a))),
            vj_torque=np.zeros((batch, v)),
            reg_buf=np.repeat(p_init[:, :, None], depth, axis=2),
            buf_idx=0,
            reg_out=p_init.copy(),
            p_link=p_init.copy(),
        )
        servo = robot.servo
        self.commands = kernel.KernelCommands(
            goal=q_init.copy(),
            profile_vel=np.full((batch, a), servo.profile_velocity_rad_s if servo else 0.0),
            profile_acc=np.full((batch, a), servo.profile_acceleration_rad_s2 if servo else 0.0),
            pressure_set=p_init.copy(),
            valve_open=np.ones((batch, c), dtype=bool),
            payload_kg=np.broadcast_to(np.asarray(payload_kg, float), (batch,)).copy(),
        )
        if robot.stepper is not None:
            steppers = [i for i, j in enumerate(robot.joints) if j.drive == "stepper"]
            self.commands.profile_vel[:, steppers] = robot.stepper.max_speed_rad_s
            self.commands.profile_acc[:, steppers] = robot.stepper.acceleration_rad_s2
        self._start_at_rest()
        self.clocks = {  # devices=False: the physics alone, nothing to read (a fit making moves again)
            name: SimulatedClocks(_clock_spec(dev.clock), batch, self.noise(name).per_bench())
            for name, dev in (robot.devices.items() if devices else ())
        }
        self.tip_tail: tuple[float, np.ndarray] | None = None  # (time, last two tip positions) of a read

    def _start_at_rest(self) -> None:
        """Start with the drives already drooped under gravity (a few fixed-point steps, clock reset),
        so the first steps do not kick the links."""
        st = self.state
        loop = self.params.drive_kind == kernel.DRIVE_POSITION_LOOP
        for _ in range(4):
            self.step(1)
            target = st.ref_pos - st.torque / self.params.drive_stiffness
            st.loop_pos[:, loop] = target[:, loop]
            st.out_pos[:, loop] = target[:, loop]
            for arr in (st.loop_vel, st.loop_acc, st.out_vel, st.delta_dot):
                arr[:] = 0.0
        # links that have held their load long before the session: creep at rest (its share of the bending)
        st.creep[:] = creep_rest(self.robot.effects.creep, st.vj_torque / self._link_stiffness())
        st.delta += st.creep.sum(axis=2)
        st.t = 0.0

    def rest_links(self, iterations: int = 6) -> None:
        """Put every link at rest where its load bends it now (δ = τ/k by a few fixed-point steps, δ̇ = 0),
        instead of letting it fall from straight and ring down (about a second at the VSL links' damping)."""
        st = self.state
        for _ in range(iterations):
            clock = st.t
            self.step(1)
            st.delta[:] = st.vj_torque / self._link_stiffness() + st.creep.sum(axis=2)
            st.delta_dot[:] = 0.0
            st.t = clock

    def _link_stiffness(self) -> np.ndarray:
        """(B, V) each virtual joint's stiffness k(p) at its link's pressure now."""
        p, st = self.params, self.state
        out = np.empty((self.batch, len(self.layout.virtual)))
        for v, link in enumerate(p.vj_link):
            ch, m = p.link_channel[link], p.table_n[link]
            pressure = st.p_link[:, ch] if ch >= 0 else np.zeros(self.batch)
            out[:, v] = interp_table(pressure, p.table_p[link, :m], p.table_k[link, :m])
        return out

    def noise(self, device: str) -> BenchNoise:
        """Device ``device``'s noise, each bench's from a generator of its own (``twin.noise``)."""
        if device not in self._noise:
            self._noise[device] = BenchNoise(self.seed, device, self.batch, self.benches)
        return self._noise[device]

    def device_rng(self, device: str) -> np.random.Generator:
        """The single bench's generator for ``device`` (the real-time rig's world: one bench)."""
        if self.batch != 1:
            raise ValueError(f"a batch of {self.batch} benches draws per bench: World.noise({device!r})")
        return self.noise(device).generators[0]

    # ------------------------------------------------------------------------------------ commands
    def command_joints(self, goal_rad: np.ndarray, profile_vel: np.ndarray | None = None,
                       profile_acc: np.ndarray | None = None) -> None:  # fmt: skip
        """New goal positions (B, A) or (A,); optional profile velocity/acceleration (0 = unlimited)."""
        self.commands.goal[:] = goal_rad  # (A,) or (B, A): assignment broadcasts
        if profile_vel is not None:
            self.commands.profile_vel[:] = profile_vel
        if profile_acc is not None:
            self.commands.profile_acc[:] = profile_acc

    def command_pressure(self, pressure_pa: np.ndarray | float) -> None:
        """Regulator set-points (B, C), (C,) or a scalar, clipped to the regulator's span."""
        p = np.clip(pressure_pa, 0.0, self.robot.pneumatics.regulator_max_pa)
        self.commands.pressure_set[:] = p

    def set_valves(self, open_: np.ndarray | bool) -> None:
        """Valve states (True = open to the regulator, False = hold with a slow leak)."""
        self.commands.valve_open[:] = open_

    def set_payload(self, payload_kg: np.ndarray | float) -> None:
        """The operator hangs a payload at the end-effector (per robot)."""
        self.commands.payload_kg[:] = payload_kg

    def virtual_joint_inertia(self) -> np.ndarray:
        """(B, V) inertia (kg·m²) the kernel gives each virtual joint now: the distal masses (payload
        included) about its axis in the current deflected configuration."""
        p, st = self.params, self.state
        rows = np.flatnonzero(p.row_virtual)
        out = np.empty((self.batch, len(self.layout.virtual)))
        frames = np.empty((len(p.row_a) + 2, 4, 4))
        world_pos = np.empty((len(p.mass_kg) + 1, 3))
        loads = np.empty(2)
        row_a = np.empty(len(p.row_a))
        for b in range(self.batch):
            kernel._row_lengths(p.row_a, p.row_channel, p.row_strain, st.p_link[b], row_a)
            kernel._frames(st.out_pos[b], st.delta[b], row_a, p.row_alpha_cs, p.row_d, p.row_offset,
                           p.row_virtual, p.row_var, p.tool_offset, frames)  # fmt: skip
            kernel._mass_positions(frames, p.mass_frame, p.mass_pos, world_pos)
            for i in rows:
                kernel._joint_loads(frames, p.mass_frame, world_pos, p.mass_kg, p.mass_inertia,
                                    self.commands.payload_kg[b], p.gravity, i, loads)  # fmt: skip
                out[b, p.row_var[i]] = loads[1]
        return out

    def tap(self, impulse_nms: np.ndarray | float, virtual_joint: str | None = None) -> None:
        """A hammer tap: an angular impulse (N·m·s, (B,) or scalar; 0 = no tap) on one virtual joint (default
        the chain's last, link 2's distal bending axis), applied as an instant change of its rate δ̇ += J / I
        with the kernel's inertia I; the link then rings freely at its damped frequency."""
        name = virtual_joint or self.layout.virtual[-1]
        if name not in self.layout.virtual:
            raise ValueError(
                f"robot {self.robot.name!r} has no virtual joint {name!r}: {self.layout.virtual}"
            )
        v = self.layout.virtual.index(name)
        impulse = np.broadcast_to(np.asarray(impulse_nms, float), (self.batch,))
        self.state.delta_dot[:, v] += impulse / self.virtual_joint_inertia()[:, v]

    # ----------------------------------------------------------------------------------- stepping
    @property
    def t(self) -> float:
        """Simulated time in seconds."""
        return self.state.t

    def step(self, n: int = 1) -> kernel.Trace:
        """Advance ``n`` steps of ``dt`` and return the true trace of those steps."""
        if n < 0:
            raise ValueError(f"cannot step a negative number of steps ({n})")
        return kernel.advance(self.params, self.state, self.commands, n)

    def run_for(self, seconds: float) -> kernel.Trace:
        """Advance by ``seconds`` of simulated time (rounded to whole steps)."""
        return self.step(round(seconds / self.dt))

    def read(self, trace: kernel.Trace, servo_rate_hz: float = 500.0) -> dict[str, streams.Stream]:
        """What every device reported during ``trace``: one column table per stream (see ``streams``), from
        each device's kind (its ``streams``). Servos are polled by the host at ``servo_rate_hz``; the boards
        and the tracker run on their clocks."""
        calls = [
            (order, i, resolve(ref), name)
            for i, (name, kind) in enumerate(device_kinds(self.robot).items())
            for order, ref in kind.streams
        ]
        out: dict[str, streams.Stream] = {}
        for _, _, stream, name in sorted(calls, key=lambda c: c[:2]):  # the kinds' order
            out.update(stream(self, name, trace, servo_rate_hz))
        return out

    def settle(self, seconds: float = 2.0) -> None:
        """Let drives, pressures and links come to rest at the current commands (trace discarded)."""
        self.run_for(seconds)


def _clock_spec(model) -> SimulatedClockSpec:
    return SimulatedClockSpec(
        tick_s=model.tick_s,
        wrap=model.wrap,
        drift_ppm_sigma=model.drift_ppm_sigma,
        offset_max_s=model.offset_max_s,
    )
