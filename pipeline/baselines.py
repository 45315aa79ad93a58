"""Baselines the hybrid networks are compared with (seed 000 V): the rigid model, a grey-box pseudo-rigid-body
model with fitted link stiffness, and two scikit-learn regressors on the networks' own inputs.

Every baseline follows one contract: the constructor only stores parameters, ``fit(train_df)`` returns self,
``predict(df)`` gives (n, 3) — the tip x (m) for ``direction="forward"``, the joint angles q (rad) for
``direction="inverse"`` — ``name`` names it in tables and ``to_dict()`` gives its JSON-able parameters.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from acquisition.devices.kinds import device_of
from models import kinematics
from models.estimator import Estimator
from models.hybrid import FORWARD_TARGETS, INVERSE_TARGETS, DirectedColumns
from models.prbm import interp_table
from models.robot import AnthropomorphicKinematics, RobotDescription, load_robot
from models.statics import gravity_moments, servo_droop
from pipeline import metrics
from pipeline.datasets import SPLIT_COLUMNS

MEASURED_Q = ("q_0", "q_1", "q_2")  # the encoders' joint angles (fk_* is their rigid FK)
DIRECTIONS = ("forward", "inverse")
K_MIN_NM_PER_RAD = 0.5  # a fitted k(p) is never let go below this (it would fold the link)


def _cols(df: pd.DataFrame, names: tuple[str, ...]) -> np.ndarray:
    return df.loc[:, list(names)].to_numpy(float)


class Baseline(Estimator, DirectedColumns):
    """Common base (the estimator contract, ``models.estimator``): the direction check in ``fit``, the
    fitted check in ``predict``; subclasses fill ``_fit`` (learning attributes ending in ``_``) and
    ``_predict``. Every fitted baseline knows ``n_train_``, the rows it was fitted on, and ``train_splits_``,
    the split columns whose train part holds all of them (None for rows without split columns)."""

    name = "baseline"

    def __init__(self, direction: str = "forward") -> None:
        self.direction = direction

    @property
    def prior(self) -> tuple[str, ...]:
        """The model-based columns the learned part corrects (fk for forward, ik for inverse)."""
        return self.inputs[:3]

    def fit(self, train_df: pd.DataFrame) -> Baseline:
        if self.direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {self.direction!r}")
        self._check_parameters()
        self._fit(train_df)
        self.n_train_ = len(train_df)  # learned by every baseline, the rigid model included
        # the splits whose train part holds every row it learned: the only splits it may be scored on
        labelled = [s for s in SPLIT_COLUMNS if s in train_df]
        self.train_splits_ = (
            tuple(s for s in labelled if (train_df[s] == "train").all()) if labelled else None
        )
        return self

    def predict(self, df: pd.DataFrame) -> np.ndarray:
        self.check_fitted()
        return self._predict(df)

    def _check_parameters(self) -> None:
        """``ValueError`` for a parameter out of its range (checked by ``fit``, as scikit-learn does)."""

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "direction": self.direction}

    def _fit(self, df: pd.DataFrame) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _predict(self, df: pd.DataFrame) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError


class RigidModel(Baseline):
    """x̂ = rigid FK of the measured q (forward), q̂ = rigid IK of the measured x (inverse); nothing to fit."""

    name = "rigid"

    def _fit(self, df: pd.DataFrame) -> None:
        pass

    def _predict(self, df: pd.DataFrame) -> np.ndarray:
        return _cols(df, self.prior)


class PrbmGreyBox(Baseline):
    """The robot description's statics: each link bends by δ = M(q, δ, m)/k(p) under the arm's point masses
    and the payload m; the tip is the chain's FK at (q, δ). Inputs: forward the measured q (``q_*``, whose
    rigid FK is ``fk_*``; the servos' droop is already in it), inverse ``ik_*``; both the link pressures
    ``p_*`` and the servo currents ``i_*``.

    The payload is not told: it is estimated from the currents (τ = K_t (i − i_idle sgn i) per servo against
    the description's gravity moments of the arm and of 1 kg at the tool, least squares over J2/J3), then
    calibrated by a linear regression on the training payloads. With ``fit_stiffness`` each link's
    k(p) = a + b·p (p in bar) is fitted by least squares on the training tip errors, starting from the
    description's table; without it the description's table is used as is.
    Inverse: the q that lands the predicted tip on the target (fixed point on the rigid IK of the tip).
    """

    def __init__(self, robot: RobotDescription | str | None = None, fit_stiffness: bool = True,
                 direction: str = "forward", iterations: int = 3) -> None:  # fmt: skip
        super().__init__(direction)
        self.robot, self.fit_stiffness, self.iterations = robot, fit_stiffness, iterations

    @property
    def name(self) -> str:
        return "prbm" if self.fit_stiffness else "prbm_description"

    # ---------------------------------------------------------------------------------------- physics
    def _setup(self, df: pd.DataFrame) -> None:
        robot = self.robot if self.robot is not None else str(df["robot"].iloc[0])
        robot = load_robot(robot) if isinstance(robot, str) else robot
        if not isinstance(robot.kinematics, AnthropomorphicKinematics) or robot.servo is None:
            raise ValueError(f"robot {robot.name!r}: the grey box needs the servo-driven VSL-type arm")
        kin = robot.kinematics
        self.robot_ = robot
        self.lengths_ = kin.arm()
        rows = [r.joint for r in robot.dh_rows()]
        self.virtual_rows_ = [i for i, r in enumerate(rows) if not r.startswith("q")]
        servo_names = list(robot.devices[device_of(robot, "joints")].ids)
        self.servo_rows_ = [rows.index(q) for q in servo_names]
        links = [robot.link_of(v) for v in robot.virtual_joints]
        self.channels_ = [link.pressure_channel or 0 for link in links]
        self.tables_ = [robot.link_table(link.name) for link in links]

    def _stiffness(self, p_pa: np.ndarray, theta: np.ndarray | None) -> np.ndarray:
        """(n, V) link stiffness: the description's table (theta None) or a + b·p_bar per link."""
        p = p_pa[:, self.channels_]
        if theta is None:
            return np.stack(
                [
                    interp_table(p[:, v], t.pressure_pa, t.stiffness_nm_per_rad)
                    for v, t in enumerate(self.tables_)
                ],
                axis=1,
            )
        a, b = theta[0::2], theta[1::2]
        return np.maximum(a + b * p / 1e5, K_MIN_NM_PER_RAD)

    def _payload_raw(self, q: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Payload (kg) that explains the servo currents under the description's gravity moments."""
        servo = self.robot_.servo
        g0 = gravity_moments(self.robot_, q, None, 0.0)[:, self.servo_rows_]
        g1 = gravity_moments(self.robot_, q, None, 1.0)[:, self.servo_rows_] - g0
        torque = servo.torque_constant_nm_per_a * (current - servo.idle_current_a * np.sign(current))
        # the drive holds τ = −G(q, m) = −(G0 + m G1): least squares in m over the servos
        return -np.sum(g1 * (torque + g0), axis=1) / np.maximum(np.sum(g1 * g1, axis=1), 1e-12)

    def _payload(self, q: np.ndarray, current: np.ndarray) -> np.ndarray:
        c0, c1 = self.payload_calibration_
        return np.maximum(c0 + c1 * self._payload_raw(q, current), 0.0)

    def _tip(self, q: np.ndarray, p_pa: np.ndarray, m: np.ndarray, theta: np.ndarray | None) -> np.ndarray:
        k = self._stiffness(p_pa, theta)
        delta = np.zeros_like(k)
        for _ in range(self.iterations):
            delta = gravity_moments(self.robot_, q, delta, m)[:, self.virtual_rows_] / k
        return self.robot_.chain().position(q, delta)

    def _theta(self) -> np.ndarray | None:
        return self.stiffness_ if self.fit_stiffness else None

    # ------------------------------------------------------------------------------------ fit/predict
    def _fit(self, df: pd.DataFrame) -> None:
        self._setup(df)
        q, p, i = _cols(df, MEASURED_Q), _cols(df, ("p_0", "p_1")), _cols(df, ("i_0", "i_1"))
        raw = self._payload_raw(q, i)
        design = np.column_stack([np.ones(len(raw)), raw])
        self.payload_calibration_ = np.linalg.lstsq(design, df["payload_kg"].to_numpy(float), rcond=None)[0]
        if not self.fit_stiffness:
            return
        m = self._payload(q, i)
        x = _cols(df, FORWARD_TARGETS)
        start = []
        lo, hi = self.robot_.pneumatics.min_operating_pa, self.robot_.pneumatics.max_operating_pa
        for t in self.tables_:  # the description's table, linearised over the operating range
            k_lo, k_hi = interp_table([lo, hi], t.pressure_pa, t.stiffness_nm_per_rad)
            b = (k_hi - k_lo) / ((hi - lo) / 1e5)
            start += [k_lo - b * lo / 1e5, b]
        x0 = np.asarray(start)
        scale = np.maximum(np.abs(x0), 10.0)
        res = least_squares(
            lambda z: ((self._tip(q, p, m, z * scale) - x) * 1e3).ravel(),
            x0 / scale,
            method="trf",
            x_scale=1.0,
        )
        self.stiffness_ = res.x * scale
        self.fit_cost_mm2_ = float(2 * res.cost / len(x))

    def _predict(self, df: pd.DataFrame) -> np.ndarray:
        p, i = _cols(df, ("p_0", "p_1")), _cols(df, ("i_0", "i_1"))
        prior = _cols(df, self.prior)
        theta = self._theta()
        if self.direction == "forward":
            q = _cols(df, MEASURED_Q)  # the measured q that fk_* is the rigid FK of
            return self._tip(q, p, self._payload(q, i), theta)
        ok = np.isfinite(prior).all(axis=1)  # ik is NaN where the measured tip is out of reach
        out = np.full_like(prior, np.nan)
        goal, p, i = prior[ok], p[ok], i[ok]
        q = goal.copy()
        for _ in range(6):
            q = q + (goal - kinematics.vsl_ik(self._tip(q, p, self._payload(q, i), theta), self.lengths_, 1))
        out[ok] = q - servo_droop(
            self.robot_, q, self._payload(q, i)
        )  # the command the servos droop from to reach q
        return out

    def to_dict(self) -> dict[str, Any]:
        self.check_fitted()
        out = super().to_dict() | {"robot": self.robot_.name, "fit_stiffness": self.fit_stiffness}
        out["payload_calibration"] = [float(v) for v in self.payload_calibration_]
        if self.fit_stiffness:
            names = [link.name for link in (self.robot_.link_of(v) for v in self.robot_.virtual_joints)]
            out["stiffness"] = {
                name: {"a_nm_per_rad": float(a), "b_nm_per_rad_per_bar": float(b)}
                for name, a, b in zip(names, self.stiffness_[0::2], self.stiffness_[1::2], strict=True)
            }
        return out


class SklearnBaseline(Baseline):
    """A scikit-learn regressor on the networks' 7 inputs, predicting the residual of the rigid model
    (x − fk forward, q − ik inverse). ``"gbr"``: HistGradientBoostingRegressor per output; ``"knn"``:
    distance-weighted k-nearest neighbours on standardised inputs. Rows with a NaN input predict NaN."""

    KINDS = ("gbr", "knn")

    def __init__(self, kind: str = "gbr", direction: str = "forward", random_state: int = 0,
                 n_neighbors: int = 8, max_iter: int = 300) -> None:  # fmt: skip
        super().__init__(direction)
        self.kind, self.random_state = kind, random_state
        self.n_neighbors, self.max_iter = n_neighbors, max_iter

    @property
    def name(self) -> str:
        return self.kind

    def _check_parameters(self) -> None:
        if self.kind not in self.KINDS:
            raise ValueError(f"kind must be one of {self.KINDS}, got {self.kind!r}")

    def _estimator(self):
        from sklearn.ensemble import HistGradientBoostingRegressor
        from sklearn.multioutput import MultiOutputRegressor
        from sklearn.neighbors import KNeighborsRegressor
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        if self.kind == "gbr":
            hgb = HistGradientBoostingRegressor(max_iter=self.max_iter, random_state=self.random_state)
            return MultiOutputRegressor(hgb)
        return make_pipeline(StandardScaler(), KNeighborsRegressor(self.n_neighbors, weights="distance"))

    def _features(self, df: pd.DataFrame) -> np.ndarray:
        """What the regressor reads per row: the networks' 7 inputs (a subclass may add more after them)."""
        return _cols(df, self.inputs)

    def _fit(self, df: pd.DataFrame) -> None:
        x, y = self._features(df), _cols(df, self.targets) - _cols(df, self.prior)
        ok = np.isfinite(x).all(axis=1) & np.isfinite(y).all(axis=1)
        self.estimator_ = self._estimator().fit(x[ok], y[ok])

    def _predict(self, df: pd.DataFrame) -> np.ndarray:
        x = self._features(df)
        ok = np.isfinite(x).all(axis=1)
        out = np.full((len(x), 3), np.nan)
        if ok.any():
            out[ok] = x[ok, :3] + self.estimator_.predict(x[ok])
        return out

    def to_dict(self) -> dict[str, Any]:
        return super().to_dict() | {
            "kind": self.kind,
            "random_state": self.random_state,
            "n_neighbors": self.n_neighbors,
            "max_iter": self.max_iter,
        }


BASELINES = {
    "rigid": RigidModel,
    "prbm_description": functools.partial(PrbmGreyBox, fit_stiffness=False),
    "prbm": PrbmGreyBox,
    "gbr": functools.partial(SklearnBaseline, "gbr"),
    "knn": functools.partial(SklearnBaseline, "knn"),
}


def part_of(data: pd.DataFrame, split: str = "split_random", part: str = "train") -> pd.DataFrame:
    """The rows of one part ("train"/"val"/"test") of a split column."""
    return data[data[split] == part]


def scored_part(model: Baseline, data: pd.DataFrame, split: str, part: str) -> pd.DataFrame:
    """The rows of ``split``'s ``part`` to score ``model`` on; ValueError if the model was fitted on rows
    outside that split's train part. The two splits deal the same rows differently: ~70 % of split_group's
    test rows are in split_random's train part, and a model scored on rows it learned looks better than it
    is — k-NN with distance weights returns a learned row's target exactly, which once gave it 0.074 mm on
    split_group against 0.24 mm on split_random."""
    fitted_on = model.train_splits_
    if fitted_on is not None and split not in fitted_on:
        raise ValueError(
            f"{model.name} was fitted on rows outside {split}'s train part: its {part} part would score "
            f"rows the model learned (fit it on part_of(data, {split!r}, 'train'))"
        )
    return part_of(data, split, part)


def evaluate_forward(model: Baseline, data: pd.DataFrame, split: str = "split_random",
                     part: str = "test") -> dict[str, Any]:  # fmt: skip
    """Tip errors (mm) of a fitted forward model on one part: summary and per pressure × payload cell (long
    records: pressure_bin, payload_g, mean_mm, count). The model must have been fitted on ``split``'s train
    part (:func:`scored_part`)."""
    rows = scored_part(model, data, split, part)
    return metrics.tip_report(metrics.tip_errors(model.predict(rows), _cols(rows, FORWARD_TARGETS)), rows)


def evaluate_inverse(model: Baseline, data: pd.DataFrame, lengths: kinematics.ArmLengths,
                     split: str = "split_random", part: str = "test") -> dict[str, Any]:  # fmt: skip
    """Joint errors of a fitted inverse model seen at the tip: |FK(q̂) − FK(q)| (mm, rigid FK), same report
    and the same check of the split it was fitted on."""
    rows = scored_part(model, data, split, part)
    q_hat, q = model.predict(rows), _cols(rows, INVERSE_TARGETS)
    return metrics.tip_report(
        metrics.tip_errors(kinematics.vsl_fk(q_hat, lengths), kinematics.vsl_fk(q, lengths)), rows
    )
