"""The twin's inner loop: true physics of a batch of robots, stepped in simulated time.

One compiled loop over time steps × robots advances the joint drives (Dynamixel-like profile and position
loop with a load-dependent steady-state error and backlash, or a microstepping stepper), the pneumatics
(regulator dead time and lag, valves that hold with a slow leak) and the pseudo-rigid-body link bending
(``models.prbm.link_step``: I δ̈ + c(p) δ̇ + k(p)(δ − w + δ_h z) = τ, an inflatable link softening above
its wrinkling moment M_w(p) and its Bouc–Wen hysteresis driven by the moment beyond M_w; with
``effects.creep``, the creep of its polymer adding Σxᵢ to the bending; with ``effects.elongation``, the
pressurised links' rows lengthened by their pressure), and records the true state of every step. Sensors,
clocks and noise are applied afterwards, vectorised (``sensors``/``clocks``).

The per-step physics comes from ``models.prbm`` compiled with numba, so the numbers the twin produces are
the ones the model functions give (tests call the same functions vectorised).

Simplifications (documented, deliberate): virtual joints are decoupled from each other (each sees the
gravity torque of everything distal to it, its own distal inertia, and the acceleration of the actuated
joints before it about its axis); centrifugal and Coriolis terms are neglected (joint speeds ≤ 3 rad/s).
Drives are bounded by their stall torque and top speed; "unlimited" profiles accelerate with the torque left
after gravity. The position loop is first order with a torque-dependent droop, so when the torque saturates
the output speed overshoots the profile for a few milliseconds (up to ≈ 2× top speed on a jolt).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from models import prbm

_link_step = numba.njit(cache=True, error_model="numpy")(prbm.link_step)
_play = numba.njit(cache=True, error_model="numpy")(prbm.play)
_interp = numba.njit(cache=True, error_model="numpy")(prbm.interp_table_scalar)
_wrinkling_moment = numba.njit(cache=True, error_model="numpy")(prbm.wrinkling_moment)

DRIVE_POSITION_LOOP = 0  # Dynamixel servo or geared motor under position control
DRIVE_STEPPER = 1


@dataclass(frozen=True)
class KernelParams:
    """Plain arrays describing one robot model, shared by every robot of the batch."""

    dt: float
    gravity: np.ndarray  # (3,)
    row_a: np.ndarray  # (R,) D-H rows, standard convention
    row_alpha_cs: np.ndarray  # (R, 2) cos α, sin α (constant: computed once)
    row_d: np.ndarray
    row_offset: np.ndarray
    row_virtual: np.ndarray  # (R,) bool: virtual (link bending) or actuated
    row_var: np.ndarray  # (R,) int: index into q (actuated) or δ (virtual)
    row_channel: np.ndarray  # (R,) int: pressure channel that lengthens the row (effects.elongation), −1 none
    row_strain: np.ndarray  # (R,) 1/Pa: the row's length is a (1 + strain · p) at its channel's pressure p
    tool_offset: np.ndarray  # (3,) in the last frame
    mass_frame: np.ndarray  # (M,) int: row whose output frame carries the mass (R−1 = tip frame)
    mass_pos: np.ndarray  # (M, 3)
    mass_kg: np.ndarray  # (M,)
    mass_inertia: np.ndarray  # (M,)
    vj_link: np.ndarray  # (V,) int link index
    vj_delta_h: np.ndarray  # (V,)
    vj_tau_y: np.ndarray  # (V,)
    vj_radius: np.ndarray  # (V,) radius of the virtual joint's inflatable link, 0 = not an inflatable beam
    link_channel: np.ndarray  # (L,) int pressure channel, −1 = pressure independent
    table_n: np.ndarray  # (L,) int entries used in the padded tables
    table_p: np.ndarray  # (L, P)
    table_k: np.ndarray  # (L, P)
    table_c: np.ndarray  # (L, P)
    drive_kind: np.ndarray  # (A,) int
    drive_stiffness: np.ndarray  # (A,) N·m/rad of the position loop
    drive_tau: np.ndarray  # (A,) s, position-loop time constant
    drive_backlash_half: np.ndarray  # (A,) rad
    drive_quantum: np.ndarray  # (A,) rad per microstep (steppers), 0 otherwise
    drive_max_torque: np.ndarray  # (A,) N·m the drive can deliver
    drive_max_speed: np.ndarray  # (A,) rad/s: the speed of an "unlimited" profile
    reg_alpha: float  # 1 − exp(−dt/τ_regulator)
    reg_max: float
    leak_factor: float  # exp(−dt/τ_leak)
    creep_a: np.ndarray  # (E,) creep fractions aᵢ of the links' elastic bending (models.effects; E = 0: none)
    creep_alpha: np.ndarray  # (E,) 1 − exp(−dt/τᵢ)
    hose_k: np.ndarray  # (A,) N·m/rad the tubes and cables across each actuated joint pull with (0: none)
    hose_slack: np.ndarray  # (A,) rad where they hang slack


@dataclass
class KernelState:
    """Mutable state of a batch of B robots (leading axis B everywhere)."""

    t: float
    ref_pos: np.ndarray  # (B, A) profile generator
    ref_vel: np.ndarray
    loop_pos: np.ndarray  # (B, A) position-loop output before backlash
    loop_vel: np.ndarray
    loop_acc: np.ndarray
    out_pos: np.ndarray  # (B, A) joint output angle (what the encoder sees)
    out_vel: np.ndarray
    torque: np.ndarray  # (B, A) torque the drive supplies
    delta: np.ndarray  # (B, V)
    delta_dot: np.ndarray
    hyst_z: np.ndarray
    creep: np.ndarray  # (B, V, E) creep elements' states xᵢ (rad)
    vj_torque: np.ndarray  # (B, V) static (gravity + payload) moment on each virtual joint, last step
    reg_buf: np.ndarray  # (B, C, D) regulator set-point delay line
    buf_idx: int
    reg_out: np.ndarray  # (B, C)
    p_link: np.ndarray  # (B, C)


@dataclass
class KernelCommands:
    """What the devices were last told (B leading)."""

    goal: np.ndarray  # (B, A) rad
    profile_vel: np.ndarray  # (B, A) rad/s, 0 = unlimited (Dynamixel semantics)
    profile_acc: np.ndarray  # (B, A) rad/s², 0 = unlimited
    pressure_set: np.ndarray  # (B, C) Pa
    valve_open: np.ndarray  # (B, C) bool
    payload_kg: np.ndarray  # (B,)


@dataclass
class Trace:
    """True state at every step of one ``advance`` call: time first after the batch axis."""

    t: np.ndarray  # (n,) seconds at the end of each step
    q: np.ndarray  # (B, n, A) joint output angles
    qd: np.ndarray  # (B, n, A)
    torque: np.ndarray  # (B, n, A) drive torque (what the current sensor sees, in N·m)
    delta: np.ndarray  # (B, n, V)
    pressure: np.ndarray  # (B, n, C) link pressures
    tip_pos: np.ndarray  # (B, n, 3) base frame (orientation: models.kinematics of q and δ, when needed)
    load: np.ndarray  # (B, n, V) static moment (gravity, payload) on each virtual joint: what drives its loop


def allocate_trace(batch: int, n: int, a: int, v: int, c: int) -> Trace:
    """Empty trace arrays for ``n`` steps."""
    return Trace(
        t=np.empty(n),
        q=np.empty((batch, n, a)),
        qd=np.empty((batch, n, a)),
        torque=np.empty((batch, n, a)),
        delta=np.empty((batch, n, v)),
        pressure=np.empty((batch, n, c)),
        tip_pos=np.empty((batch, n, 3)),
        load=np.empty((batch, n, v)),
    )


def advance(params: KernelParams, state: KernelState, cmd: KernelCommands, n: int) -> Trace:
    """Step every robot ``n`` times (mutates ``state``) and return the true trace."""
    b, a = state.out_pos.shape
    trace = allocate_trace(b, n, a, state.delta.shape[1], state.p_link.shape[1])
    threads = numba.get_num_threads()
    if b >= threads:
        _advance_all(params, state, cmd, n, trace)
    else:  # a thread without a robot would only wait at the parallel loop's end: on a busy machine one
        numba.set_num_threads(max(b, 1))  # robot's step(1) took 16 ms on 2 threads, 25 µs on one
        try:
            _advance_all(params, state, cmd, n, trace)
        finally:
            numba.set_num_threads(threads)
    trace.t[:] = state.t + params.dt * np.arange(1, n + 1)
    state.t = float(trace.t[-1]) if n else state.t
    return trace


def _advance_all(params: KernelParams, state: KernelState, cmd: KernelCommands, n: int, trace: Trace) -> None:
    p = params
    state.buf_idx = _advance(
        n, p.dt, p.gravity, p.row_a, p.row_alpha_cs, p.row_d, p.row_offset, p.row_virtual, p.row_var,
        p.row_channel, p.row_strain, p.tool_offset, p.mass_frame, p.mass_pos, p.mass_kg, p.mass_inertia,
        p.vj_link, p.vj_delta_h,
        p.vj_tau_y, p.vj_radius, p.link_channel, p.table_n, p.table_p, p.table_k, p.table_c, p.drive_kind,
        p.drive_stiffness, p.drive_tau, p.drive_backlash_half, p.drive_quantum, p.drive_max_torque,
        p.drive_max_speed, p.reg_alpha, p.reg_max,
        p.leak_factor, p.creep_a, p.creep_alpha, p.hose_k, p.hose_slack,
        state.ref_pos, state.ref_vel, state.loop_pos, state.loop_vel, state.loop_acc, state.out_pos,
        state.out_vel, state.torque, state.delta, state.delta_dot, state.hyst_z, state.creep, state.vj_torque,
        state.reg_buf, state.buf_idx, state.reg_out, state.p_link,
        cmd.goal, cmd.profile_vel, cmd.profile_acc, cmd.pressure_set, cmd.valve_open, cmd.payload_kg,
        trace.q, trace.qd, trace.torque, trace.delta, trace.pressure, trace.tip_pos, trace.load,
    )  # fmt: skip


def link_end_states(params: KernelParams, q, delta, tip, steps: range, frame: int, rotations, forces) -> None:
    """What an IMU at the chain's frame ``frame`` (0: the base, i + 1: after D-H row i) senses at each step
    ``s`` of ``steps``, from a ring of the twin's recent states (capacity C; step s at slot s % C): ``q``
    (C, a), ``δ`` (C, v), the tip's position ``tip`` (C, 3). Writes at slot s % C the frame's rotation to
    ``rotations`` (C, 3, 3) and the tip's specific force in that frame, Rᵀ (ẍ − g) with ẍ the tip's second
    difference over steps s − 2 … s, to ``forces`` (C, 3): the kernel's own kinematics, in one call (a link
    board's IMU reads it a thousand times a second; numpy spent ~100 µs a sample)."""
    p = params
    _link_end_states(q, delta, tip, steps.start, steps.stop, frame, p.dt, p.gravity, p.row_a,
                     p.row_alpha_cs, p.row_d, p.row_offset, p.row_virtual, p.row_var, p.tool_offset,
                     rotations, forces)  # fmt: skip


@numba.njit(cache=True, error_model="numpy")
def _link_end_states(q, delta, tip, first, stop, frame, dt, gravity, row_a, row_alpha_cs, row_d, row_offset,
                     row_virtual, row_var, tool, rotations, forces):  # fmt: skip
    cap = q.shape[0]
    frames = np.empty((row_a.shape[0] + 2, 4, 4))
    sensed = np.empty(3)  # a − g in the base frame
    for s in range(first, stop):
        i, i1, i2 = s % cap, (s - 1) % cap, (s - 2) % cap
        _frames(q[i], delta[i], row_a, row_alpha_cs, row_d, row_offset, row_virtual, row_var, tool, frames)
        for k in range(3):
            sensed[k] = (tip[i, k] - 2.0 * tip[i1, k] + tip[i2, k]) / (dt * dt) - gravity[k]
            for j in range(3):
                rotations[i, k, j] = frames[frame, k, j]
        for j in range(3):  # Rᵀ (a − g)
            forces[i, j] = 0.0
            for k in range(3):
                forces[i, j] += frames[frame, k, j] * sensed[k]


@numba.njit(cache=True, error_model="numpy")
def _profile_step(ref, vel, goal, vmax, amax, dt):
    """Dynamixel-like trapezoidal profile: brake in time to stop at the goal; 0 means unlimited."""
    e = goal - ref
    speed = abs(e) / dt
    if amax > 0.0:
        speed = min(speed, math.sqrt(2.0 * amax * abs(e)))
    if vmax > 0.0:
        speed = min(speed, vmax)
    v_des = math.copysign(speed, e)
    if amax > 0.0:
        dv = min(max(v_des - vel, -amax * dt), amax * dt)
        vel = vel + dv
    else:
        vel = v_des
    return ref + vel * dt, vel


@numba.njit(cache=True, error_model="numpy")
def _row_lengths(row_a0, row_channel, row_strain, p, out):
    """The rows' lengths a at the link pressures ``p``: a₀ (1 + strain · p) where a channel lengthens them."""
    for i in range(row_a0.shape[0]):
        ch = row_channel[i]
        out[i] = row_a0[i] * (1.0 + row_strain[i] * p[ch]) if ch >= 0 else row_a0[i]


@numba.njit(cache=True, error_model="numpy")
def _frames(q, delta, row_a, row_alpha_cs, row_d, row_offset, row_virtual, row_var, tool, out):
    """Cumulative D-H transforms: out[0] = base, out[i+1] = after row i, out[R+1] = tool point."""
    r = row_a.shape[0]
    for i in range(4):
        for j in range(4):
            out[0, i, j] = 1.0 if i == j else 0.0
    for i in range(r):
        th = row_offset[i] + (delta[row_var[i]] if row_virtual[i] else q[row_var[i]])
        ct, st = math.cos(th), math.sin(th)
        ca, sa = row_alpha_cs[i, 0], row_alpha_cs[i, 1]
        # T = Rz(θ) Tz(d) Tx(a) Rx(α)
        t00, t01, t02, t03 = ct, -st * ca, st * sa, row_a[i] * ct
        t10, t11, t12, t13 = st, ct * ca, -ct * sa, row_a[i] * st
        t21, t22, t23 = sa, ca, row_d[i]
        for k in range(3):
            m0, m1, m2, m3 = out[i, k, 0], out[i, k, 1], out[i, k, 2], out[i, k, 3]
            out[i + 1, k, 0] = m0 * t00 + m1 * t10
            out[i + 1, k, 1] = m0 * t01 + m1 * t11 + m2 * t21
            out[i + 1, k, 2] = m0 * t02 + m1 * t12 + m2 * t22
            out[i + 1, k, 3] = m0 * t03 + m1 * t13 + m2 * t23 + m3
        out[i + 1, 3, 0], out[i + 1, 3, 1], out[i + 1, 3, 2], out[i + 1, 3, 3] = 0.0, 0.0, 0.0, 1.0
    for k in range(4):
        for j in range(3):
            out[r + 1, k, j] = out[r, k, j]
        out[r + 1, k, 3] = (
            out[r, k, 0] * tool[0] + out[r, k, 1] * tool[1] + out[r, k, 2] * tool[2] + out[r, k, 3]
        )


@numba.njit(cache=True, error_model="numpy")
def _mass_positions(frames, mass_frame, mass_pos, out):
    """Base-frame positions of the point masses; the last row is the payload at the tool point."""
    nm = mass_frame.shape[0]
    for m in range(nm):
        f = mass_frame[m] + 1
        lx, ly, lz = mass_pos[m, 0], mass_pos[m, 1], mass_pos[m, 2]
        for k in range(3):
            out[m, k] = frames[f, k, 0] * lx + frames[f, k, 1] * ly + frames[f, k, 2] * lz + frames[f, k, 3]
    tip = frames.shape[0] - 1
    for k in range(3):
        out[nm, k] = frames[tip, k, 3]


@numba.njit(cache=True, error_model="numpy")
def _joint_loads(frames, mass_frame, world_pos, mass_kg, mass_inertia, payload, gravity, row, out):
    """Gravity torque about row ``row``'s axis and the distal inertia about it → out[0], out[1]."""
    zx, zy, zz = frames[row, 0, 2], frames[row, 1, 2], frames[row, 2, 2]
    ox, oy, oz = frames[row, 0, 3], frames[row, 1, 3], frames[row, 2, 3]
    nm = mass_kg.shape[0]
    tau = 0.0
    inertia = 0.0
    for m in range(nm + 1):
        if m < nm:
            if mass_frame[m] < row:
                continue
            mk, ik = mass_kg[m], mass_inertia[m]
        else:  # the payload hangs at the tool point
            mk, ik = payload, 0.0
        rx, ry, rz = world_pos[m, 0] - ox, world_pos[m, 1] - oy, world_pos[m, 2] - oz
        # (r × m g) · z
        tau += mk * ((ry * gravity[2] - rz * gravity[1]) * zx + (rz * gravity[0] - rx * gravity[2]) * zy
                     + (rx * gravity[1] - ry * gravity[0]) * zz)  # fmt: skip
        along = rx * zx + ry * zy + rz * zz
        inertia += mk * (rx * rx + ry * ry + rz * rz - along * along) + ik
    out[0] = tau
    out[1] = inertia


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _advance(
    n, dt, gravity, row_a0, row_alpha_cs, row_d, row_offset, row_virtual, row_var, row_channel, row_strain,
    tool, mass_frame, mass_pos,
    mass_kg, mass_inertia, vj_link, vj_delta_h, vj_tau_y, vj_radius, link_channel, table_n, table_p, table_k,
    table_c,
    drive_kind, drive_stiffness, drive_tau, drive_backlash_half, drive_quantum, drive_max_torque,
    drive_max_speed, reg_alpha, reg_max,
    leak_factor, creep_a, creep_alpha, hose_k, hose_slack,
    ref_pos, ref_vel, loop_pos, loop_vel, loop_acc, out_pos, out_vel, torque, delta, delta_dot, hyst_z,
    creep, vj_torque, reg_buf, buf_idx, reg_out, p_link,
    goal, prof_vel, prof_acc, p_set, valve_open, payload,
    tr_q, tr_qd, tr_torque, tr_delta, tr_p, tr_tip, tr_load,
):  # fmt: skip
    nb, na = out_pos.shape
    nv = delta.shape[1]
    nc = p_link.shape[1]
    nr = row_a0.shape[0]
    depth = reg_buf.shape[2]
    drive_alpha = 1.0 - np.exp(-dt / drive_tau)
    # robots are independent: each runs all n steps (parallel over the batch, bit-identical to serial)
    for b in numba.prange(nb):
        frames = np.empty((nr + 2, 4, 4))
        loads = np.empty(2)
        world_pos = np.empty((mass_kg.shape[0] + 1, 3))
        row_a = np.empty(nr)  # the rows' lengths at this robot's link pressures
        _row_lengths(row_a0, row_channel, row_strain, p_link[b], row_a)
        _frames(
            out_pos[b], delta[b], row_a, row_alpha_cs, row_d, row_offset, row_virtual, row_var, tool, frames
        )
        for s in range(n):
            slot = (buf_idx + s + 1) % depth
            # --- pneumatics: dead time (delay line), first-order regulator, valve hold with slow leak
            for c in range(nc):
                reg_buf[b, c, slot] = p_set[b, c]
                delayed = reg_buf[b, c, (slot + 1) % depth]
                reg_out[b, c] = min(max(reg_out[b, c] + reg_alpha * (delayed - reg_out[b, c]), 0.0), reg_max)
                p_link[b, c] = reg_out[b, c] if valve_open[b, c] else p_link[b, c] * leak_factor
            # --- kinematics of the current (deflected) configuration: the previous step's end frames
            _mass_positions(frames, mass_frame, mass_pos, world_pos)
            # --- joints: loads, then the drives move
            for i in range(nr):
                if row_virtual[i]:
                    continue
                j = row_var[i]
                _joint_loads(frames, mass_frame, world_pos, mass_kg, mass_inertia, payload[b], gravity, i,
                             loads)  # fmt: skip
                # the tubes and cables across the joint add their torque to gravity's
                loads[0] -= hose_k[j] * (out_pos[b, j] - hose_slack[j])
                prev_out = out_pos[b, j]
                prev_ref_vel = ref_vel[b, j]
                # "unlimited" (0) profiles mean what the motor can do: its top speed, and the acceleration
                # its torque leaves after holding gravity
                vmax = prof_vel[b, j] if prof_vel[b, j] > 0.0 else drive_max_speed[j]
                vmax = min(vmax, drive_max_speed[j])
                amax = prof_acc[b, j]
                if drive_max_torque[j] < np.inf and loads[1] > 0.0:
                    reserve = max(drive_max_torque[j] - abs(loads[0]), 0.05 * drive_max_torque[j])
                    amax = min(amax, reserve / loads[1]) if amax > 0.0 else reserve / loads[1]
                ref_pos[b, j], ref_vel[b, j] = _profile_step(
                    ref_pos[b, j], ref_vel[b, j], goal[b, j], vmax, amax, dt
                )
                # the drive holds gravity and accelerates the distal inertia along its profile (the
                # reference acceleration: using the loop's own acceleration would close an algebraic loop)
                demand = -loads[0] + loads[1] * (ref_vel[b, j] - prev_ref_vel) / dt
                torque[b, j] = min(max(demand, -drive_max_torque[j]), drive_max_torque[j])
                if drive_kind[j] == DRIVE_STEPPER:
                    new = round(ref_pos[b, j] / drive_quantum[j]) * drive_quantum[j]
                    loop_acc[b, j] = (ref_vel[b, j] - loop_vel[b, j]) / dt
                    loop_vel[b, j] = ref_vel[b, j]
                    loop_pos[b, j] = new
                    out_pos[b, j] = new
                else:
                    target = ref_pos[b, j] - torque[b, j] / drive_stiffness[j]
                    new = loop_pos[b, j] + drive_alpha[j] * (target - loop_pos[b, j])
                    vel = (new - loop_pos[b, j]) / dt
                    loop_acc[b, j] = (vel - loop_vel[b, j]) / dt
                    loop_vel[b, j] = vel
                    loop_pos[b, j] = new
                    out_pos[b, j] = _play(new, out_pos[b, j], drive_backlash_half[j])
                out_vel[b, j] = (out_pos[b, j] - prev_out) / dt
            # --- links: each virtual joint rings under gravity and the drives' accelerations
            for i in range(nr):
                if not row_virtual[i]:
                    continue
                v = row_var[i]
                _joint_loads(frames, mass_frame, world_pos, mass_kg, mass_inertia, payload[b], gravity, i,
                             loads)  # fmt: skip
                inertia = loads[1]
                coupling = 0.0  # acceleration of the actuated joints before it, about its axis
                for i2 in range(i):
                    if not row_virtual[i2]:
                        dot = (frames[i2, 0, 2] * frames[i, 0, 2] + frames[i2, 1, 2] * frames[i, 1, 2]
                               + frames[i2, 2, 2] * frames[i, 2, 2])  # fmt: skip
                        coupling += dot * loop_acc[b, row_var[i2]]
                link = vj_link[v]
                ch = link_channel[link]
                p = p_link[b, ch] if ch >= 0 else 0.0
                m = table_n[link]
                k = _interp(p, table_p[link, :m], table_k[link, :m])
                c = _interp(p, table_p[link, :m], table_c[link, :m])
                tau = loads[0] - inertia * coupling
                # creep: each element relaxes toward its share of the elastic bending under the static load,
                # and the link bends that much more (a torque k·Σxᵢ moves its rest angle by Σxᵢ)
                shift = 0.0
                for e in range(creep_a.shape[0]):
                    creep[b, v, e] += creep_alpha[e] * (creep_a[e] * loads[0] / k - creep[b, v, e])
                    shift += creep[b, v, e]
                tau += k * shift
                # the hysteresis and the wrinkling follow the static load (gravity and payload moment), not
                # the ringing of the drives' accelerations; an inflatable link's M_w is taken per bending axis
                m_w = _wrinkling_moment(p, vj_radius[v])
                delta[b, v], delta_dot[b, v], hyst_z[b, v] = _link_step(
                    delta[b, v], delta_dot[b, v], hyst_z[b, v], tau, loads[0], vj_torque[b, v], k, c, inertia,
                    vj_delta_h[v], vj_tau_y[v], m_w, dt,
                )  # fmt: skip
                vj_torque[b, v] = loads[0]
                tr_load[b, s, v] = loads[0]
            # --- record the true state (tip pose from this step's kinematics)
            _row_lengths(row_a0, row_channel, row_strain, p_link[b], row_a)
            _frames(out_pos[b], delta[b], row_a, row_alpha_cs, row_d, row_offset, row_virtual, row_var, tool,
                    frames)  # fmt: skip
            for j in range(na):
                tr_q[b, s, j] = out_pos[b, j]
                tr_qd[b, s, j] = out_vel[b, j]
                tr_torque[b, s, j] = torque[b, j]
            for v in range(nv):
                tr_delta[b, s, v] = delta[b, v]
            for c in range(nc):
                tr_p[b, s, c] = p_link[b, c]
            for k in range(3):
                tr_tip[b, s, k] = frames[nr + 1, k, 3]
    return (buf_idx + n) % depth
