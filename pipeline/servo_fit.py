"""The servos' stiffness and backlash (issue 33) from a dataset's settled points: how far each position-
controlled drive sits from its goal, against the torque it holds.

A Dynamixel's encoder reads its output shaft. At rest its position loop stands τ/k short of the goal (k =
P gain × stiffness per P gain, τ the torque the drive holds), and the gears' play lets the output rest
anywhere within ±b/2 of where the loop stands (b the backlash). So at every settled point, per servo,

    d = qc − q = τ/k + e,    e ∈ [−b/2, b/2] (+ the encoder's half count),

with ``qc`` the goal in force and ``q`` the encoder (both in the dataset: ``qc_<j>``, ``q_<j>``) and τ read
from the drive's current (``i_<s>``: τ = K_t · (i − i_idle · sign i), the description's current model at
rest). Where in the play a point rests depends on each move's last moments (the loop's lag and the
deceleration's torque can turn the output back by more or less than the play): it is not modelled. The fit
is the band every point's ``e`` fits in, symmetric about zero (goal and encoder share the encoder's zero):
1/k is the slope that makes the widest ``|d − τ/k|`` smallest (a one-parameter Chebyshev fit through the
origin, over every servo: one spec holds them all). Least squares would not do: where a point rests in the
play follows the move that brought it there, which correlates with the pose, and so with τ (on a lab arm
it took k 16–40 % soft). The band's edge is b/2 plus the encoder's half count, blurred by the currents'
noise (τ read from them): the widest ``|e|`` alone lands that noise's largest draw beyond it (b 2.4 % high
on a lab arm), so the edge is fitted by likelihood to the points within a fifth of a count of the widest:
a density that ends at the edge, smoothed by a normal spread (both fitted).

Standard errors: a delete-half jackknife over the sessions (a session's points share its bench): the
spread of the fit over ``HALVES`` draws of half the sessions (every half where there are fewer), times
r/d (r sessions kept, d left out; Shao and Wu 1989, whose delete-d jackknife stays consistent for estimates
set by a few extreme points, as a band's edge and slope are, where deleting one session does not: the
points that set the slope lie in a few sessions, and leaving out any other changes nothing. On twelve
3,000-point campaigns of the lab arm (bench/lab_arm.yaml; some with the sensors' noise off) the delete-one
errors put the stiffness 14 errors from its truth once, rms 5.6; these: rms 1.4, the largest 2.7, the
estimate 0.2 % low on average). Identifiable: each
value whose error is at most half its nominal value; nothing without goals (a passive recording) or
currents, and the stiffness not where the torques the drives held span too little to tell it.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pandas as pd
from scipy.optimize import minimize, minimize_scalar
from scipy.special import log_ndtr, ndtr

from acquisition.devices.kinds import device_of, kind_of
from models.estimator import Estimator
from models.robot import RobotDescription, load_robot

STIFFNESS = "servo.stiffness_per_p_gain_nm_per_rad"  # k / P: the description's field
BACKLASH = "servo.backlash_rad"  # b, the play's whole width
EDGE_WINDOW_COUNTS = 0.2  # the band's edge is fitted to the points this near the widest (encoder counts)
HALVES = 100  # draws of half the sessions for the errors (the spread's own error ~7 %)
SQRT_2PI = np.sqrt(2 * np.pi)  # the normal density's denominator, as scipy.stats.norm writes it


class ServoFit(Estimator):
    """The servos' stiffness and backlash from settled points: ``ServoFit(robot).fit(points)``.

    ``robot``: the nominal description (a name, a path or a :class:`RobotDescription`); ``torque_constant``:
    the drives' N·m per A when known better than the description's (the static fit's, which weighs the arm
    with the currents). Learns ``values_`` / ``stderr_`` / ``nominal_`` (``STIFFNESS``: N·m/rad per unit of
    P gain; ``BACKLASH``: rad), ``not_identifiable_`` (parameter → why), ``band_rad_`` (the band's edge: how
    far ``qc − q − τ/k`` reaches either way), ``n_points_`` and ``n_sessions_``.
    """

    def __init__(self, robot: RobotDescription | str = "vsl", torque_constant: float | None = None) -> None:
        self.robot = robot
        self.torque_constant = torque_constant

    def fit(self, points: pd.DataFrame) -> ServoFit:
        robot = load_robot(self.robot) if isinstance(self.robot, str) else self.robot
        servo = robot.servo
        self.nominal_ = (
            {STIFFNESS: servo.stiffness_per_p_gain_nm_per_rad, BACKLASH: servo.backlash_rad}
            if servo is not None
            else {STIFFNESS: float("nan"), BACKLASH: float("nan")}  # a robot of steppers: nothing to fit
        )
        self.values_, self.stderr_, self.not_identifiable_ = {}, {}, {}
        self.band_rad_, self.n_points_, self.n_sessions_ = float("nan"), 0, 0
        droop, torque, sessions, count, why = _droops(robot, points, self.torque_constant)
        if why:
            self.not_identifiable_ = dict.fromkeys(self.nominal_, why)
            return self
        half_count = count / 2
        slope, edge = _band(droop, torque, count)
        labels = np.unique(sessions)
        if len(labels) >= 2:
            each = np.array([_band(droop[keep], torque[keep], count) for keep in _halves(sessions, labels)])
            kept = len(labels) // 2
            se_slope, se_edge = np.sqrt(kept / (len(labels) - kept) * each.var(axis=0))
        else:
            se_slope = se_edge = float("inf")
        p_gain = servo.p_gain
        found = {STIFFNESS: (1 / (slope * p_gain), se_slope / (slope**2 * p_gain)),
                 BACKLASH: (2 * max(edge - half_count, 0.0), 2 * se_edge)}  # fmt: skip
        held = np.ptp(torque[np.isfinite(torque)])
        for name, (value, se) in found.items():
            if name == STIFFNESS and held / servo.stiffness_nm_per_rad < 2 * half_count:  # at the nominal k
                why = f"the torques held span {held:.3f} N·m: the droop moves by less than an encoder count"
                self.not_identifiable_[name] = why
            elif not np.isfinite(se) or se > 0.5 * self.nominal_[name]:
                self.not_identifiable_[name] = f"the points do not constrain it (standard error {se:.3g})"
            else:
                self.values_[name], self.stderr_[name] = float(value), float(se)
        self.band_rad_ = float(edge)
        self.n_points_ = int(np.isfinite(droop).any(axis=1).sum())
        self.n_sessions_ = len(labels)
        return self

    def table(self) -> pd.DataFrame:
        """One row per parameter: ``parameter``, ``value``, ``stderr``, ``nominal`` (NaN value and error where
        not identifiable) and ``why`` it was not."""
        self.check_fitted()
        return pd.DataFrame(
            [{"parameter": n, "value": self.values_.get(n, np.nan), "stderr": self.stderr_.get(n, np.nan),
              "nominal": v, "why": self.not_identifiable_.get(n, "")} for n, v in self.nominal_.items()]
        )  # fmt: skip


def _droops(robot: RobotDescription, points: pd.DataFrame, torque_constant: float | None):
    """(qc − q, τ) per point and servo (n, S), the points' sessions, the step the goals and readings come in
    (rad, the joints' device kind's), and why nothing can be fitted ("" when it can): the rows where a
    servo's goal, encoder and current are all finite."""
    nothing = (None, None, None, None)
    servos = [k for k, j in enumerate(robot.joints) if j.drive == "servo"]
    joints = device_of(robot, "joints")
    count = kind_of(robot, joints).resolution_rad if joints is not None else None
    if robot.servo is None or not servos or count is None:
        return *nothing, f"robot {robot.name!r} has no servos whose positions come in counts"
    goals, encoders = [f"qc_{j}" for j in servos], [f"q_{j}" for j in servos]
    currents = [f"i_{s}" for s in range(len(servos))]
    if not set(goals) <= set(points.columns) or not np.isfinite(points[goals].to_numpy(float)).any():
        return *nothing, "the dataset has no goals the servos were given (qc_*): a passive recording"
    if not set(currents) <= set(points.columns):
        return *nothing, "the dataset has no joint currents (i_*): the torques the servos held"
    droop = points[goals].to_numpy(float) - points[encoders].to_numpy(float)
    amps = points[currents].to_numpy(float)
    k_t = torque_constant or robot.servo.torque_constant_nm_per_a
    torque = k_t * (amps - robot.servo.idle_current_a * np.sign(amps))
    bad = ~(np.isfinite(droop) & np.isfinite(torque))
    droop[bad], torque[bad] = np.nan, np.nan
    keep = ~bad.all(axis=1)
    if keep.sum() < 10:
        return *nothing, f"{keep.sum()} settled points with a servo's goal, encoder and current"
    sessions = points["session"].to_numpy()[keep] if "session" in points else np.zeros(keep.sum())
    return droop[keep], torque[keep], sessions, count, ""


def _halves(sessions: np.ndarray, labels: np.ndarray) -> list[np.ndarray]:
    """The points' masks of ``HALVES`` sets of half the sessions (⌊g/2⌋ of g), drawn without repeats by a
    fixed seed, or every such set where there are at most that many."""
    kept = len(labels) // 2
    if math.comb(len(labels), kept) <= HALVES:
        picks = [list(c) for c in itertools.combinations(labels, kept)]
    else:
        rng, seen, picks = np.random.default_rng(0), set(), []
        while len(picks) < HALVES:
            pick = tuple(sorted(rng.choice(len(labels), kept, replace=False)))
            if pick not in seen:
                seen.add(pick)
                picks.append(labels[list(pick)])
    return [np.isin(sessions, pick) for pick in picks]


def _band(droop: np.ndarray, torque: np.ndarray, count: float) -> tuple[float, float]:
    """(1/k, the band's edge) of every servo's finite points: the slope through the origin that makes the
    widest ``|droop − torque · slope|`` smallest (convex in the slope: a bounded scalar search), then the
    edge of those residuals, both signs pooled (:func:`_edge`)."""
    ok = np.isfinite(droop)
    d, t = droop[ok], torque[ok]

    def widest(slope: float) -> float:
        return float(np.abs(d - t * slope).max())

    top = 10 * np.abs(d).max() / max(np.abs(t).max(), 1e-9)  # a slope no arm's droop asks for
    found = minimize_scalar(widest, bounds=(0.0, top), method="bounded", options={"xatol": 1e-9 * top})
    e = d - t * found.x
    return float(found.x), _edge(np.concatenate([e, -e]), EDGE_WINDOW_COUNTS * count)


def _edge(values: np.ndarray, window: float) -> float:
    """Where the density of ``values`` ends, blurred by normal noise: the maximum-likelihood edge E (and
    spread σ) of the values within ``window`` of the largest, their density there taken as flat up to E,
    smoothed by N(0, σ²): each value's likelihood Φ((E − v)/σ), over its integral from the window's start."""
    low = values.max() - window
    near = values[values >= low]

    def minus_log_likelihood(z: np.ndarray) -> float:
        edge, spread = z[0], np.exp(z[1])
        a = (edge - low) / spread
        # ∫ Φ((E − v)/σ) dv from the window's start (scipy.special's Φ and log Φ, which scipy.stats.norm calls
        # after checking its arguments: a fit asks for this ~40,000 times)
        mass = spread * (a * ndtr(a) + np.exp(-(a**2) / 2.0) / SQRT_2PI)
        return -(log_ndtr((edge - near) / spread).sum() - len(near) * np.log(mass))

    start = np.array([values.max(), np.log(window / 4)])
    found = minimize(minus_log_likelihood, start, method="Nelder-Mead",
                     options={"xatol": 1e-10, "fatol": 1e-10})  # fmt: skip
    return float(found.x[0])
