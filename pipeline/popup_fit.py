"""The twin of the lab's own POPUP arm (issue 33): a link's Table 1 fitted to the lab's link tests, each value
with its standard error, written back as a description that ``extends:`` the nominal one.

Seed 001 measured link 2 on a fixed joint twice: statically (``popup_static``: loads hung at the tip, the
static stiffness k per pressure from τ against δ below the wrinkling moment) and dynamically
(``popup_impact``: taps, the damped frequency f_s and damping ratio ζ of each free oscillation). Its Table 1
joins them (``pipeline.link_tests.table1_estimates``): the link's inertia about its hinge I = k / ω_n² at each
pressure with both tests (ω_n = 2π f_s / √(1 − ζ²)), one I, their mean; then at every tapped pressure
k̂ = I ω_n² and ĉ = 2 ζ I ω_n. The nominal description's table *is* seed 001's k̂ and ĉ, so the fit writes
the lab's k̂ and ĉ into the link's table and its inertia into the link's mass.

Standard errors: I's the larger of the spread of its per-pressure values (any disagreement between the two
tests shows there) and what the static regressions' own errors give it, ω_n's and ζ's from the
spread of the taps at each pressure; k̂'s and ĉ's by propagation (I's error is shared by every pressure). A
pressure tapped fewer than twice has no spread: its values are named not identifiable and left nominal.

Named, not fitted: the other links (the link tests test one, the others rigid on the fixed joint; a link whose
table follows the tested one's, ``from_link``, follows the fitted table), and the link's hysteresis (the
static test's loops are drawn, Figure 7, not fitted yet).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from models.estimator import Estimator
from models.robot import PressureTable, RobotDescription, load_robot
from pipeline.link_tests import (
    elastic_stiffness,
    link_hinge,
    static_curves,
    table1_estimates,
    tap_parameters,
)
from pipeline.twin_fit import TwinFitError


def stiffness_knot(link: str, pressure_pa: float) -> str:
    return f"{link}.k@{pressure_pa / 1e3:g}kPa"


def damping_knot(link: str, pressure_pa: float) -> str:
    return f"{link}.c@{pressure_pa / 1e3:g}kPa"


class PopupLinkFit(Estimator):
    """``PopupLinkFit(robot, link).fit(holds, taps)``: ``holds``, the static test's settled holds
    (``pipeline.link_tests.static_holds`` of its sessions); ``taps``, the dynamic test's taps
    (``impact_taps``). Learns ``values_``, ``stderr_``, ``nominal_`` (by parameter: ``link2.k@10kPa``,
    ``link2.c@10kPa``, ``link2.inertia_kgm2``), ``not_identifiable_`` (name → why), ``measured_`` (Table 1
    per tapped pressure, each value with its standard error: f_s, ζ, the elastic stiffness of the static
    test where it was run, k̂, ĉ) and ``n_holds_``, ``n_taps_``, ``sessions_``."""

    def __init__(self, robot: RobotDescription | str = "popup", link: str = "link2") -> None:
        self.robot = robot
        self.link = link

    def fit(self, holds: pd.DataFrame, taps: pd.DataFrame) -> PopupLinkFit:
        robot = self.robot if isinstance(self.robot, RobotDescription) else load_robot(self.robot)
        spec = next((lk for lk in robot.links if lk.name == self.link), None)
        if spec is None or not isinstance(spec.table, PressureTable):
            raise TwinFitError(f"robot {robot.name!r} has no link {self.link!r} with a stiffness table of "
                               "its own: its link tests cannot be fitted")  # fmt: skip
        for what, rows, test in (("static", holds, "popup_static"), ("dynamic", taps, "popup_impact")):
            if not len(rows):
                raise TwinFitError(f"no {what} test of {self.link}: record {test} sessions of it first")
            known = sorted(set(rows["robot"].astype(str)))
            if known != [robot.name]:
                raise TwinFitError(f"the {what} test's sessions are of robot {', '.join(known)}, not "
                                   f"{robot.name}")  # fmt: skip
        static = elastic_stiffness(static_curves(holds))
        tapped = tap_parameters(taps)
        estimates = table1_estimates(static, tapped)  # seed 001's procedure, on the elastic stiffness
        w_n = 2 * np.pi * tapped["f_s_hz"].to_numpy() / np.sqrt(1 - tapped["zeta"].to_numpy() ** 2)
        measured = static.set_index("pressure_pa").reindex(tapped["pressure_pa"])
        both = measured["k"].notna().to_numpy()
        if both.sum() < 2:
            raise TwinFitError("the static and the dynamic test share fewer than two pressures: the link's "
                               "inertia (I = k / ω_n²) needs two to say how well it is known")  # fmt: skip
        per_pressure = measured["k"].to_numpy()[both] / w_n[both] ** 2  # what table1_estimates averages
        inertia = float(estimates["inertia_kgm2"].iloc[0])
        scatter = float(per_pressure.std(ddof=1) / np.sqrt(len(per_pressure)))
        k_rel_se = measured["k_se"].to_numpy()[both] / measured["k"].to_numpy()[both]
        regressions = float(np.sqrt(np.sum((per_pressure * k_rel_se) ** 2)) / len(per_pressure))
        rel_i = max(scatter, regressions) / inertia  # the larger: what the tests disagree on shows in either

        n = tapped["taps"].to_numpy(float)
        zeta = tapped["zeta"].to_numpy()
        with np.errstate(invalid="ignore", divide="ignore"):
            rel_f = tapped["f_s_std_hz"].to_numpy() / np.sqrt(n) / tapped["f_s_hz"].to_numpy()
            rel_z = tapped["zeta_std"].to_numpy() / np.sqrt(n) / zeta
        rel_w = np.hypot(rel_f, zeta**2 / (1 - zeta**2) * rel_z)  # ω_n = 2π f_s (1 − ζ²)^(−1/2)
        k_hat, c_hat = estimates["k_hat"].to_numpy(), estimates["c_hat"].to_numpy()
        se_k = k_hat * np.hypot(rel_i, 2 * rel_w)
        se_c = c_hat * np.sqrt(rel_i**2 + rel_z**2 + rel_w**2)

        table = robot.link_table(self.link)
        values, stderr, nominal, why = {}, {}, {}, {}
        pressures = tapped["pressure_pa"].to_numpy(float)
        for j, p in enumerate(pressures):
            for name, value, se, nominal_value in (
                (stiffness_knot(self.link, p), k_hat[j], se_k[j],
                 np.interp(p, table.pressure_pa, table.stiffness_nm_per_rad)),
                (damping_knot(self.link, p), c_hat[j], se_c[j],
                 np.interp(p, table.pressure_pa, table.damping_nms_per_rad)),
            ):  # fmt: skip
                if n[j] < 2 or not np.isfinite(se):
                    why[name] = f"{int(n[j])} tap at {p / 1e3:g} kPa: no spread to say how well it is known"
                    continue
                values[name], stderr[name], nominal[name] = float(value), float(se), float(nominal_value)
        name = f"{self.link}.inertia_kgm2"
        values[name], stderr[name], nominal[name] = inertia, inertia * rel_i, hinge_inertia(robot, self.link)
        for other in robot.links:
            if other.name == self.link:
                continue
            alone = f"the link tests test {self.link} alone ({other.name} rigid on the fixed joint)"
            follows = getattr(other.table, "from_link", None) == self.link
            why[other.name] = (
                f"{alone}; its table follows {self.link}'s (× {other.table.factor:g}): the fitted one"
                if follows else alone
            )  # fmt: skip
        why[f"{self.link}.hysteresis"] = "the static test's loops are drawn (Figure 7), not fitted yet"
        self.values_, self.stderr_, self.nominal_, self.not_identifiable_ = values, stderr, nominal, why
        self.measured_ = tapped[["pressure_pa", "taps", "f_s_hz"]].assign(
            f_s_se=tapped["f_s_std_hz"] / np.sqrt(n), zeta=zeta, zeta_se=tapped["zeta_std"] / np.sqrt(n),
            k_static=measured["k"].to_numpy(), k_static_se=measured["k_se"].to_numpy(),
            k_hat=k_hat, k_hat_se=se_k, c_hat=c_hat, c_hat_se=se_c,
        )  # fmt: skip
        self.robot_ = robot
        self.n_holds_, self.n_taps_ = len(holds), len(taps)
        self.sessions_ = sorted({*holds["session_id"].astype(str), *taps["session_id"].astype(str)})
        return self

    def table(self) -> pd.DataFrame:
        """One row per parameter: value, stderr, nominal, and why where it was not identified."""
        self.check_fitted()
        rows = [{"parameter": k, "value": v, "stderr": self.stderr_[k], "nominal": self.nominal_[k],
                 "why": ""} for k, v in self.values_.items()]  # fmt: skip
        rows += [{"parameter": k, "value": np.nan, "stderr": np.nan, "nominal": np.nan, "why": w}
                 for k, w in self.not_identifiable_.items()]  # fmt: skip
        return pd.DataFrame(rows)

    def description(self, name: str, extends: str, link_tests: str, code_version: str) -> dict[str, Any]:
        """The fitted description as YAML data: ``extends`` the nominal one; the link's table at every
        pressure the dynamic test tapped (k̂, ĉ; the nominal table's other pressures as they were), its
        mass's inertia moved by what the fitted inertia about the hinge adds, and a ``fitted`` block (the
        link tests in words, ``link_tests``, the code version, each value with its standard error and
        nominal value, what was not identified and why, Table 1 as measured)."""
        self.check_fitted()
        robot, link = self.robot_, self.link
        nominal = robot.link_table(link)
        knots = {float(p): (k, c) for p, k, c in zip(nominal.pressure_pa, nominal.stiffness_nm_per_rad,
                                                      nominal.damping_nms_per_rad, strict=True)}  # fmt: skip
        for p in self.measured_["pressure_pa"]:
            k, c = stiffness_knot(link, p), damping_knot(link, p)
            if k in self.values_:
                knots[float(p)] = (round(self.values_[k], 4), round(self.values_[c], 6))
        links, k_max = [], max(k for k, _ in knots.values())
        for spec in robot.links:
            data = spec.model_dump(mode="json", exclude_none=True)
            if spec.name == link:
                pressures = sorted(knots)
                data["table"] = {"pressure_pa": pressures,
                                 "stiffness_nm_per_rad": [knots[p][0] for p in pressures],
                                 "damping_nms_per_rad": [knots[p][1] for p in pressures]}  # fmt: skip
            if spec.hysteresis is not None:  # the loop's yield stays above k·δ_h (the description's check)
                follows = getattr(spec.table, "from_link", None) == link
                stiffest = (k_max if spec.name == link else k_max * spec.table.factor if follows
                            else max(robot.link_table(spec.name).stiffness_nm_per_rad))  # fmt: skip
                least = round(stiffest * spec.hysteresis.delta_h_rad, 6) + 1e-6
                data["hysteresis"]["tau_y_nm"] = max(spec.hysteresis.tau_y_nm, least)
            links.append(data)
        masses = [m.model_dump(mode="json", exclude_none=True) for m in robot.masses]
        added = self.values_[f"{link}.inertia_kgm2"] - self.nominal_[f"{link}.inertia_kgm2"]
        own = _link_mass(robot, link)
        if own is not None and (masses[own].get("inertia_kgm2", 0.0) + added) > 0:
            masses[own]["inertia_kgm2"] = round(masses[own].get("inertia_kgm2", 0.0) + added, 7)
        return {
            "extends": extends,
            "name": name,
            "description": f"{robot.description}, fitted to its link tests",
            "links": links,
            "masses": masses,
            "fitted": {
                "link_tests": link_tests,
                "code_version": code_version,
                "static_holds": self.n_holds_,
                "taps": self.n_taps_,
                "parameters": {
                    n: {"value": self.values_[n], "stderr": self.stderr_[n], "nominal": self.nominal_[n]}
                    for n in self.values_
                },
                "not_identifiable": dict(self.not_identifiable_),
                "table1": [
                    {k: (None if pd.isna(v) else float(v)) for k, v in row.items()}
                    for row in self.measured_.to_dict("records")
                ],
            },
        }


def hinge_inertia(robot: RobotDescription, link: str) -> float:
    """The moment of inertia about ``link``'s hinge of every mass carried on the hinge's frame (kg·m²): what
    the dynamic test swings."""
    hinge, arm = link_hinge(robot, link)
    return float(sum(m.mass_kg * (arm + m.position_m[0]) ** 2 + (m.inertia_kgm2 or 0.0)
                     for m in robot.masses if m.frame == hinge))  # fmt: skip


def _link_mass(robot: RobotDescription, link: str) -> int | None:
    """The index of the mass that is ``link``'s own (named after it, on its hinge's frame), or None."""
    hinge, _ = link_hinge(robot, link)
    return next((k for k, m in enumerate(robot.masses) if m.frame == hinge and m.name == link), None)
