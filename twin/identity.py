"""What made a simulated session: the robot description, the plan with its parameters and seed, the code.

A simulated session's id is its plan's name, so a lab holding a session of that name may hold one made from
another robot (a perturbed or edited description), other parameters or other code. The identity, recorded in
the session's card, tells them apart: a complete session is reused only when its identity is this run's; any
other (one from an older vslab, which recorded none, included) is refused in one message, never overwritten
and never silently taken for this run's. Refusing, not keeping both, because ``vslab build`` selects sessions
by experiment: two robots' sessions under one experiment would mix in one dataset.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from acquisition.code_version import code_version
from acquisition.errors import AcquisitionError
from acquisition.plans.plan import Plan
from models.robot import RobotDescription

IDENTITY = "twin_identity"  # session metadata key: the identity, as JSON
TWIN_MODULES = ("twin.runner",)  # the twin's code: these and everything they import
PLAN_ARRAYS = ("goal_t", "goal_q", "goal_speed", "pressure_t", "pressure_pa", "valve_open", "payload_t",
               "payload_kg", "tap_t", "tap_impulse_nms")  # fmt: skip
FIELDS = {"robot_sha256": "robot description", "plan_sha256": "parameters", "model": "learned model",
          "code_version": "twin code"}  # fmt: skip
SHOWN = 3  # session ids named in a refusal
UNKNOWN_MODEL = "unknown"  # a learned compensator that names no model: its sessions never match another run's


class StaleSessionsError(AcquisitionError, ValueError):
    """Complete simulated sessions on disk with this run's ids that another robot, other parameters or other
    code made (or of unknown making): names them, what differs and what to do."""


def robot_sha256(robot: RobotDescription) -> str:
    """sha256 of the description as simulated (``extends:`` chain merged, an experiment's changes made)."""
    return hashlib.sha256(robot.model_dump_json().encode()).hexdigest()


def plan_sha256(plan: Plan, seed: int) -> str:
    """sha256 of everything the plan commands, its parameters and the twin's seed."""
    h = hashlib.sha256()
    h.update(json.dumps({"name": plan.name, "robot": plan.robot, "duration_s": plan.duration_s, "seed": seed,
                         "parameters": plan.parameters}, sort_keys=True, default=str).encode())  # fmt: skip
    for name in PLAN_ARRAYS:
        a = np.ascontiguousarray(getattr(plan, name))
        h.update(f"{name}{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(repr(plan.events).encode())
    return h.hexdigest()


def session_identity(plan: Plan, robot: RobotDescription, seed: int, compensator=None) -> dict:
    """The identity of the session ``plan`` makes on ``robot`` with ``seed``, by this checkout's code; with a
    learned ``compensator`` in the loop, the model it runs (its ``identity``: a saved version's id)."""
    return {
        "robot_sha256": robot_sha256(robot),
        "plan_sha256": plan_sha256(plan, seed),
        "model": model_identity(compensator),
        "code_version": code_version(*TWIN_MODULES),
    }


def model_identity(compensator) -> str | None:
    """What a compensator runs, as the session's identity records it: None for none or model-based ones (the
    plan's parameters say which); a learned one names its model (``identity``), or is of unknown making."""
    if compensator is None or not hasattr(compensator, "model"):
        return None
    return getattr(compensator, "identity", None) or UNKNOWN_MODEL


def recorded_identity(card: dict) -> dict | None:
    """The identity a session card records; None where it records none (an older vslab) or a damaged one."""
    raw = card.get(IDENTITY)
    try:
        identity = json.loads(raw) if isinstance(raw, str) else raw
    except json.JSONDecodeError:
        return None
    return identity if isinstance(identity, dict) else None


def differences(recorded: dict | None, wanted: dict[str, str]) -> list[str]:
    """What differs between a recorded identity and this run's, in words (empty: the same)."""
    if recorded is None:
        return ["unknown (no identity recorded: an older vslab)"]
    differ = [what for key, what in FIELDS.items() if recorded.get(key) != wanted[key]]
    if wanted["model"] == UNKNOWN_MODEL and FIELDS["model"] not in differ:  # nothing says it is the same
        differ.append(f"{FIELDS['model']} (this run's names no saved version)")
    return differ


def refuse(stale: dict[str, list[str]], sessions_dir: Path) -> None:
    """Raise :class:`StaleSessionsError` for ``stale`` (session id → what differs), if any, in one line."""
    if not stale:
        return
    ids = sorted(stale)
    named = ", ".join(ids[:SHOWN]) + (f" and {len(ids) - SHOWN} more" if len(ids) > SHOWN else "")
    whats = sorted({w for ws in stale.values() for w in ws})
    raise StaleSessionsError(
        f"{len(ids)} complete session(s) in {sessions_dir} have this run's ids but not its making "
        f"({named}; differs: {', '.join(whats)}): not reused, not overwritten; move them out of "
        f"{sessions_dir} (or use another --lab) to simulate them again"
    )
