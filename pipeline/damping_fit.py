"""The VSL links' damping from their swings after each move (issue 33's dynamic part).

Settled points hold no motion to damp; the moves into them do. After each move of a campaign the links ring at
a few hertz for a few tenths of a second, and the tracker (40 Hz) sees it at the tip: about a millimetre where
its noise is 0.25 mm. A dataset keeps those windows (``moves``: each point's timeline rows from its goal's
command to its settled window, ``pipeline.segment.move_windows``). Here each move is made again on the twin
of the arm whose statics were fitted (``pipeline.twin_fit``): from the point before at rest, the new
pressures, payload and goals commanded together at the move speed, as the campaign commands them (one robot
of a batch per move, ``twin.world.World``), and the tip's swing about where it settles is compared with the
tracked one's about the point's settled mean, from the move's planned end for ``ring_s``. Comparing swings
about the settled ends leaves out what the statics got wrong; the move itself (the drives' profiles,
hundreds of millimetres) is not compared.

Fitted: each link's damping table scaled as a whole (``<link>.damping_scale``: its shape across pressures is
the description's; a fit per pressure is not built), beside each link's stiffness table scaled as a whole (the
swings' frequency is the stiffness's over the inertia: what the statics left wrong in it would otherwise bend
the damping; reported as a check, ``stiffness_``, not written) and the lag of the tracked tip behind the
goal's time stamp (``lag_s_``: the tracker's latency and the bus's). Standard errors from the Jacobian,
clustered by session. A link whose scale's error exceeds half its value is named not identifiable and left
nominal, as is every link where the dataset has no moves or too few.

On the lab arm's 3,000-point campaign (``bench/lab_arm.yaml``: the upper link's damping the papers', the
lower's ×1.5625; seed 3, 300 of its moves) after the statics' fit: 1.0000 ± 0.0077 and 1.558 ± 0.039, the
swings left at 0.26 mm per axis (the tracker's noise: 0.25 mm), in 17 s on 2 cores; from its 17,568 points,
1.0077 ± 0.0060 and 1.532 ± 0.055. The errors carry the statics' (``within_errors``: the arm with one fitted
mass, loop, length or servo value at a time moved by its error): the swings' decay is the damping over the
inertia, and at 17,568 points the upper link's damping came out 0.8 % high where its mass had, 0.9 %, which
the swings' own error (0.0032) put at 2.4 errors. The stiffness scales said ×0.993 ± 0.004 and ×1.060 ±
0.018 of the statics' tables at 3,000 points (which are ×0.991 and ×1.01–1.11 of the truth's).
Made on the papers' nominal arm instead of the fitted one (its stiffness 20–25 % off, no stiffness scale
fitted), the damping came out ×1.40 and ×2.4 with 0.52 mm left: so the statics are fitted first.

Tried, not built: a stiffness factor per table node (0.5, 1, 1.5, 2 bar) instead of one a link, to fuse
with the statics' table where they measure the lower link to 6–11 % at 3,000 points. On that campaign the
upper link's nodes came out 31.95, 64.03, 96.12, 128.83 N·m/rad (truth 32, 64, 96, 128; ± 0.2–0.35 %),
better than the statics' 0.2–1.3 %; the lower link's 45.5, 103.0, 154.1, 226.6 (truth 50, 100, 150,
200; ± 2.8, 3.2, 6.3, 10.9 %), its 0.5 bar node 9 % low at 3.2 errors. Fused by their errors with the
statics' (−1.4, −7.3, −6.9, −10.2 %) that node moves the wrong way, and the lower link stays outside 3 %:
what the 3,000 points hold of it does not reach 3 % either way. Each fit also took 11 twin batches a
Jacobian instead of 5 (323 s beside a CI run; 17 s for this fit on a quiet machine).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from models.estimator import Estimator
from models.robot import RobotDescription
from pipeline.errors import PipelineError

TIP = ("x_0", "x_1", "x_2")
RING_S = 0.6  # s of each move's swing compared, from its planned end (the ring is down to noise by then)
SETTLE_S = 0.3  # s each move's start is held on the twin before it is commanded (its links put at rest)
MIN_MOVES = 20  # moves with their swings recorded below which the damping is not fitted
MAX_MOVES = 300  # moves made again (every k-th, in the points' order): 17 s, the damping to 0.2 % and 2.4 %
LOOSE = 0.5  # a scale whose standard error exceeds this is not identifiable
HELD_S = 3.0  # s after a move's planned end its point's settled window is taken to be at most
GROUPS = 4  # batches of like durations the moves are made in (each runs as long as its longest)
STEP = 0.1  # the scales are solved for in tenths: the solver's first steps are one (in percent, a damping
# 56 % off took it 9 iterations, its trust region doubling from 1 %)


class DampingFitError(PipelineError, ValueError):
    """Moves the fit cannot use (no rows, no points before them); the message says which."""


def scale_name(link: str) -> str:
    return f"{link}.damping_scale"


def damped(robot: RobotDescription, scales: dict[str, float], stiffer: dict[str, float] | None = None
           ) -> RobotDescription:  # fmt: skip
    """``robot`` with each named link's damping table multiplied by its scale (link name → factor), and its
    stiffness table by ``stiffer``'s."""
    links = []
    stiffer = stiffer or {}
    for link in robot.links:
        if (link.name in scales or link.name in stiffer) and link.virtual_joints:
            table = robot.link_table(link.name)
            c, k = scales.get(link.name, 1.0), stiffer.get(link.name, 1.0)
            scaled = {"damping_nms_per_rad": [v * c for v in table.damping_nms_per_rad],
                      "stiffness_nm_per_rad": [v * k for v in table.stiffness_nm_per_rad]}  # fmt: skip
            table = table.model_copy(update=scaled)
            link = link.model_copy(update={"table": table})
        links.append(link)
    return robot.model_copy(update={"links": links})


class VslDampingFit(Estimator):
    """Each VSL link's damping scale from the moves into a dataset's settled points:
    ``VslDampingFit(arm, speed).fit(moves, points)``.

    ``robot``: the arm the moves are made on (its statics fitted: ``pipeline.twin_fit``).
    ``move_speed_rad_s``: the campaign's joint speed (``pipeline.move_paths.move_speed`` reads it from the
    points' times).
    ``ring_s``: seconds of each swing compared. ``max_moves``: at most this many moves are simulated.
    ``stiffness``: fit each link's stiffness scale beside its damping (else the statics' tables are taken as
    they are). ``within_errors``: the arm with one of its fitted static values at a time moved by its
    standard error; how far each moves the solution is added to its errors.

    Learns ``values_`` / ``stderr_`` / ``nominal_`` (``<link>.damping_scale`` → its value, error, 1.0),
    ``not_identifiable_`` (parameter → why), ``lag_s_`` (and ``lag_stderr_s_``), ``residual_rms_mm_`` (of
    the swings, per axis), ``stiffness_`` (link → the factor on its stiffness table the swings' frequency
    says, and its error), ``n_moves_``, ``n_sessions_`` and ``seconds_`` (how long it took).
    """

    def __init__(self, robot: RobotDescription, move_speed_rad_s: float = 1.0, ring_s: float = RING_S,
                 max_moves: int = MAX_MOVES, stiffness: bool = True,
                 within_errors: tuple[RobotDescription, ...] = ()) -> None:  # fmt: skip
        self.stiffness = stiffness
        self.within_errors = within_errors
        self.robot = robot
        self.move_speed_rad_s = move_speed_rad_s
        self.ring_s = ring_s
        self.max_moves = max_moves

    def fit(self, moves: pd.DataFrame, points: pd.DataFrame) -> VslDampingFit:
        began = time.perf_counter()
        robot = self.robot
        links = [link for link in robot.links if link.virtual_joints]
        names = [scale_name(link.name) for link in links]
        self.nominal_ = dict.fromkeys(names, 1.0)
        self.values_, self.stderr_, self.not_identifiable_ = {}, {}, {}
        self.lag_s_ = self.lag_stderr_s_ = self.residual_rms_mm_ = float("nan")
        self.n_moves_ = self.n_sessions_ = 0
        self.stiffness_ = {}
        self.seconds_ = 0.0
        if not (self.move_speed_rad_s > 0 and self.ring_s > 0 and self.max_moves >= 1):
            raise DampingFitError(f"move_speed_rad_s {self.move_speed_rad_s}, ring_s {self.ring_s} and "
                                  f"max_moves {self.max_moves} must be positive")  # fmt: skip
        made = _moves(robot, moves, points, self.move_speed_rad_s, self.ring_s, self.max_moves)
        if made is None or made["n"] < MIN_MOVES:
            n = 0 if made is None else made["n"]
            why = (f"{n} moves with their swings recorded (the fit needs {MIN_MOVES}): the dataset keeps "
                   "the moves into its points where its sessions recorded the servo goals")  # fmt: skip
            self.not_identifiable_ = dict.fromkeys(names, why)
            return self
        self.n_moves_, self.n_sessions_ = made["n"], len(np.unique(made["session"]))
        measured = made["swing"]
        which, t_move = made["which"], made["t_move"]

        n_links = len(links)
        traces: dict[bytes, tuple] = {}  # the twin's moves at the last scales asked for (the lag needs none)

        def swings(z: np.ndarray, base: RobotDescription = robot) -> tuple[np.ndarray, np.ndarray]:
            """The twin's swings at the rows' times (m) and their rate there (m/s), at the scales ``z`` of
            ``base``'s tables."""
            scales = z[:-1]
            key = scales.tobytes() + str(id(base)).encode()
            if key not in traces:
                factor = [1.0 + STEP * s for s in scales]
                arm = damped(base, {link.name: c for link, c in zip(links, factor, strict=False)},
                             {link.name: k for link, k in zip(links, factor[n_links:], strict=False)}
                             if self.stiffness else None)  # fmt: skip
                traces.clear()
                traces[key] = _simulate(arm, made, self.ring_s)
            t, tip, settled = traces[key]
            at = t_move - z[-1] * 1e-3  # the tracked tip lags the goal's stamp (ms)
            k = np.clip(np.searchsorted(t, at), 1, len(t) - 1)
            f = np.clip((at - t[k - 1]) / (t[k] - t[k - 1]), 0.0, 1.0)[:, None]
            before, after = tip[which, k - 1], tip[which, k]
            rate = (after - before) / (t[k] - t[k - 1])[:, None]
            return before * (1 - f) + after * f - settled[which], rate

        def residual(z: np.ndarray, base: RobotDescription = robot) -> np.ndarray:
            return (measured - swings(z, base)[0]).ravel() * 1e3  # mm

        def jacobian(z: np.ndarray) -> np.ndarray:
            """Forward differences in the scales (a twin's run each); the lag's column from the swings' rate
            (the same run, read later)."""
            swing, rate = swings(z)
            r0 = (measured - swing).ravel() * 1e3
            lag = rate.ravel() * 1e-3 * 1e3  # d(measured − swing(t − lag))/d lag, mm per ms
            columns = []
            for j in range(len(z) - 1):
                h = 1e-3 * max(1.0, abs(z[j]))
                step = z.copy()
                step[j] += h
                columns.append((residual(step) - r0) / h)
            return np.stack([*columns, lag], axis=1)

        start = np.zeros(len(links) * (2 if self.stiffness else 1) + 1)  # each scale in STEPs, the lag in ms
        solution = least_squares(residual, start, jac=jacobian, x_scale=1.0, ftol=1e-5, max_nfev=40)
        r = solution.fun
        cov = clustered_covariance(solution.jac, r, np.repeat(made["session"][which], 3))
        # what the statics' errors add: the solution's shift where one of their values lies an error away
        # (its inertia, read in the swings' decay beside the damping: the upper link's damping came 0.8 % high
        # where its mass was 0.9 % so, 2.4 of the swings' errors)
        towards = np.linalg.pinv(solution.jac)
        for arm in self.within_errors:
            shift = towards @ (residual(solution.x, arm) - r)
            cov = cov + np.outer(shift, shift)
        se = np.sqrt(np.diag(cov))
        for j, (name, link) in enumerate(zip(names, links, strict=True)):
            value, error = 1.0 + STEP * solution.x[j], STEP * se[j]
            if not np.isfinite(error) or error > LOOSE * abs(value) or value <= 0:
                self.not_identifiable_[name] = (
                    f"its swings do not constrain it ({value:.3g} ± {error:.2g} of {link.name}'s table over "
                    f"{self.n_moves_} moves)"
                )
            else:
                self.values_[name], self.stderr_[name] = float(value), float(error)
        self.lag_s_, self.lag_stderr_s_ = float(solution.x[-1] * 1e-3), float(se[-1] * 1e-3)
        if self.stiffness:  # what the swings' frequency says of the statics' stiffness (not written)
            self.stiffness_ = {link.name: (1.0 + STEP * solution.x[n_links + j], STEP * se[n_links + j])
                               for j, link in enumerate(links)}  # fmt: skip
        self.residual_rms_mm_ = float(np.sqrt(np.mean(r**2)))
        self.seconds_ = time.perf_counter() - began
        return self

    def table(self) -> pd.DataFrame:
        """One row per link's damping scale: ``parameter``, ``value``, ``stderr``, ``nominal`` (NaN value and
        error where not identifiable) and ``why`` it was not."""
        self.check_fitted()
        return pd.DataFrame(
            [{"parameter": n, "value": self.values_.get(n, np.nan), "stderr": self.stderr_.get(n, np.nan),
              "nominal": self.nominal_[n], "why": self.not_identifiable_.get(n, "")} for n in self.nominal_]
        )  # fmt: skip


def _moves(robot: RobotDescription, moves: pd.DataFrame, points: pd.DataFrame, speed: float, ring_s: float,
           max_moves: int) -> dict | None:  # fmt: skip
    """The moves to make again: each from the point before it in its session (its goals, pressures and
    payload), to its own; the tracked swings about the point's settled tip, from the move's planned end for
    ``ring_s``. None where the moves or the points lack what this needs."""
    joints = [f"qc_{k}" for k in range(len(robot.joints))]
    channels = [f"p_{c}" for c in range(robot.pneumatics.channels)]
    need = {"session", "point", "t", "payload_kg", *TIP, *joints, *channels}
    if moves is None or not len(moves) or not {"session", "point", "t", "t_command", *TIP} <= set(moves):
        return None
    if not need <= set(points.columns):
        return None
    p = points[points["point"] >= 0].sort_values(["session", "t"], kind="stable").reset_index(drop=True)
    before = p.groupby("session", sort=False).shift(1)
    ok = before["t"].notna().to_numpy().copy()
    ok &= np.isfinite(p[[*joints, *channels, *TIP]].to_numpy(float)).all(axis=1)
    ok &= np.isfinite(before[[*joints, *channels, "payload_kg"]].to_numpy(float)).all(axis=1)
    recorded = pd.MultiIndex.from_frame(moves[["session", "point"]].drop_duplicates())
    ok &= pd.MultiIndex.from_frame(p[["session", "point"]]).isin(recorded)
    chosen = np.flatnonzero(ok)
    chosen = chosen[:: max(1, -(-len(chosen) // max_moves))]
    if not len(chosen):
        return None
    new, old = p.iloc[chosen], before.iloc[chosen]
    q0, q1 = old[joints].to_numpy(float), new[joints].to_numpy(float)
    duration = np.abs(q1 - q0).max(axis=1) / speed
    index = pd.Series(np.arange(len(chosen)), index=pd.MultiIndex.from_frame(new[["session", "point"]]))
    rows = moves[pd.MultiIndex.from_frame(moves[["session", "point"]]).isin(index.index)]
    which = index.reindex(pd.MultiIndex.from_frame(rows[["session", "point"]])).to_numpy()
    t_move = (rows["t"] - rows["t_command"]).to_numpy(float)
    commanded = rows.groupby(which)["t_command"].first().reindex(np.arange(len(chosen))).to_numpy(float)
    # the settled window's middle (its mean is the tip there), since the command; at most 3 s after the move
    held = np.clip(np.nan_to_num(new["t"].to_numpy(float) - commanded, nan=np.inf), duration + ring_s,
                   duration + HELD_S)  # fmt: skip
    x = rows[list(TIP)].to_numpy(float)
    use = (t_move >= duration[which]) & (t_move < duration[which] + ring_s) & np.isfinite(x).all(axis=1)
    which, t_move, x = which[use], t_move[use], x[use]
    return {
        "n": len(chosen), "q0": q0, "q1": q1, "duration": duration, "held": held, "speed": speed,
        "p0": old[channels].to_numpy(float), "p1": new[channels].to_numpy(float),
        "m0": old["payload_kg"].to_numpy(float), "m1": new["payload_kg"].to_numpy(float),
        "session": new["session"].to_numpy(), "which": which, "t_move": t_move,
        "swing": x - new[list(TIP)].to_numpy(float)[which],
    }  # fmt: skip


def _simulate(arm: RobotDescription, made: dict, ring_s: float, groups: int = GROUPS
              ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Every move made again on ``arm``'s twin: (t (steps,) s since the goals were commanded, tip (moves,
    steps, 3) m in the base frame, each move's settled tip (moves, 3): at the middle of its point's settled
    window, ``made["held"]``). The moves run in ``groups`` batches of like durations, each only as long as
    its longest needs (a move's tip is held at its last sample after its batch's run)."""
    from acquisition.plans.experiments import together
    from twin.world import World

    held = made["held"]
    steps = None
    tip = None
    settled = np.empty((len(held), 3))
    for batch in np.array_split(np.argsort(held, kind="stable"), min(groups, len(held))):
        world = World(arm, batch=len(batch), q0=made["q0"][batch], pressure_pa=made["p0"][batch],
                      payload_kg=made["m0"][batch], devices=False)  # fmt: skip
        world.rest_links()
        world.settle(SETTLE_S)
        world.command_pressure(made["p1"][batch])
        world.set_payload(made["m1"][batch])
        step = made["q1"][batch] - made["q0"][batch]
        speeds = np.stack([together(s, made["speed"]) for s in step])
        world.command_joints(made["q1"][batch], profile_vel=speeds)
        begun = world.t
        if steps is None:  # the longest run: every batch's time axis is its beginning
            n = int(np.ceil(float(held.max()) / world.dt)) + 2
            steps = (np.arange(n) + 1) * world.dt
            tip = np.empty((len(held), n, 3))
        trace = world.run_for(float(held[batch].max()) + 2 * world.dt)
        m = min(len(trace.t), len(steps))
        tip[batch, :m] = trace.tip_pos[:, :m]
        tip[batch, m:] = trace.tip_pos[:, m - 1 : m]
        at = np.clip(np.searchsorted(trace.t - begun, held[batch]), 0, len(trace.t) - 1)
        settled[batch] = trace.tip_pos[np.arange(len(batch)), at]
    return steps, tip, settled


def clustered_covariance(jac: np.ndarray, r: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """The least-squares estimate's covariance with residuals correlated within each group (the sandwich
    (JᵀJ)⁻¹ (Σ_g J_gᵀ r_g r_gᵀ J_g) (JᵀJ)⁻¹ with the usual small-sample factor); the plain s² (JᵀJ)⁻¹ when
    there are under 10 groups, too few to estimate the middle from."""
    n, k = jac.shape
    bread = np.linalg.pinv(jac.T @ jac)
    labels, index = np.unique(groups, return_inverse=True)
    if len(labels) < 10:
        return bread * float(r @ r) / max(n - k, 1)
    scores = np.zeros((len(labels), k))
    np.add.at(scores, index, jac * r[:, None])
    g = len(labels)
    meat = scores.T @ scores * (g / (g - 1)) * ((n - 1) / max(n - k, 1))
    return bread @ meat @ bread
