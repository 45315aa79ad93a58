"""`vslab twin check` (issue 33): how well descriptions of the arm predict a dataset the fit did not see.

Each description predicts every settled point's tracked tip from what was measured there (the encoders, the
link pressures, the payload, and the moves that led to it: the statics of ``pipeline.twin_fit``, hysteresis
included), with only the tracker registration fitted to the dataset (the same six numbers for every
description: the registration is the lab's bench, not the arm). The distances are tabled per pressure ×
payload cell, and beside them the floor (``pipeline.floor``) when the dataset's repeat is given: what no
static model can predict. A fitted twin is as good as the data allow when it reaches the floor.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from models.robot import RobotDescription
from pipeline.floor import floor_errors_mm, matched_points
from pipeline.metrics import cell_pressure_pa, cell_records
from pipeline.twin_fit import VslStaticFit


def twin_check(descriptions: dict[str, RobotDescription], data: pd.DataFrame,
               repeat: pd.DataFrame | None = None) -> pd.DataFrame:  # fmt: skip
    """Per pressure × payload cell and over all (``pressure_bin`` "all"), the mean distance (mm) between
    each description's prediction and the tracked tip (``<name>_mm``) and, given ``repeat`` (the same
    campaign points visited in another order), the floor (``floor_mm``) on the points both visited.
    ``TwinFitError`` for data no prediction can be made of; ``ValueError`` when ``repeat`` is not the
    dataset's repeat."""
    rows = matched_points(data, repeat) if repeat is not None else data.reset_index(drop=True)
    errors = {
        f"{name}_mm": VslStaticFit(robot, fit_parameters=False).fit(rows).errors_mm_
        for name, robot in descriptions.items()
    }
    if repeat is not None:
        kin = next(iter(descriptions.values())).kinematics  # the rigid FK that takes out what q explains
        errors["floor_mm"] = floor_errors_mm(rows, kin.arm())
    cells = pd.DataFrame(cell_records(errors, cell_pressure_pa(rows), rows["payload_kg"].to_numpy(float)))
    overall = {"pressure_bin": "all", "payload_g": -1, "n": len(rows)}
    overall |= {f"{name}_mean": float(np.nanmean(e)) for name, e in errors.items()}
    return pd.concat([cells, pd.DataFrame([overall])], ignore_index=True)
