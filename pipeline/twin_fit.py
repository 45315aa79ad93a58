"""The twin of the lab's own robot (issue 33): a robot description's identifiable parameters fitted to a lab's
dataset, each with its standard error, written back as a description that ``extends:`` the nominal one.

This is the VSL arm's fit (:class:`VslStaticFit`, its statics and, from the moves, its damping). From a
dataset's settled points
(``x_*``: the tracked tip in the base frame, ``q_*``: the encoders, ``p_*``: the link pressures,
``payload_kg``: the plan's payload, ``t`` and ``session``: their order) it fits

- each link's stiffness table k(p) at the table's pressures the data reaches (linear in between, as the
  twin interpolates it),
- each link's hysteresis (the loop's half width δ_h and how soon it turns, τ_y), and
- the link lengths ``l2_m`` and ``l3_m`` and the joint offsets of ``q2`` and ``q3`` (their encoders' zero
  errors, ``kinematics.joint_offsets_rad``),
- how much the links lengthen with pressure (``effects.elongation``, an effect the papers' statics leave
  out; none, 0, where the points show none),
- the masses each link carries beyond its hinge, scaled together (``<link>.mass_scale``: one by one they are
  not told apart by their moments) and, where the dataset has the servos' currents (``i_*``), their torque
  constant: the currents weigh the arm (each current residual weighted by its noise against the tip's),
- and from those currents too, the tubes and cables across each servo's joint (``effects.hoses``: a torque
  K (q − slack) the servo holds beside gravity's; none, K = 0, where the currents show none),
- the links' creep (``effects.creep``): each element's fraction aᵢ at its time constant (the description's,
  or 2 s and 60 s, unmodelled-effects.md's placeholder, where it has none; the times are not fitted), each
  point's creep the lag of the elastic bending τ/k through the session's points in time (``t``); an element
  within 3 errors of zero is none,

beside a small rigid correction of the tracker registration (the dataset's registration was fitted with the
nominal arm: a lab arm's other lengths move it a little). The tip model is the description's statics, the
twin's: each link bends by δ = τ/k(p) − δ_h·z, τ = M(q, δ, m) its gravity moment, z its Bouc–Wen state. A
settled point's z depends on how the arm got there: it is followed along each session's moves in time order.
Without the hysteresis the stiffness came out 10–55 % high on the nominal twin's own campaign; with a single
step per move, 2–15 % low; along straight joint-space lines (``substeps`` torques a move), within 0.3 %
(upper link) and 1.4–5 % (lower link, less loaded) on its 17,568 points, but the loops 13–15 % small on a lab
arm's: each link rings after a move and the swings relax its loop. So the fit runs twice: along straight
lines, then through the moves the twin of the arm just fitted makes between the same points
(``pipeline.move_paths``: the drives' profiles and loops, the links' ringing; the move speed read from the
points' times), which on that lab arm brought the loops within 6 % (a third pass changed nothing).

What the data cannot separate is named, with the reason, and left at its nominal value: ``l1_m`` (it moves
the tip along the base's vertical axis exactly as the registration's offset does), ``q1``'s offset (it turns
the arm about that axis as the registration's rotation does), a table pressure no point
was recorded near, and anything whose standard error exceeds half its nominal value (a joint offset, whose
nominal value is 0: half a degree). A link whose loop the points do not show (δ_h zero within two errors)
has none: δ_h = 0, and its τ_y named (left in place, the nominal loop took the stiffness of an arm without
hysteresis 6–21 % low). Standard errors come
from the Jacobian at the solution, clustered by session (a session's points share its bench and its drift:
treating them as independent would make the errors too small). A value fixed because the points could not
constrain it (or fixed at zero: a loop, a lengthening, a creep or a hose they do not show) leaves the others'
errors as they were while it was free: fixing it tells nothing more about them.

The servos' stiffness and backlash come from their goals against their encoders (``pipeline.servo_fit``), with
the torque constant fitted here. Where the residuals show the tracker's field distortion (a smooth bias
repeating at each place: ``pipeline.tracker_field``; left out, it took the stiffness ×0.45 to ×1.5), it is
fitted beside the arm as a Gaussian process profiled out of every residual, and the lengths and offsets it
cannot be told from are named not identifiable. Settled points cannot tell damping: where the dataset keeps
the moves into its points (``moves``), each link's damping comes from its swings after them, made again on
the twin of the arm just fitted (``pipeline.damping_fit``); where it keeps none, it is named not
identifiable. The POPUP arm's link is fitted to its link tests by ``pipeline.popup_fit``.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from models.effects import TrackerDistortion
from models.estimator import Estimator
from models.prbm import interp_table
from models.robot import AnthropomorphicKinematics, RobotDescription, extended, load_robot
from models.statics import gravity_moments, servo_current_a
from pipeline.arm_history import (
    creep_states,
    hysteresis_states,
    mass_bodies,
    path_parts,
    path_torques,
    scaled_masses,
    session_order,
)
from pipeline.damping_fit import VslDampingFit, clustered_covariance, scale_name
from pipeline.errors import PipelineError
from pipeline.move_paths import move_speed, simulated_moves
from pipeline.servo_fit import BACKLASH, STIFFNESS, ServoFit
from pipeline.tracker_field import FieldBasis, described_bias_m, field_prior, fitted_distortion, placement

MEASURED_Q = ("q_0", "q_1", "q_2")
TIP = ("x_0", "x_1", "x_2")
NEEDED = (*MEASURED_Q, *TIP, "payload_kg")
L1_CONFOUNDED = (
    "moves the tip along the base's vertical axis exactly as the tracker registration's offset does"
)
TORQUE_CONSTANT = (
    "servo.torque_constant_nm_per_a"  # the drives' current → torque (their currents weigh the arm)
)
CURRENT_WEIGHT_MM_PER_MA = (
    0.04  # a first guess (0.12 mm of tip noise per 3 mA of current noise), then measured
)
STRAIN = "elongation.strain_per_bar"  # the links' lengthening with pressure (effects.elongation)
Q1_CONFOUNDED = (
    "turns the arm about the base's vertical axis exactly as the tracker registration's rotation does"
)
UNDAMPED = (  # why each link's damping table is left nominal where the dataset has no moves
    "settled points hold no motion to damp, and the dataset keeps no moves into them (built before vslab "
    "kept them, or its sessions recorded no servo goals): its links' swings after each move are what tell it"
)
FIRST_PASS_POINTS = 2000  # about as many points of a share of the sessions place the moves (see _first_pass)
# beside the tables, the fitted values that shape the links' swings (their errors are the damping's too)
SWINGING = ("l2_m", "l3_m", ".mass_scale", ".delta_h_rad", ".tau_y_nm", "stiffness_per_p_gain_nm_per_rad",
            "backlash_rad")  # fmt: skip
OFFSETS = ("q1", "q2", "q3")  # the anthropomorphic arm's joints, in order (its kinematics' joint_offsets_rad)


class TwinFitError(PipelineError, ValueError):
    """Data a fit cannot use (no rows, missing columns, another kind of robot); the message says which."""


class VslStaticFit(Estimator):
    """The VSL arm's static parameters from settled points: ``VslStaticFit(robot).fit(points)``.

    ``robot``: the nominal description (a name, a path or a :class:`RobotDescription`). ``min_weight``: a
    table pressure is identifiable when the points' interpolation weights on it sum to at least this (about
    that many points recorded at it). ``iterations``: of the statics' fixed point δ = M(q, δ, m)/k.
    ``substeps``: torques a straight move between two points is followed by. ``moves``: ``"simulated"`` (the
    arm's own moves on its twin, where the points' times give their speed or ``move_speed_rad_s`` says it) or
    ``"straight"`` (joint-space lines). ``fit_parameters`` False: only the
    registration's correction is fitted, the description kept as it is (its own prediction: ``vslab twin
    check``).

    Learns ``robot_`` (the nominal description), ``values_`` / ``stderr_`` / ``nominal_`` (parameter name →
    value, standard error, nominal value; lengths in m, stiffness in N·m/rad), ``not_identifiable_``
    (parameter → why), ``correction_`` (the registration's rotation vector in rad and translation in m),
    ``residual_rms_mm_`` (of the fitted tip, per axis), ``errors_mm_`` (each point's distance from the fitted
    tip, NaN where a point could not be used), ``n_points_``, ``n_sessions_``, ``move_speed_rad_s_`` (the
    speed the moves were simulated at; None where they were taken as straight lines) and ``damping_`` (the
    links' damping fit, :class:`pipeline.damping_fit.VslDampingFit`, where ``fit`` was given the moves; its
    scales are among ``values_``).
    """

    def __init__(self, robot: RobotDescription | str = "vsl", min_weight: float = 20.0,
                 iterations: int = 3, substeps: int = 8, fit_parameters: bool = True,
                 moves: str = "simulated", move_speed_rad_s: float | None = None) -> None:  # fmt: skip
        self.robot = robot
        self.min_weight = min_weight
        self.iterations = iterations
        self.substeps = substeps
        self.fit_parameters = fit_parameters
        self.moves = moves
        self.move_speed_rad_s = move_speed_rad_s

    # ------------------------------------------------------------------------------------------ fit
    def fit(self, points: pd.DataFrame, moves: pd.DataFrame | None = None) -> VslStaticFit:
        """Fit to a dataset's settled points (``data``) and, where given, the moves into them (its ``moves``
        table): each link's damping from the swings after each move (``pipeline.damping_fit``)."""
        self._fit_statics(points)
        self.damping_ = None  # the damping fit, where it ran
        if self.fit_parameters:
            names = [scale_name(link.name) for link in self.robot_.links if link.virtual_joints]
            damping, why = None, UNDAMPED
            if moves is not None and len(moves) and self.move_speed_rad_s_ is None:  # no speed to remake them
                why = "the points' times give no move speed: the moves into them cannot be made again"
            elif moves is not None and len(moves):
                moved = [{n: self.values_[n] + self.stderr_[n]} for n in self.values_ if n.endswith(SWINGING)]
                arm, *within = (self._arm(change) for change in [{}, *moved])
                damping = VslDampingFit(arm, self.move_speed_rad_s_, within_errors=tuple(within))
                damping = damping.fit(moves, points)
            self.nominal_ |= dict.fromkeys(names, 1.0)
            self.not_identifiable_ |= dict.fromkeys(names, why) if damping is None else {}
            if damping is not None:
                self.values_ |= damping.values_
                self.stderr_ |= damping.stderr_
                self.not_identifiable_ |= damping.not_identifiable_
                self.damping_ = damping
        return self

    def _fit_statics(self, points: pd.DataFrame) -> None:
        robot = load_robot(self.robot) if isinstance(self.robot, str) else self.robot
        links = _check(robot, points, same_name=self.fit_parameters)
        channels = [f"p_{link.pressure_channel or 0}" for link in links]
        ok = np.isfinite(points[[*NEEDED, *channels]].to_numpy(float)).all(axis=1)
        rows = points.loc[ok]
        if len(rows) < 10:
            raise TwinFitError(f"{len(rows)} usable settled points (q, p, payload and tracked tip finite): "
                               "a fit needs at least 10")  # fmt: skip
        q, x = rows[list(MEASURED_Q)].to_numpy(float), rows[list(TIP)].to_numpy(float)
        p = rows[channels].to_numpy(float)
        m = rows["payload_kg"].to_numpy(float)
        sessions = rows["session"].to_numpy() if "session" in rows else np.zeros(len(rows))
        amps = _currents(robot, rows)  # (n, servos) A, or None: the drives' currents weigh the arm too

        tables = [robot.link_table(link.name) for link in links]
        nominal: dict[str, float] = {"l2_m": robot.kinematics.l2_m, "l3_m": robot.kinematics.l3_m}
        nominal |= {
            f"{j}.offset_rad": o for j, o in zip(OFFSETS, robot.kinematics.joint_offsets_rad, strict=True)
        }
        elongation = robot.effects.elongation
        nominal[STRAIN] = elongation.strain_per_bar if elongation is not None else 0.0
        free: list[str] = ["l2_m", "l3_m", "q2.offset_rad", "q3.offset_rad", STRAIN]
        hidden: dict[str, str] = {"l1_m": L1_CONFOUNDED, "q1.offset_rad": Q1_CONFOUNDED}
        creep = robot.effects.creep  # its elements' fractions at the description's time constants (or ours)
        times = creep.time_constants_s if creep is not None else CREEP_TIME_CONSTANTS_S
        fractions = creep.fractions if creep is not None else (0.0,) * len(times)
        nominal |= {_creep(time): a for time, a in zip(times, fractions, strict=True)}
        if "t" in rows:
            free += [_creep(time) for time in times]
        else:
            hidden |= {_creep(time): "the dataset has no times (t): no load history" for time in times}
        bodies = mass_bodies(robot, links)  # each link's masses scale together: their sum and balance
        nominal |= {f"{body}.mass_scale": 1.0 for body in bodies}  # (one by one, the masses on a body are
        free += [f"{body}.mass_scale" for body in bodies]  # not told apart by its moments: 2–3× their values)
        nominal[TORQUE_CONSTANT] = robot.servo.torque_constant_nm_per_a
        hoses = robot.effects.hoses.joints if robot.effects.hoses is not None else {}
        held = [j.name for j in robot.joints if j.drive == "servo"]  # the joints whose currents are read
        servo_columns = [[j.name for j in robot.joints].index(name) for name in held]  # their q columns
        middle = dict(zip(held, q[:, servo_columns].mean(axis=0), strict=True))  # each joint's mean angle
        for joint in held:  # the tubes and cables across a joint: a torque K (q − slack) its servo holds
            hose = hoses.get(joint)
            k, slack = (hose.stiffness_nm_per_rad, hose.slack_rad) if hose is not None else (0.0, 0.0)
            nominal |= {_hose(joint, "k"): k, _hose(joint, "slack"): slack,
                        _hose(joint, "t0"): k * (middle[joint] - slack)}  # fmt: skip
        if amps is not None:
            free += [TORQUE_CONSTANT, *(_hose(j, part) for j in held for part in ("k", "t0"))]
        else:
            hidden[TORQUE_CONSTANT] = "the dataset has no joint currents (i_*)"
            hidden |= {_hose(j, part): "the dataset has no joint currents (i_*)" for j in held
                       for part in ("k", "slack")}  # fmt: skip
        for link, table, pv in zip(links, tables, p.T, strict=True):
            if link.hysteresis is not None:  # the loop's half width: how far a point falls short of τ/k
                nominal[f"{link.name}.delta_h_rad"] = link.hysteresis.delta_h_rad
                nominal[f"{link.name}.tau_y_nm"] = link.hysteresis.tau_y_nm  # how soon the loop turns
                free += [f"{link.name}.delta_h_rad", f"{link.name}.tau_y_nm"]
            for j, (pk, k) in enumerate(zip(table.pressure_pa, table.stiffness_nm_per_rad, strict=True)):
                name = _knot(link.name, pk)
                nominal[name] = k
                w = _hat(pv, table.pressure_pa, j)
                if w.sum() >= self.min_weight:
                    free.append(name)
                else:
                    hidden[name] = (f"{w.sum():.1f} points' worth recorded near {pk / 1e5:g} bar "
                                    f"(the fit needs {self.min_weight:g})")  # fmt: skip
        if not self.fit_parameters:
            free, hidden = [], {}
        # each point's hysteresis state follows the arm's torques along each session's moves
        t = rows["t"].to_numpy(float) if "t" in rows else np.arange(len(rows), dtype=float)
        order = session_order(sessions, t)
        moving = self._moving(robot, links, rows, q, order, t)  # (goals, pressures, speed) or None: straight
        begin: dict[str, Any] = {}  # where the solves start (nominal, unless a first pass says better)
        field: list = [None]  # the tracker's field distortion: a FieldBasis where the residuals show one,
        # False where they show none, None until they have been read (once: by the first pass, where one ran)
        tracker = placement(robot)  # (R, t): the tracker's frame, the field's
        at = x @ tracker[0].T + tracker[1]  # where the points are in it
        # a check predicts what the description's tracker reports: its field's bias too (a fit reads the
        # lab's field from the points: a description's drawn field is not the lab's)
        reported = self.fit_parameters or robot.effects.tracker_distortion is None
        moves = None  # straight lines between the points, unless the arm's own moves are simulated
        if moving is not None:  # through the moves of the arm (a check: of the description checked)
            arm = robot
            if self.fit_parameters:
                arm, first = self._first_pass(robot, rows, sessions)
                field[:] = [FieldBasis(at, first.field_) if first.field_ is not None else False]
                if field[0]:  # what the first pass found the field hides (below) is not fitted again
                    hidden |= {n: first.not_identifiable_[n] for n in KINEMATICS if n in free}
                    free = [n for n in free if n not in KINEMATICS]
                begin = {n: v for n, v in first.values_.items() if n in nominal}
                for joint in held:  # a hose's torque at the joint's mean angle, from its K and slack
                    k, slack = first.values_.get(_hose(joint, "k")), first.values_.get(_hose(joint, "slack"))
                    if k is not None and slack is not None:
                        begin[_hose(joint, "t0")] = k * (middle[joint] - slack)
                turn, shift = first.correction_["rotation_rad"], first.correction_["translation_m"]
                begin["registration"] = np.array([*turn, *shift]) * 1e3  # mrad, mm
            moves = simulated_moves(arm, *moving[:2], m, order, moving[2])
        parts = path_parts(robot, links, q, m, order, self.substeps, moves)

        weight = [CURRENT_WEIGHT_MM_PER_MA]  # a current residual's worth in tip millimetres, then measured
        states: dict[tuple, np.ndarray] = {}  # the loops' states of the last few loads and τ_y asked for
        last: dict[str, Any] = {}  # the last pass's solution (scaled): where the next one starts
        arms: dict[tuple, tuple] = {}  # the arm's tip, torques and drive torques at the last values asked for
        cached = threading.Lock()  # over both caches

        covariance: list[pd.DataFrame] = []  # the last pass's, of ``free`` (a hose's slack is a ratio)
        n_tip = 3 * len(q)
        # The idle current flows the way the held torque turns: a step at τ = 0 that a finite-difference
        # Jacobian read as a derivative of ~10⁷ where a point's torque sat at zero (a solution is drawn to
        # such kinks): the standard errors came out hundreds of times too small and the lower link 3–6 %
        # soft. The directions are the measured currents' instead (|i| ≥ the idle current, 60 mA on the
        # VSL's servos, where the noise is ~19 mA: the current says which way its servo holds), fixed for
        # every solve.
        idle = np.sign(amps) if amps is not None else None

        def solve(free: list[str], fixed: dict) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
            """Values, registration rotation and shift, residuals (tip in mm, then the currents' in mA) and
            standard errors of ``free`` (the others nominal, or as ``fixed``)."""
            unit = {"_m": 1e-3, "_rad": 1e-4, "_bar": 1e-4}  # fitted in mm, 0.1 mrad, 0.01 %/bar and % of k
            unit |= {HOSE_K: 1e-3, HOSE_T0: 1e-3, CREEP: 1e-3}  # a hose's mN·m/rad and mN·m, creep's 0.1 %
            scale = np.array([unit.get(n[n.find(".hose") :] if ".hose" in n else CREEP if n.startswith(CREEP)
                                       else n[n.rfind("_") :], 0.01 * nominal[n]) for n in free])  # fmt: skip

            def unpack(z: np.ndarray) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
                values = nominal | fixed
                values.update({n: nominal[n] + s * v for n, s, v in zip(free, scale, z, strict=False)})
                return values, z[len(free) : len(free) + 3] * 1e-3, z[len(free) + 3 :] * 1e-3  # mrad, mm

            def raw(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                """The tip's residuals (n, 3) (mm, before the field takes its share) and the currents' (mA,
                weighted; empty without currents)."""
                values, rotvec, shift = unpack(z)
                tau_y = tuple(values.get(f"{link.name}.tau_y_nm", 1.0) for link in links)
                loads = tuple(values.get(f"{body}.mass_scale", 1.0) for body in parts)
                key = (tau_y, loads)  # most of the Jacobian's columns change neither
                with cached:  # the Jacobian's columns are computed in threads: the caches are shared
                    state = states.get(key)
                if state is None:
                    torques = path_torques(parts, values)  # the fitted masses load the links along the moves
                    state = hysteresis_states(torques, np.asarray(tau_y), order)
                    with cached:
                        if len(states) > 8:
                            states.pop(next(iter(states)))  # the oldest
                        states[key] = state
                arm_key = tuple(
                    v for n, v in values.items() if ".hose" not in n
                )  # the registration's and the hoses' columns of the Jacobian leave the arm as is
                with cached:
                    arm = arms.get(arm_key)
                if arm is None:
                    arm = self._tip(robot, links, tables, values, q, p, m, state, (order, t))
                    if not reported:
                        tip, torque, drive = arm
                        arm = (tip + described_bias_m(robot, tip), torque, drive)
                    with cached:
                        if len(arms) > 2:
                            arms.pop(next(iter(arms)))  # the oldest
                        arms[arm_key] = arm
                tip, _, drive = arm
                out = (Rotation.from_rotvec(rotvec).apply(tip) + shift - x) * 1e3  # mm
                if amps is None:
                    return out, np.zeros(0)
                servo = robot.servo.model_copy(update={"torque_constant_nm_per_a": values[TORQUE_CONSTANT]})
                hose = np.stack([values[_hose(j, "k")] * (q[:, c] - middle[j]) + values[_hose(j, "t0")]
                                 for j, c in zip(held, servo_columns, strict=True)], axis=1)  # fmt: skip
                wrong = (servo_current_a(servo, drive + hose, 0.0, idle) - amps) * 1e3  # mA
                return out, weight[0] * wrong.ravel()

            def assemble(out: np.ndarray, currents: np.ndarray) -> np.ndarray:
                """The residual the solver minimises from ``raw``'s parts (``out`` (n, 3·c): c columns at
                once, or their differences): the tip's, the currents', the field's prior on its weights."""
                penalty = np.zeros((0, out.shape[1]))
                if field[0]:  # the field's weights profiled out: what it leaves, and its prior
                    out, penalty = field[0].project(out)
                c = out.shape[1] // 3
                tip, prior = out.reshape(-1, 3, c), penalty.reshape(-1, 3, c)  # each column's rows as ravel's
                return np.concatenate([tip.reshape(-1, c), currents.reshape(-1, c), prior.reshape(-1, c)])

            evaluated: dict[bytes, tuple] = {}  # raw's parts at the last point the residual was asked for

            def residual(z: np.ndarray) -> np.ndarray:
                parts = raw(z)
                evaluated.clear()
                evaluated[z.tobytes()] = parts
                return assemble(*parts)[:, 0]

            def jacobian(z: np.ndarray) -> np.ndarray:
                """The residual's forward differences (scipy's ``2-point`` steps: without a field, its
                Jacobian bit for bit), the field's share taken of all columns at once: it is linear, and one
                product over the columns reads its features once where one per column read them ~50 times
                (the distorted paper-size fit: 76 s)."""
                out0, cur0 = evaluated.get(z.tobytes()) or raw(z)
                steps = np.finfo(float).eps ** 0.5 * np.where(z >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(z))
                steps = (z + steps) - z

                def column(j: int) -> tuple[np.ndarray, np.ndarray]:
                    out, cur = raw(z + steps[j] * np.eye(len(z))[j])
                    return (out - out0) / steps[j], (cur - cur0) / steps[j]

                # one column a CPU at once: the statics are numpy over every point, which lets go of the GIL
                outs, curs = zip(*columns.map(column, range(len(z))), strict=True)
                return assemble(np.stack(outs, axis=2).reshape(len(out0), -1), np.stack(curs, axis=1))

            seed = {n: (begin[n] - nominal[n]) / size for n, size in zip(free, scale, strict=True)
                    if n in begin}  # fmt: skip
            turned = last.get("registration", begin.get("registration", np.zeros(6)))
            start = np.array([last.get(n, seed.get(n, 0.0)) for n in free] + list(turned))
            with ThreadPoolExecutor(max(1, len(os.sched_getaffinity(0)))) as columns:
                fit = least_squares(residual, start, jac=jacobian, method="trf", x_scale=1.0)
            last.clear()  # the next pass starts where this one ended
            last.update(zip(free, fit.x[: len(free)], strict=True), registration=fit.x[len(free) :])
            groups = np.repeat(sessions, 3)
            if amps is not None:
                groups = np.concatenate([groups, np.repeat(sessions, amps.shape[1])])
            if field[0]:  # each prior row on its own
                priors = [f"\0field{k}" for k in range(3 * field[0].phi.shape[1])]
                groups = np.concatenate([groups.astype(str), priors])
            cov = clustered_covariance(fit.jac, fit.fun, groups)
            cov = cov[: len(free), : len(free)] * np.outer(scale, scale)
            se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            covariance[:] = [pd.DataFrame(cov, index=free, columns=free)]
            return *unpack(fit.x), fit.fun, dict(zip(free, se.tolist(), strict=True))

        # what the points cannot constrain, or a loop no link can hold, is named and the rest fitted again; a
        # loop the points do not show is none (δ_h = 0), and the rest fitted again
        fixed: dict[str, float] = {}
        at_zero: dict[str, float] = {}  # δ_h fitted at 0: its standard error where it was last free
        # Each value's standard error where what was dropped was still free: fixing what the points could not
        # constrain (at its nominal value, or at zero) tells nothing more about the rest, so their errors do
        # not shrink by it. (On the lab arm, a draw whose lower loop's τ_y was too loose to fit fixed it at
        # the papers' 0.18 N·m, where the arm's is 0.3: δ_h then came out 0.00038 ± 0.00007 rad, 7 errors
        # from its 0.00087; with τ_y free its error had been 0.00025.)
        floor: dict[str, float] = {}
        while True:  # ends: each pass that does not end it takes at least one name out of ``free``
            values, rotvec, shift, r, se = solve(free, fixed)
            if amps is not None and weight[0] == CURRENT_WEIGHT_MM_PER_MA:  # each residual by its own noise
                tip_rms, amp_rms = np.std(r[:n_tip]), np.std(r[n_tip : n_tip + amps.size]) / weight[0]
                weight[0] = tip_rms / max(amp_rms, 1e-6)
                continue
            if self.fit_parameters and field == [None]:  # a field the residuals show: fitted beside the rest
                prior = field_prior(at, r[:n_tip].reshape(-1, 3))
                field[:] = [FieldBasis(at, prior) if prior is not None else False]
            if field[0] and (shown := [n for n in KINEMATICS if n in free]):
                prior = field[0].prior  # the arm's lengths and offsets move the tip through it as it does
                why = FIELD_CONFOUNDED.format(rms=prior.rms_mm, length=prior.length_scale_m * 1e3)
                hidden |= dict.fromkeys(shown, why)
                free = [n for n in free if n not in shown]
                continue
            loose = {n for n, e in se.items() if not np.isfinite(e) or e > _loosest(n, nominal[n])}
            dropped = {n: f"the points do not constrain it (standard error {se[n]:.3g})" for n in loose}
            # a loop is none where its δ_h is zero within errors small enough to tell; one too loose to fit
            # is not identifiable, left nominal (on 600 points of the papers' arm, 4–5 a session, the lower
            # loop's δ_h came out 0.0068 ± 0.012 rad: taken as none, it took the upper loop 30 % wide and the
            # upper link 10 % soft at 1.5–2 bar, 3.5 errors)
            for name, why in _absent_loops(links, values, free, se, loose).items():
                fixed[name], at_zero[name] = 0.0, se[name]
                dropped |= {name: "", name.replace("delta_h_rad", "tau_y_nm"): why}
            # a lengthening zero within 2 errors is none; a creep element within 3: on the lab arm, which
            # does not creep, a draw put its 60 s element at 1.05 % (2.65 errors; the errors are too small
            # at 3,000 points: across four draws 15 % of its values fell beyond 2 errors, not 5 %)
            for name in (STRAIN, *(n for n in free if n.startswith(CREEP))):
                errors = 2 if name == STRAIN else 3
                if name in free and values[name] < errors * se[name] and name not in dropped:
                    fixed[name], at_zero[name] = 0.0, se[name]  # the links do not lengthen (creep): none
                    dropped[name] = ""
            for joint in held:  # a hose whose torque the currents do not show (zero within 2 errors): none
                k_name, t0 = _hose(joint, "k"), _hose(joint, "t0")
                if k_name in free and values[k_name] < 2 * se[k_name] and k_name not in dropped:
                    fixed[k_name], fixed[t0], at_zero[k_name] = 0.0, 0.0, se[k_name]
                    dropped |= {k_name: "", t0: ""}
                    hidden[_hose(joint, "slack")] = f"no hose torque shows on {joint}: none, so no slack"
            dropped |= _impossible_loops(links, tables, values, [n for n in free if n not in dropped], se)
            if not dropped:
                break
            floor |= {n: max(se[n], floor.get(n, 0.0)) for n in free if n not in dropped}
            hidden |= {n: why for n, why in dropped.items() if why}
            free = [n for n in free if n not in dropped]
        # the servos' stiffness and backlash: their goals against their encoders (the drives' torque from
        # their currents, with the torque constant fitted here where it was)
        servo = ServoFit(robot, values[TORQUE_CONSTANT] if TORQUE_CONSTANT in free else None)
        servo = servo.fit(rows) if self.fit_parameters else None  # (a check fits the registration only)
        self.robot_ = robot
        self.nominal_ = {n: v for n, v in nominal.items() if not n.endswith(HOSE_T0)}
        self.nominal_ |= servo.nominal_ if servo else {}
        if covariance:  # the errors (and the covariance, its correlations kept) at least their floor
            widen = np.array([max(1.0, floor.get(n, 0.0) / se[n]) if se[n] > 0 else 1.0 for n in free])
            covariance[0] = covariance[0] * np.outer(widen, widen)
            se = {n: se[n] * w for n, w in zip(free, widen, strict=True)}
        values, se = _hose_slacks(middle, free, values, se, covariance[0] if covariance else None)
        shown = [n.replace(HOSE_T0, HOSE_SLACK) for n in free]  # a hose's slack where its t0 was fitted
        fixed = {n: v for n, v in fixed.items() if not n.endswith(HOSE_T0)}
        self.values_ = {n: float(values[n]) for n in shown} | fixed | (servo.values_ if servo else {})
        self.stderr_ = {n: float(se[n]) for n in shown} | at_zero | (servo.stderr_ if servo else {})
        self.not_identifiable_ = hidden | (servo.not_identifiable_ if servo else {})
        self.correction_ = {
            "rotation_rad": [float(v) for v in rotvec],
            "translation_m": [float(v) for v in shift],
        }
        tip_r = r[:n_tip]
        self.residual_rms_mm_ = float(np.sqrt(np.mean(tip_r**2)))
        self.current_rms_ma_ = (
            float(np.sqrt(np.mean((r[n_tip : n_tip + amps.size] / weight[0]) ** 2)))
            if amps is not None
            else None
        )
        self.field_ = field[0].prior if field[0] else None  # the field distortion the residuals showed
        self.distortion_ = None  # and the map of it fitted (the description's ``effects.tracker_distortion``)
        if field[0]:
            tail = r[len(r) - 3 * field[0].phi.shape[1] :]  # the prior's rows: √(σ²/s²)·the weights
            fitted = tail.reshape(-1, 3) / np.sqrt(field[0].ridge)
            self.distortion_ = fitted_distortion(field[0], fitted, tracker[0])
        self.errors_mm_ = np.full(len(points), np.nan)
        self.errors_mm_[ok] = np.linalg.norm(tip_r.reshape(-1, 3), axis=1)
        self.n_points_ = len(rows)
        self.n_sessions_ = len(set(sessions.tolist()))
        self.move_speed_rad_s_ = moving[2] if moving is not None else None

    def _arm(self, moved: dict[str, float]) -> RobotDescription:
        """The fitted arm (``moved``: with these values in place of the fitted ones)."""
        data = self.description("statics", self.robot_.name, "", "", moved)
        data.pop("fitted")
        return extended(self.robot_, data)

    def _first_pass(self, robot: RobotDescription, rows: pd.DataFrame, sessions: np.ndarray) -> tuple:
        """The arm whose moves the fit follows, and its fit (where the solves start): fitted along straight
        lines to every k-th session (about ``FIRST_PASS_POINTS`` points; a third pass through the moves of
        the arm fitted through its moves changed no value by more than 0.1 %)."""
        share = max(1, round(len(rows) / FIRST_PASS_POINTS))
        keep = np.isin(sessions, pd.unique(sessions)[::share])
        first = VslStaticFit(robot, self.min_weight / share, self.iterations, self.substeps, moves="straight")
        data = first.fit(rows.loc[keep]).description("moves", robot.name, "", "")
        data.pop("fitted")
        return extended(robot, data), first

    def _moving(self, robot: RobotDescription, links, rows: pd.DataFrame, q: np.ndarray, order: np.ndarray,
                t: np.ndarray) -> tuple | None:  # fmt: skip
        """What the arm's moves are simulated from (``pipeline.move_paths``): each point's goals (the
        encoders' angles where the recording has none), its pressures by channel and the move speed; None
        where the moves are taken as straight lines (``moves="straight"``, or no speed given or readable
        from the points' times)."""
        if self.moves == "straight":
            return None
        if self.moves != "simulated":
            raise TwinFitError(f"moves: 'simulated' or 'straight', not {self.moves!r}")
        commanded = [f"qc_{k}" for k in range(q.shape[1])]
        goals = q.copy()
        if set(commanded) <= set(rows.columns):
            sent = rows[commanded].to_numpy(float)
            goals = np.where(np.isfinite(sent), sent, q)
        speed = self.move_speed_rad_s or move_speed(t, goals, order)
        if speed is None:
            return None
        pressures = np.zeros((len(rows), robot.pneumatics.channels))
        for link in links:
            channel = link.pressure_channel or 0
            pressures[:, channel] = rows[f"p_{channel}"].to_numpy(float)
        return goals, pressures, float(speed)

    def _tip(
        self, robot: RobotDescription, links, tables, values: dict, q, p, m, z, history=None
    ) -> tuple[np.ndarray, ...]:
        """The statics' tip (base frame) of the arm with ``values``' lengths, offsets, lengthening with
        pressure, masses and stiffness tables, the links' torques (δ = τ/k − δ_h·z + Σ aᵢ xᵢ, z each link's
        hysteresis state, xᵢ its creep elements' states along the session's ``history``, (order, t)) and the
        torques the servos hold."""
        fitted = {"l2_m": values["l2_m"], "l3_m": values["l3_m"],
                  "joint_offsets_rad": tuple(values[f"{j}.offset_rad"] for j in OFFSETS)}  # fmt: skip
        masses = scaled_masses(robot, links, values)
        arm = robot.model_copy(
            update={"kinematics": robot.kinematics.model_copy(update=fitted), "masses": masses}
        )
        a = None
        if values.get(STRAIN):  # the rows' lengths at each point's pressures, by channel
            by_channel = np.zeros((len(q), robot.pneumatics.channels))
            for i, link in enumerate(links):
                by_channel[:, link.pressure_channel or 0] = p[:, i]
            a = arm.row_lengths(by_channel, values[STRAIN])
        k = np.stack(
            [
                interp_table(pv, t.pressure_pa, [values[_knot(link.name, pk)] for pk in t.pressure_pa])
                for link, t, pv in zip(links, tables, p.T, strict=True)
            ],
            axis=1,
        )
        rows = [row.joint for row in arm.dh_rows()]
        virtual = [i for i, joint in enumerate(rows) if not joint.startswith("q")]
        servos = [rows.index(j.name) for j in arm.joints if j.drive == "servo"]
        delta = np.zeros_like(k)
        hyst = np.array([values.get(f"{link.name}.delta_h_rad", 0.0) for link in links])
        creep = [(v, float(n[len(CREEP) : -1])) for n, v in values.items() if n.startswith(CREEP) and v]
        for _ in range(self.iterations):
            moments = gravity_moments(arm, q, delta, m, a)
            torque = moments[:, virtual]
            elastic = torque / np.maximum(k, 1e-3)
            delta = elastic - hyst * z
            for fraction, time in creep if history is not None else ():
                delta = delta + fraction * creep_states(elastic, history[1], history[0], time)
        return arm.chain().position(q, delta, a), torque, -moments[:, servos]  # the drives hold −M

    # ----------------------------------------------------------------------------------- the result
    def table(self) -> pd.DataFrame:
        """One row per parameter: ``parameter``, ``value``, ``stderr``, ``nominal`` (NaN value and error where
        not identifiable) and ``why`` it was not."""
        self.check_fitted()
        rows = [
            {"parameter": n, "value": self.values_.get(n, np.nan), "stderr": self.stderr_.get(n, np.nan),
             "nominal": self.nominal_.get(n, np.nan), "why": self.not_identifiable_.get(n, "")}
            for n in [*self.values_, *self.not_identifiable_]
        ]  # fmt: skip
        return pd.DataFrame(rows)

    def description(self, name: str, extends: str, dataset: str, code_version: str,
                    moved: dict[str, float] | None = None) -> dict[str, Any]:  # fmt: skip
        """The fitted description as YAML data: ``extends`` the nominal one, says the fitted lengths and every
        link's table (the fitted pressures; the others as they were), and carries a ``fitted`` block (the
        dataset, the residual, the code version, each value with its standard error and nominal value, and
        what could not be identified, with why). ``moved``: values in place of the fitted ones (the damping
        fit moves each static value by its error to carry its uncertainty)."""
        self.check_fitted()
        fitted = {**self.values_, **(moved or {})}
        robot, values = self.robot_, {**self.nominal_, **fitted}
        links = []
        for link in robot.links:
            data = link.model_dump(mode="json", exclude_none=True)
            if link.virtual_joints:
                table = robot.link_table(link.name)
                data["table"] = {
                    "pressure_pa": list(table.pressure_pa),
                    "stiffness_nm_per_rad": [
                        round(values[_knot(link.name, pk)], 4) for pk in table.pressure_pa
                    ],
                    "damping_nms_per_rad": [  # scaled as a whole where the swings told it
                        round(c * values.get(scale_name(link.name), 1.0), 5)
                        for c in table.damping_nms_per_rad
                    ],
                }
            if link.hysteresis is not None:
                loop = {
                    field: float(values.get(f"{link.name}.{field}", getattr(link.hysteresis, field)))
                    for field in ("delta_h_rad", "tau_y_nm")
                }
                k_max = max(values[_knot(link.name, pk)] for pk in robot.link_table(link.name).pressure_pa)
                loop["tau_y_nm"] = max(loop["tau_y_nm"], k_max * loop["delta_h_rad"])  # within 2 SE of it
                data["hysteresis"] = loop
            links.append(data)
        return {
            "extends": extends,
            "name": name,
            "description": f"{robot.description}, fitted to {dataset}",
            "kinematics": {
                "l2_m": round(values["l2_m"], 7),
                "l3_m": round(values["l3_m"], 7),
                "joint_offsets_rad": [round(values[f"{j}.offset_rad"], 7) for j in OFFSETS],
            },
            "links": links,
            "masses": [
                mass.model_dump(mode="json", exclude_none=True) | {"mass_kg": round(mass.mass_kg, 6)}
                for mass in scaled_masses(robot, [robot.link_of(v) for v in robot.virtual_joints], values)
            ],
            "servo": {
                "torque_constant_nm_per_a": round(values[TORQUE_CONSTANT], 6),
                "stiffness_per_p_gain_nm_per_rad": round(
                    values.get(STIFFNESS, robot.servo.stiffness_per_p_gain_nm_per_rad), 6
                ),
                "backlash_rad": round(values.get(BACKLASH, robot.servo.backlash_rad), 7),
            },
            **_effects_block(robot, fitted, self.distortion_),
            "fitted": {
                "dataset": dataset,
                "code_version": code_version,
                "points": self.n_points_,
                "sessions": self.n_sessions_,
                "residual_rms_mm": round(self.residual_rms_mm_, 4),
                "tracker_field": (
                    {
                        "rms_mm": round(self.field_.rms_mm, 4),
                        "length_scale_mm": round(self.field_.length_scale_m * 1e3, 1),
                        "noise_mm": round(self.field_.noise_mm, 4),
                    }
                    if self.field_ is not None
                    else None
                ),
                "registration_correction": self.correction_,
                "damping": (
                    {
                        "moves": self.damping_.n_moves_,
                        "swing_residual_rms_mm": round(self.damping_.residual_rms_mm_, 4),
                        "tracker_lag_s": round(self.damping_.lag_s_, 5),
                        "stiffness_from_swings": {  # what their frequency says of the fitted tables (a check)
                            link: {"factor": round(float(f), 4), "stderr": round(float(e), 4)}
                            for link, (f, e) in self.damping_.stiffness_.items()
                        },
                    }
                    if getattr(self, "damping_", None) is not None and self.damping_.n_moves_
                    else None
                ),
                "parameters": {
                    n: {"value": fitted[n], "stderr": self.stderr_[n], "nominal": self.nominal_[n]}
                    for n in fitted
                },
                "not_identifiable": dict(self.not_identifiable_),
            },
        }


def _currents(robot: RobotDescription, rows: pd.DataFrame) -> np.ndarray | None:
    """The servos' currents (n, servos) in A (``i_0`` … in the servos' order), or None where the dataset has
    none or any is not finite."""
    names = [f"i_{k}" for k in range(sum(j.drive == "servo" for j in robot.joints))]
    if not names or not set(names) <= set(rows.columns):
        return None
    amps = rows[names].to_numpy(float)
    return amps if np.isfinite(amps).all() else None


def _effects_block(robot: RobotDescription, values: dict, distortion: TrackerDistortion | None) -> dict:
    """The fitted description's ``effects`` where the fit says other than the nominal description: the links'
    lengthening with pressure, the hoses across the joints, their creep and the tracker's field (``null``:
    none, where the nominal one has it)."""
    out: dict[str, Any] = {}
    creep = {float(n[len(CREEP) : -1]): a for n, a in values.items() if n.startswith(CREEP)}
    if creep:  # the elements the data shows (none: no creep)
        shown = {time: a for time, a in creep.items() if a > 0}
        if shown or robot.effects.creep is not None:
            out["creep"] = (
                {"fractions": [float(a) for a in shown.values()], "time_constants_s": list(shown)}
                if shown
                else None
            )
    strain = values.get(STRAIN)
    nominal = robot.effects.elongation
    if strain is not None and strain != (nominal.strain_per_bar if nominal else 0.0):
        out["elongation"] = {"strain_per_bar": float(strain)} if strain > 0 else None
    fitted = {name.removesuffix(HOSE_K): k for name, k in values.items() if name.endswith(HOSE_K)}
    if fitted:
        known = robot.effects.hoses.joints if robot.effects.hoses is not None else {}
        hoses = {joint: {"stiffness_nm_per_rad": float(k),
                         "slack_rad": float(values.get(_hose(joint, "slack"),
                                                       known[joint].slack_rad if joint in known else 0.0))}
                 for joint, k in fitted.items() if k > 0}  # fmt: skip
        if hoses or robot.effects.hoses is not None:
            out["hoses"] = {"joints": hoses} if hoses else None
    if distortion is not None:  # the lab's tracker field, fitted (none: the points show none)
        out["tracker_distortion"] = distortion.model_dump(mode="json")
    elif robot.effects.tracker_distortion is not None:
        out["tracker_distortion"] = None
    return {"effects": out} if out else {}


def _check(robot: RobotDescription, points: pd.DataFrame, same_name: bool = True) -> list:
    """The links the fit bends (those with virtual joints), or a ``TwinFitError`` saying what is missing.
    ``same_name``: the points must be of the robot of that name (a fit; a check compares other descriptions
    of the arm, a fitted one among them, with its points)."""
    if not isinstance(robot.kinematics, AnthropomorphicKinematics) or robot.servo is None:
        raise TwinFitError(f"robot {robot.name!r} is not a VSL-type arm (anthropomorphic, servo-driven): "
                           "its static fit is not built")  # fmt: skip
    if not len(points):
        raise TwinFitError("the dataset has no settled points")
    known = sorted(set(points["robot"].astype(str))) if "robot" in points else [robot.name]
    if same_name and (others := sorted(set(known) - {robot.name})):
        if robot.name not in known:
            raise TwinFitError(f"the dataset's points are of robot {', '.join(known)}, not {robot.name}")
        raise TwinFitError(f"the dataset mixes robots ({', '.join(known)}): fit one robot's points, not "
                           f"{', '.join(others)} too")  # fmt: skip
    links = [robot.link_of(v) for v in robot.virtual_joints]
    if len({link.name for link in links}) != len(links):
        raise TwinFitError(f"robot {robot.name!r} has a link with several virtual joints: its static fit is "
                           "built for one bend per link")  # fmt: skip
    missing = sorted((set(NEEDED) | {f"p_{lk.pressure_channel or 0}" for lk in links}) - set(points.columns))
    if missing:
        raise TwinFitError(f"the dataset has no column {', '.join(missing)}")
    return links


KINEMATICS = ("l2_m", "l3_m", "q2.offset_rad", "q3.offset_rad")  # what a distorted field hides (below)
FIELD_CONFOUNDED = (
    "the tracker's field is distorted ({rms:.2g} mm per axis, over {length:.0f} mm): the links' lengths and "
    "the joints' offsets move the tip smoothly through the field, as its bias does, and the points cannot "
    "tell them apart (on a lab arm with a 0.7 mm field they came 1-2.5 mm and 0.4° off, 3-5 standard "
    "errors): "
    "calibrate the tracker's field, or fit them from a session with an undistorted one"
)
LOOSEST_OFFSET_RAD = np.radians(0.5)  # a joint offset known no better than this is not identified
LOOSEST_CREEP = 0.05  # nor a creep fraction known no better than 5 % of the elastic bending
CREEP = "creep.fraction@"  # a creep element's fraction, by its time constant: creep.fraction@2s
CREEP_TIME_CONSTANTS_S = (
    2.0,
    60.0,
)  # ASSUMED (unmodelled-effects.md's placeholder): where a description has none
LOOSEST_STRAIN_PER_BAR = 1e-3  # nor a lengthening known no better than 0.25 mm per bar of a 0.25 m link


HOSE_K = ".hose_stiffness_nm_per_rad"  # effects.hoses.joints.<joint>.stiffness_nm_per_rad
HOSE_SLACK = ".hose_slack_rad"  # … .slack_rad
HOSE_T0 = ".hose_torque_mid_nm"  # what the fit solves for beside K: the torque at the joint's mean angle
# (linear, never degenerate where a hose is nominally absent, and apart from K: q − its mean)


def _hose(joint: str, part: str) -> str:
    """The name of a joint's hose stiffness (``part`` "k"), slack ("slack") or torque at its mean angle
    ("t0")."""
    return joint + {"k": HOSE_K, "slack": HOSE_SLACK, "t0": HOSE_T0}[part]


def _hose_slacks(middle: dict, free: list[str], values: dict, se: dict, cov: pd.DataFrame | None):
    """``values`` and ``se`` with each fitted hose's slack = q̄ − t0/K (q̄ its joint's mean angle, ``middle``)
    and its standard error (first order, from the covariance of K and t0)."""
    values, se = dict(values), dict(se)
    for joint, mean in middle.items():
        k, t0 = _hose(joint, "k"), _hose(joint, "t0")
        if k in free and t0 in free and cov is not None:
            slack = mean - values[t0] / values[k]
            gradient = np.array([values[t0] / values[k] ** 2, -1 / values[k]])  # ∂slack/∂K, ∂slack/∂t0
            part = cov.loc[[k, t0], [k, t0]].to_numpy()
            values[_hose(joint, "slack")] = slack
            se[_hose(joint, "slack")] = float(np.sqrt(max(gradient @ part @ gradient, 0.0)))
    return values, se


def _loosest(name: str, nominal: float) -> float:
    """The largest standard error a fitted value may have: half its nominal value; for those nominally zero,
    half a degree (a joint offset) or 0.1 % per bar (the links' lengthening)."""
    if name.endswith(".offset_rad"):
        return LOOSEST_OFFSET_RAD
    if name.startswith(CREEP) and not nominal:
        return LOOSEST_CREEP
    if name.endswith((HOSE_K, HOSE_T0)):
        return np.inf  # a hose's: zero within two errors makes it none (below)
    return LOOSEST_STRAIN_PER_BAR if name == STRAIN and not nominal else 0.5 * abs(nominal)


def _creep(time_constant_s: float) -> str:
    return f"{CREEP}{time_constant_s:g}s"


def _knot(link: str, pressure_pa: float) -> str:
    return f"{link}.k@{pressure_pa / 1e5:g}bar"


def _hat(p: np.ndarray, knots: list[float], j: int) -> np.ndarray:
    """Each point's linear-interpolation weight on knot ``j`` (the weight the fitted value gets there)."""
    basis = np.zeros(len(knots))
    basis[j] = 1.0
    return interp_table(p, knots, basis)


def _absent_loops(links, values: dict, free: list[str], se: dict, loose: set[str]) -> dict[str, str]:
    """Each link's δ_h that is zero within two standard errors (or below zero), with why its τ_y cannot be
    told: the points show no hysteresis loop on that link, so it has none (δ_h = 0) rather than the nominal
    one (kept, a loop the arm does not have would bias its stiffness: 6–21 % on an arm without hysteresis).
    Not a δ_h too ``loose`` to tell: the points do not show whether the link has a loop at all."""
    out = {}
    for link in links:
        delta_h = f"{link.name}.delta_h_rad"
        if (delta_h in free and delta_h not in loose and f"{link.name}.tau_y_nm" in free
                and values[delta_h] < 2 * se[delta_h]):  # fmt: skip
            out[delta_h] = (f"the points show no hysteresis loop on {link.name} (δ_h fitted "
                            f"{values[delta_h]:.3g} ± {se[delta_h]:.2g} rad, taken as 0): no loop for τ_y to "
                            "shape")  # fmt: skip
    return out


def _impossible_loops(links, tables, values: dict, free: list[str], se: dict) -> dict[str, str]:
    """The fitted hysteresis of each link whose loop no link can hold (τ_y below k_max·δ_h: the link would
    deflect against its load) by more than two standard errors of τ_y, with why: the points' history effect
    is something the statics leave out. (Within two errors of the bound the loop is kept: the description
    written takes τ_y at the bound.)"""
    out = {}
    for link, table in zip(links, tables, strict=True):
        names = (f"{link.name}.delta_h_rad", f"{link.name}.tau_y_nm")
        if not set(names) <= set(free):
            continue
        delta_h, tau_y = values[names[0]], values[names[1]]
        bound = max(values[_knot(link.name, pk)] for pk in table.pressure_pa) * delta_h
        if delta_h < 0 or tau_y <= 0 or tau_y < bound - 2 * se[names[1]]:
            why = (f"the fitted loop (δ_h {delta_h:.3g} rad, τ_y {tau_y:.3g} N·m) is none a link can hold "
                   f"(τ_y under k_max·δ_h = {bound:.3g} N·m): the points' history is something the statics "
                   "leave out (creep, hose torques)")  # fmt: skip
            out |= dict.fromkeys(names, why)
    return out
