"""A trained inverse network in the control loop: the runners' compensation hook (Experiment 2, seed 000).

At each new set-point the runner calls ``compensator(q_ik, pressure_pa, current_a)``: the model-based IK of
the desired point, the link pressures and the joint currents measured now. The hybrid inverse model maps
(q_ik, p, i) to the servo commands that land the tip there: q̃ = L⁻¹(q, p, i). Every call is timed, so the
per-step inference latency of a run can be reported.
"""

from __future__ import annotations

import time

import numpy as np

from models.robot import RobotDescription


class InverseModelCompensator:
    """Wrap a model with ``predict((n, 7) [ik_0..2, p_0, p_1, i_0, i_1]) -> (n, 3) q`` as a compensator for
    ``robot``: currents are taken from its servo joints (the dataset's i_0, i_1 are J2 and J3)."""

    def __init__(self, model, robot: RobotDescription) -> None:
        self.model = model
        self.servo_joints = [k for k, j in enumerate(robot.joints) if j.drive != "stepper"]
        self.latencies_s: list[float] = []

    def __call__(self, q_ik: np.ndarray, pressure_pa: np.ndarray, current_a: np.ndarray) -> np.ndarray:
        start = time.perf_counter()
        q_ik = np.atleast_2d(np.asarray(q_ik, float))
        inputs = np.concatenate(
            [q_ik, np.atleast_2d(pressure_pa), np.atleast_2d(current_a)[:, self.servo_joints]], axis=1
        )
        out = np.asarray(self.model.predict(inputs), float).reshape(q_ik.shape)
        self.latencies_s.append(time.perf_counter() - start)
        return out

    def latency_us(self) -> dict[str, float]:
        """p50 / p99 / max of the calls so far, in µs."""
        if not self.latencies_s:
            return {"calls": 0}
        lat = np.asarray(self.latencies_s) * 1e6
        return {"calls": len(lat), "p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max())}  # fmt: skip
