"""The moves between a session's settled points as the arm makes them, for the twin fit's hysteresis.

A link's Bouc–Wen state at a settled point depends on every reversal of its load along the move into it. A
straight joint-space line between two points turns the load once at most; the arm does not: its drives
accelerate and brake along their profiles, their position loops lag and catch up, and each link rings after
the stop, every swing turning its gravity moment back and forth (the moment is the deflected arm's). On the
lab arm's campaign (``bench/lab_arm.yaml``, 1 rad/s moves, 16 benches × 60 points) the states a straight line
gives were 0.047 (upper link) and 0.025 (lower) rms off the twin's own, where their mean size is 0.50 and
0.16, and 3–4 % too large (the ring's swings relax each loop toward its middle): the fit took the upper
loop's δ_h and τ_y 13–15 % low. The moves simulated here, on the same arm, leave 0.002–0.003; on the
nominal arm instead of the lab's, 0.010 and 0.006.

So the moves are the twin's (:class:`twin.world.World`, every session one robot of a batch): each point's
goals (``qc_*``, the measured angles where a recording has none), its pressures and payload, commanded as the
campaign commands them (every joint at the speed that brings it to its goal with the others:
``acquisition.plans.experiments.together``, the largest at the move speed), then ``ring_s`` of ringing.
The move speed is read from the points' times: within a session the time between two points grows by
|Δq|/v with their largest joint step (the plan waits that long, then settles and holds for a fixed time).
The Bouc–Wen step is exact for any monotone stretch of load (``models.prbm.bouc_wen_step``), so each link's
load along a move (the kernel's own, ``twin.kernel.Trace.load``) is kept only at its turning points (and
its end): a few per move where the twin steps a thousand times a second.
"""

from __future__ import annotations

import numba
import numpy as np

from models.robot import RobotDescription

TURNS = 16  # turning points of a link's load kept per move (the ring's later swings turn it by less)
RING_S = 0.3  # s after a move's planned end: the ring has died down to what turns a loop by < 1 %
TOLERANCE_NM = 1e-4  # a swing of the load smaller than this is not a turn (τ_y is 0.1–0.3 N·m)


def move_speed(t: np.ndarray, goals: np.ndarray, order: np.ndarray) -> float | None:
    """The joint speed (rad/s) of the largest joint step between consecutive points, from their times (a line
    through the time between two points against their largest step: its slope is 1/v), or None where the
    times do not show one (fewer than 10 moves, no spread of steps, or no time it takes)."""
    dt, step = [], []
    for row in order:
        row = row[row >= 0]
        if len(row) > 1:
            dt.append(np.diff(t[row]))
            step.append(np.abs(np.diff(goals[row], axis=0)).max(axis=1))
    if not dt:
        return None
    dt, step = np.concatenate(dt), np.concatenate(step)
    ok = np.isfinite(dt) & np.isfinite(step)
    dt, step = dt[ok], step[ok]
    if len(dt) < 10 or np.ptp(step) < 1e-3 or np.std(dt) < 1e-6:
        return None
    slope, intercept = np.polyfit(step, dt, 1)
    fitted = slope * step + intercept
    if slope <= 0 or np.std(dt - fitted) > 0.1 * np.std(dt):  # not a wait per radian: no speed to read
        return None
    return float(1.0 / slope)


def simulated_moves(robot: RobotDescription, goals: np.ndarray, pressures: np.ndarray, payload: np.ndarray,
                    order: np.ndarray, speed_rad_s: float, ring_s: float = RING_S,
                    turns: int = TURNS) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Each point's move on ``robot``'s twin, where each link's gravity moment turns: ``(q, delta)`` of shapes
    (n, turns, links, joints) and (n, turns, links, links), the joint angles and the links' bending at the
    ``turns`` samples of the move into each point where that link's load turned, the move's end last (padded
    with it). ``goals`` (n, joints) rad, ``pressures`` (n, channels) Pa, ``payload`` (n,) kg; ``order``
    (sessions × points, −1 past a session's end, ``pipeline.arm_history.session_order``)."""
    from acquisition.plans.experiments import together
    from twin.world import World

    rows = [i for i, r in enumerate(robot.dh_rows()) if not r.joint.startswith("q")]
    n, links, joints = len(goals), len(rows), goals.shape[1]
    held = order.copy()  # a session past its end holds its last point
    for s in range(len(held)):
        for k in range(1, held.shape[1]):
            if held[s, k] < 0:
                held[s, k] = held[s, k - 1]
    first = held[:, 0]
    world = World(robot, batch=len(held), q0=goals[first], pressure_pa=pressures[first],
                  payload_kg=payload[first])  # fmt: skip
    world.settle(2.0)
    out_q = np.empty((n, turns, links, joints))
    out_d = np.empty((n, turns, links, world.state.delta.shape[1]))
    q_prev, d_prev = world.state.out_pos.copy(), world.state.delta.copy()
    load_prev = world.state.vj_torque.copy()  # the kernel's load on each link, settled
    for k in range(held.shape[1]):
        at, real = held[:, k], order[:, k] >= 0
        step = goals[at] - world.commands.goal
        world.command_pressure(pressures[at])
        world.set_payload(payload[at])
        world.command_joints(goals[at], profile_vel=np.stack([together(s, speed_rad_s) for s in step]))
        trace = world.run_for(float(np.abs(step).max()) / speed_rad_s + ring_s)
        # the kernel's own load on each link, each step's from the configuration the step began in (its
        # first with this point's payload hung on where the last move ended)
        q = np.concatenate([q_prev[:, None], trace.q[:, :-1]], axis=1)
        d = np.concatenate([d_prev[:, None], trace.delta[:, :-1]], axis=1)
        # turning points of [the last move's final load, this path]: indices ≥ 1, so into the path at −1
        which = np.empty((len(held), turns, links), np.int64)
        _turning_points(np.concatenate([load_prev[:, None], trace.load], axis=1), TOLERANCE_NM, which)
        which -= 1
        for link in range(links):
            pick = which[:, :, link]
            out_q[at[real], :, link] = np.take_along_axis(q, pick[:, :, None], axis=1)[real]
            out_d[at[real], :, link] = np.take_along_axis(d, pick[:, :, None], axis=1)[real]
        q_prev, d_prev, load_prev = trace.q[:, -1], trace.delta[:, -1], trace.load[:, -1]
    return out_q, out_d


@numba.njit(cache=True)
def _turning_points(load, tolerance, out):
    """out[b, :, link]: the indices into ``load`` (batch, samples, links) where the load turned back by more
    than ``tolerance`` from its extreme (at most out.shape[1] − 1 of them), then the last sample."""
    batch, samples, links = load.shape
    keep = out.shape[1]
    for b in range(batch):
        for link in range(links):
            found, extreme, direction = 0, 0, 0.0
            for s in range(1, samples):
                change = load[b, s, link] - load[b, extreme, link]
                if direction == 0.0:
                    if abs(change) > tolerance:
                        direction = 1.0 if change > 0.0 else -1.0
                        extreme = s
                elif change * direction > 0.0:
                    extreme = s  # further the same way
                elif -change * direction > tolerance:  # turned back: the extreme was a turning point
                    if found < keep - 1:
                        out[b, found, link] = extreme
                        found += 1
                    direction = -direction
                    extreme = s
            for r in range(found, keep):
                out[b, r, link] = samples - 1
