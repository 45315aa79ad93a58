"""A trained inverse model in the control loop: the runners' compensation hook (Experiment 2, seed 000).

At each new set-point the runner calls ``compensator(q_ik, pressure_pa, current_a, t_s=t)``: the model-based
IK of the desired point, the link pressures and the joint currents measured now, and the set-point's time.
The inverse model maps (q_ik, p, i) to the servo commands that land the tip there: q̃ = L⁻¹(q, p, i). A
history-aware model (``pipeline.history.HistoryModel``) also reads what came before: the compensator keeps
that history itself, one :class:`~pipeline.history.HistoryState` over the calls, the same code that computed
its training rows' history. Every call is timed, so the per-step inference latency of a run can be reported.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

import numpy as np
import pandas as pd

from acquisition.plans.compensation import CompensationError
from acquisition.plans.plan import Plan
from models.hybrid import INVERSE_INPUTS
from models.robot import RobotDescription, load_robot
from pipeline.baselines import Baseline
from pipeline.history import HistoryModel, HistoryState


class InverseModelCompensator:
    """Wrap a model with ``predict((n, 7) [ik_0..2, p_0, p_1, i_0, i_1]) -> (n, 3) q`` as a compensator for
    ``robot``: currents are taken from its servo joints (the dataset's i_0, i_1 are J2 and J3). A baseline
    (``pipeline.baselines``) gets its rows as a DataFrame; a :class:`HistoryModel` gets them with their
    history, which this compensator keeps from call to call (one compensator per session: each starts with
    no history). ``identity``: what the model is (a saved version's id, or what trained it), recorded in
    each simulated session it drives so a session is never reused for another model."""

    def __init__(self, model, robot: RobotDescription, identity: str | None = None) -> None:
        self.model, self.identity = model, identity
        self.servo_joints = [k for k, j in enumerate(robot.joints) if j.drive != "stepper"]
        self.latencies_s: list[float] = []
        self.history: HistoryState | None = None
        if isinstance(model, HistoryModel):
            self.history_inputs = model.history_inputs()
            self.columns = model.window.columns(self.history_inputs)
            self.history = HistoryState(model.window, len(self.history_inputs))

    def __call__(self, q_ik: np.ndarray, pressure_pa: np.ndarray, current_a: np.ndarray,
                 t_s: float | None = None) -> np.ndarray:  # fmt: skip
        start = time.perf_counter()
        q_ik = np.atleast_2d(np.asarray(q_ik, float))
        inputs = np.concatenate(
            [q_ik, np.atleast_2d(pressure_pa), np.atleast_2d(current_a)[:, self.servo_joints]], axis=1
        )
        if self.history is not None:
            out = self.model.predict(self._with_history(inputs, t_s))
        elif isinstance(self.model, Baseline):
            out = self.model.predict(pd.DataFrame(inputs, columns=list(INVERSE_INPUTS)))
        else:
            out = self.model.predict(inputs)
        out = np.asarray(out, float).reshape(q_ik.shape)
        self.latencies_s.append(time.perf_counter() - start)
        return out

    def _with_history(self, inputs: np.ndarray, t_s: float | None) -> pd.DataFrame:
        if t_s is None:
            raise ValueError("a history-aware compensator needs each set-point's time (t_s)")
        if len(inputs) != 1:
            raise ValueError(f"a history-aware compensator takes one set-point per call, got {len(inputs)}")
        row = dict(zip(INVERSE_INPUTS, inputs[0], strict=True))
        history = self.history.update(t_s, [row[c] for c in self.history_inputs])
        return pd.DataFrame([row | dict(zip(self.columns, history, strict=True))])

    def latency_us(self) -> dict[str, float]:
        """p50 / p99 / max of the calls so far, in µs."""
        if not self.latencies_s:
            return {"calls": 0}
        lat = np.asarray(self.latencies_s) * 1e6
        return {"calls": len(lat), "p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max())}  # fmt: skip


def learned_compensators(
    models: Mapping[str, object],
    robot: RobotDescription | None = None,
    identities: Mapping[str, str | None] | None = None,
) -> Callable[[Plan], InverseModelCompensator]:
    """The learned half of the runners' choice (``acquisition.plans.compensation.compensator_for``): a plan
    whose ``commands`` is a key of ``models`` ("hybrid", "history") gets a new
    :class:`InverseModelCompensator` of that model for ``robot`` (default: the plan's robot by name),
    recorded as ``identities[commands]``. One per plan: a history-aware one starts each session with no
    history."""

    def learned(plan: Plan) -> InverseModelCompensator:
        mode = plan.parameters.get("commands", "ik")
        if mode not in models:
            raise CompensationError(f"{mode} commands need a trained inverse model")
        description = robot if robot is not None else load_robot(plan.robot)
        return InverseModelCompensator(models[mode], description, identity=(identities or {}).get(mode))

    return learned
