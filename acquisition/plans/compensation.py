"""The compensation hook of Experiment 2: desired joint angles in, commanded joint angles out.

A plan's goals are the model-based IK of the desired path (q_ik). A runner with a compensator sends, at every
new set-point, ``compensator(q_ik, pressure_pa, current_a, t_s=t)`` instead: the link pressures and joint
currents are the latest measured ones (seed 000 IV: q̃ = L⁻¹(q, p, i)) and ``t_s`` the set-point's time in
seconds (any fixed origin: a compensator with memory of the path, ``pipeline.in_loop``'s history-aware one,
needs it; the others ignore it). Anything with that call signature plugs in —
the hybrid inverse network once one is trained (``pipeline`` builds it and hands it to the runner), or the
grey-box :class:`StaticModelCompensator` here.

Shapes: q_ik (n, A) rad, pressure_pa (n, C) Pa, current_a (n, A) A → (n, A) rad.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from acquisition.errors import AcquisitionError
from acquisition.plans.plan import Plan
from models import kinematics
from models.robot import AnthropomorphicKinematics, RobotDescription
from models.statics import servo_droop, static_deflection


class Compensator(Protocol):
    def __call__(self, q_ik: np.ndarray, pressure_pa: np.ndarray, current_a: np.ndarray,
                 t_s: float | None = None) -> np.ndarray: ...  # fmt: skip


LEARNED = ("hybrid", "history")  # commands a trained inverse model gives (``pipeline.in_loop`` builds them)


class CompensationError(AcquisitionError, ValueError):
    """A plan's commands cannot be given: a learned kind without a model to give them."""


def compensator_for(
    plan: Plan, robot: RobotDescription, learned: Callable[[Plan], Compensator] | None = None
) -> Compensator | None:
    """What turns ``plan``'s goals into commands, by its ``commands`` parameter: nothing (``ik``: model-based
    IK), the static model (``static``), or ``learned(plan)`` (``hybrid``, ``history``). The one place the
    choice is made, for the real-time and the simulated runner alike; the learned compensators come from
    ``pipeline.in_loop.learned_compensators`` (the pipeline is above both runners, so it is passed in)."""
    mode = plan.parameters.get("commands", "ik")
    if mode == "static":
        return StaticModelCompensator(robot, plan.parameters["payload_kg"])
    if mode in LEARNED:
        if learned is None:
            raise CompensationError(f"{mode} commands need a trained inverse model")
        return learned(plan)
    return None


class StaticModelCompensator:
    """Grey-box compensation from the robot description: the links bend by δ = M/k(p) and the servos droop by
    τ/K under the static load of the arm and a known payload; find the command whose predicted tip lands on
    the desired one (fixed point on the rigid IK of the predicted tip). The currents are not used: the payload
    is told, not inferred (that is what the hybrid network adds)."""

    def __init__(self, robot: RobotDescription, payload_kg: float, iterations: int = 4) -> None:
        if not isinstance(robot.kinematics, AnthropomorphicKinematics) or robot.servo is None:
            raise ValueError(f"robot {robot.name!r}: static compensation needs the servo-driven VSL-type arm")
        kin = robot.kinematics
        self.robot, self.payload_kg, self.iterations = robot, payload_kg, iterations
        self.lengths = kin.arm()

    def predict_tip(self, q_cmd: np.ndarray, pressure_pa: np.ndarray) -> np.ndarray:
        """Where the tip comes to rest for commands ``q_cmd`` (n, A): servo droop, then link bending."""
        q_out = q_cmd + servo_droop(self.robot, q_cmd, self.payload_kg)
        delta, _ = static_deflection(self.robot, q_out, pressure_pa, self.payload_kg)
        return self.robot.chain().position(q_out, delta)

    def __call__(self, q_ik: np.ndarray, pressure_pa: np.ndarray, current_a: np.ndarray,
                 t_s: float | None = None) -> np.ndarray:  # fmt: skip
        q_ik = np.atleast_2d(np.asarray(q_ik, float))
        pressure_pa = np.broadcast_to(pressure_pa, (len(q_ik), self.robot.pneumatics.channels))
        q_cmd = q_ik.copy()
        for _ in range(self.iterations):
            # the rigid IK of the predicted tip says which angles the arm "really" reached
            q_reached = kinematics.vsl_ik(self.predict_tip(q_cmd, pressure_pa), self.lengths, 1)
            q_cmd = q_cmd + (q_ik - q_reached)
        return q_cmd
