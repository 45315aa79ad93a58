"""The floor under every static model of the arm, measured as a lab could: the campaign run twice.

A static model maps what is measured at a point — joint angles q, pressures p, currents i — to the tip. What
it cannot predict is what changes between two visits to the same point: the tracker's noise and whatever the
arm remembers of how it got there (creep, the links' hysteresis, the servos' backlash). So the same campaign
points are visited again in another order (``visit_order: shuffled``: every point reached from another
history, in a random order of its own) and the two tracked tips of each point compared. Not backwards
(``reversed``): creep runs along a session, so a point early in one run and late in the other gets errors of
opposite sign from it (r ≈ −0.15 to −0.3 between the two visits) and the floor comes out 3–11 % too high.
For forward models, the part of their difference the measured joints explain (the rigid FK of q₁ minus that
of q₂: a forward model reads q) is taken out; inverse models do not read the joints, so for them it stays
(the servos' backlash is history to them). What remains, d, is two independent draws of the unpredictable
error, so one draw's size is |d| / √2 (exact in distribution for isotropic Gaussian errors, and the RMS
exactly for any independent, identically distributed pair). It is the floor of *static* models: one that
reads the points before (``pipeline.history``) knows part of the history and may go below it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from models import kinematics
from models.hybrid import FORWARD_TARGETS
from pipeline import metrics
from pipeline.baselines import MEASURED_Q


def matched_points(first: pd.DataFrame, repeat: pd.DataFrame) -> pd.DataFrame:
    """The static points of ``first`` (its rows, in its order) with the repeat's tip and joints beside them as
    ``<column>_repeat``; points either dataset lacks (a window the build rejected) are left out. ValueError
    if the two are not the same campaign points (a point's payload or commanded joints differ)."""
    cols = ["point", *FORWARD_TARGETS, *MEASURED_Q, "payload_kg", *(c for c in first if c.startswith("qc_"))]
    a, b = first[first["point"] >= 0], repeat[repeat["point"] >= 0]
    for name, d in (("first", a), ("repeat", b)):
        if d["point"].duplicated().any():
            raise ValueError(f"{name}: a point appears twice: not one campaign (points are numbered once)")
    both = a.merge(b[cols], on="point", suffixes=("", "_repeat"), validate="one_to_one")
    if both.empty:
        raise ValueError("the two datasets share no campaign point: not a campaign and its repeat")
    commanded = [c for c in both if c.startswith("qc_") and not c.endswith("_repeat")]
    tolerance = 1e-3  # rad: the stepper's command is known to a fraction of its 2e-3 rad microstep
    same = np.isclose(both["payload_kg"], both["payload_kg_repeat"])
    for c in commanded:
        same &= np.isclose(both[c], both[f"{c}_repeat"], atol=tolerance)
    if not same.all():
        raise ValueError(
            f"{int((~same).sum())} of {len(both)} points differ in payload or commanded joints: the repeat "
            "is not the same campaign (run it with the same seed and points, visit_order: shuffled)"
        )
    tips = [list(FORWARD_TARGETS), [f"{c}_repeat" for c in FORWARD_TARGETS]]
    if (unchanged := int((both[tips[0]].to_numpy() == both[tips[1]].to_numpy()).all(axis=1).sum())) > 0:
        raise ValueError(
            f"{unchanged} of {len(both)} points were measured exactly as in the first run: not reached from "
            "another history (a session of one point is the same backwards); give each session several points"
        )
    return both


def floor_errors_mm(
    both: pd.DataFrame, lengths: kinematics.ArmLengths, direction: str = "forward"
) -> np.ndarray:
    """Per matched point, the size (mm) of one draw of what no static map of the direction's inputs predicts.
    Forward models read the measured joints, so what they explain (the rigid FK of q₁ − q₂) is taken out;
    inverse models read the tip, pressures and currents, not the joints: the two visits share one command, and
    all of the tips' difference is what a static inverse map cannot tell apart."""
    if direction not in ("forward", "inverse"):
        raise ValueError(f"direction must be 'forward' or 'inverse', got {direction!r}")
    x1 = both[list(FORWARD_TARGETS)].to_numpy(float)
    x2 = both[[f"{c}_repeat" for c in FORWARD_TARGETS]].to_numpy(float)
    q1 = both[list(MEASURED_Q)].to_numpy(float)
    q2 = both[[f"{c}_repeat" for c in MEASURED_Q]].to_numpy(float)
    d = x1 - x2
    if direction == "forward":
        d = d - (kinematics.vsl_fk(q1, lengths) - kinematics.vsl_fk(q2, lengths))
    return np.linalg.norm(d, axis=1) * 1e3 / np.sqrt(2.0)


def repeat_floor(first: pd.DataFrame, repeat: pd.DataFrame, lengths: kinematics.ArmLengths,
                 split: str = "split_group", part: str = "test",
                 direction: str = "forward") -> dict:  # fmt: skip
    """The floor of ``direction``'s models on one part of ``first``'s split (the rows they are scored on):
    its ``summary`` and ``per_cell`` records in the models' format (``metrics.tip_report``)."""
    both = matched_points(first[first[split] == part], repeat)
    return metrics.tip_report(floor_errors_mm(both, lengths, direction), both)
