"""`vslab twin check` for the POPUP arm (issue 33): how well descriptions predict the lab's link tests.

Each description runs the link tests on the twin (``popup_static`` and ``popup_impact``, in a store of its
own, with its own noise: another seed than the lab's), and its sessions are measured exactly as the lab's
are (``pipeline.popup_fit.PopupLinkFit``'s Table 1: the taps' f_s and ζ at each pressure, the static test's
elastic stiffness where it ran). The table sets each quantity the lab measured, with its standard error,
beside what each description's twin gives and how far that is (%). The standard error is the spread of one
session's taps, not a floor: the same arm's tests run again with other noise differ by tens of them in f_s
(the lab's own description, another seed: 0.1 % of f_s, 38 of those errors), so the distances are read in
per cent: a fitted twin within a fraction of a per cent of its arm, the nominal one tens of per cent away
where the arm differs from the paper's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from acquisition.recorder.sessions import SessionStore
from models.robot import load_robot
from pipeline.lab import Lab
from pipeline.link_tests import impact_taps, static_holds
from pipeline.popup_fit import PopupLinkFit
from pipeline.twin_fit import TwinFitError

# what the twin is checked on: the quantities the link tests observe (not k̂, ĉ: derived from them and I)
QUANTITIES = {"f_s_hz": "f_s_se", "zeta": "zeta_se", "k_static": "k_static_se"}
TESTS = (("popup_static", static_holds), ("popup_impact", impact_taps))


def simulated_link_tests(robot: str | Path, store: SessionStore, seed: int,
                         overrides: dict[str, dict] | None = None) -> tuple[pd.DataFrame, ...]:  # fmt: skip
    """(holds, taps) of the link tests run on the twin of ``robot`` (a name or a description file) into the
    session store ``store`` (complete sessions are kept); ``overrides``: per experiment, as ``vslab simulate
    --set`` takes them."""
    from twin.runner import simulate_experiment

    read = {}
    for experiment, rows in TESTS:
        given = (overrides or {}).get(experiment, {}) | {"robot": str(robot)}
        reports = simulate_experiment(experiment, store, seed=seed, overrides=given)
        sessions = sorted({s for r in reports for s in (*r.sessions, *r.skipped)})
        read[experiment] = pd.concat([rows(store.path(s)) for s in sessions], ignore_index=True)
    return read["popup_static"], read["popup_impact"]


def popup_check(descriptions: dict[str, str | Path], measured: pd.DataFrame, link: str, lab: Lab,
                seed: int = 1, overrides: dict[str, dict] | None = None) -> pd.DataFrame:  # fmt: skip
    """One row per tapped pressure and quantity (:data:`QUANTITIES`) the lab measured (``measured``: its
    ``PopupLinkFit(...).measured_``): ``pressure_kpa``, ``quantity``, ``measured``, ``se``, and for each
    description (by its name in ``descriptions``) its twin's value ``<name>`` and distance ``<name>_pct``
    (signed, twin − measured, % of measured). Each description's link tests are simulated into
    ``lab.study(<name>)`` with ``seed``; ``TwinFitError`` where a twin's tests cannot be measured."""
    twins = {}
    for name, robot in descriptions.items():
        holds, taps = simulated_link_tests(robot, lab.study(name).sessions, seed, overrides)
        try:
            twins[name] = (
                PopupLinkFit(load_robot(robot), link).fit(holds, taps).measured_.set_index("pressure_pa")
            )
        except TwinFitError as exc:
            raise TwinFitError(f"the link tests on the twin of {name}: {exc}") from None
    rows = []
    for ours in measured.to_dict("records"):  # the lab's
        p = ours["pressure_pa"]
        for quantity, se_column in QUANTITIES.items():
            value, se = float(ours[quantity]), float(ours[se_column])
            if not np.isfinite(value):  # the static test did not run at this pressure
                continue
            row = {"pressure_kpa": p / 1e3, "quantity": quantity, "measured": value, "se": se}
            for name, twin in twins.items():
                predicted = float(twin[quantity].get(p, np.nan))
                row[name] = predicted
                row[f"{name}_pct"] = 100 * (predicted - value) / value
            rows.append(row)
    return pd.DataFrame(rows)


def check_summary(table: pd.DataFrame, names: list[str]) -> pd.DataFrame:
    """Per quantity, each description's root-mean-square distance (% of measured) over the pressures."""
    return table.groupby("quantity", sort=False).apply(
        lambda g: pd.Series({name: float(np.sqrt(np.nanmean(g[f"{name}_pct"] ** 2))) for name in names}),
        include_groups=False,
    )
