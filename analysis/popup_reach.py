"""Seed 001 Figs. 12–13 and 15–16: target reaching with the velocity law eq. (3), the rigid-body model (RBM)
against the pseudo-rigid-body model (PRBM, links bending under the load), without and with visual servoing.

The joint motion is planned on the RBM: at every step the tip's Cartesian velocity is the law's
v = min(a0·t, v0, √(2·a0·|d|))·d/|d| towards the target (d = target − RBM tip), mapped to joint rates by the
RBM Jacobian's pseudo-inverse. The same joint angles on the PRBM, with the links' virtual joints at their
static deflection δ = M/k(p) under the arm's masses and the payload (models.statics), give the tip the real
(soft) arm reaches. The paper reports the RBM–PRBM end-effector difference: 6.6 mm at the start, 24.4 mm at
the target (its link masses are not given; ours are ASSUMED in configs/robots/popup.yaml). With visual
servoing the tip error is measured on the soft arm itself (a camera at its end-effector), so the soft arm
reaches the target although the Jacobian is still the RBM's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analysis.figure_files import save_figure
from models.robot import RobotDescription
from models.statics import static_deflection
from models.trajectories import velocity_law_reach

PAPER = {"difference_start_mm": 6.6, "difference_target_mm": 24.4}  # seed 001, Sec. 6
TASK = {"payload_kg": 2.0, "pressure_pa": 60e3, "v0_m_s": 0.1, "a0_m_s2": 0.05,
        "q0_deg": (0.0, 60.0, -120.0), "target_mm": (-800.0, 800.0, 400.0)}  # fmt: skip  # seed 001


@dataclass(frozen=True)
class Reach:
    t: np.ndarray  # (n,) s
    q: np.ndarray  # (n, 3) rad, planned on the RBM
    rbm: np.ndarray  # (n, 3) m, rigid-body tip
    prbm: np.ndarray  # (n, 3) m, the soft arm's tip at the same joint angles
    target: np.ndarray  # (3,) m

    @property
    def difference_mm(self) -> np.ndarray:
        return 1e3 * np.linalg.norm(self.prbm - self.rbm, axis=1)


def reach(robot: RobotDescription, task: dict | None = None, dt: float = 0.02, tol_m: float = 1e-3,
          max_s: float = 60.0, visual_servoing: bool = False) -> Reach:  # fmt: skip
    """Reach the target with the velocity law and the RBM Jacobian's pseudo-inverse, the tip error taken
    from the RBM (the robot controlled as rigid: Figs. 12–13) or, with ``visual_servoing``, measured on the
    soft arm by a camera at its end-effector (the PRBM tip: Figs. 15–16); evaluated on the RBM and PRBM."""
    task = TASK | (task or {})
    chain = robot.chain()
    target = np.asarray(task["target_mm"], float) * 1e-3
    pressure = np.full(robot.pneumatics.channels, task["pressure_pa"])

    def soft_tip(q: np.ndarray) -> np.ndarray:
        return chain.position(q, static_deflection(robot, q, pressure, task["payload_kg"])[0])

    q0, law = np.radians(task["q0_deg"]), (task["v0_m_s"], task["a0_m_s2"])
    tip = soft_tip if visual_servoing else None
    ts, q_path = velocity_law_reach(chain, q0, target, *law, dt=dt, tol_m=tol_m, max_s=max_s, tip=tip)
    pressure = np.full((len(q_path), robot.pneumatics.channels), task["pressure_pa"])
    delta, _ = static_deflection(robot, q_path, pressure, task["payload_kg"])
    return Reach(ts, q_path, chain.position(q_path), chain.position(q_path, delta), target)


def figures_15_16(rigid: Reach, servoed: Reach, out_dir: Path, made_from: dict | None = None) -> dict:
    """Fig. 15: the PRBM and RBM tip paths when the camera closes the loop on the soft arm's tip; Fig. 16: the
    motor joint positions of the two controls (RBM-based and visual servoing) over time."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6, 4.2))
    # RBM solid blue, PRBM dashed orange, as in Fig. 12
    for path, label, style, colour in ((servoed.rbm, "RBM at the same joint angles", "-", "tab:blue"),
                                       (servoed.prbm, "PRBM (the soft arm, seen by the camera)", "--",
                                        "tab:orange")):  # fmt: skip
        ax.plot(1e3 * np.hypot(path[:, 0], path[:, 1]), 1e3 * path[:, 2], style, color=colour, label=label)
    goal = 1e3 * servoed.target
    ax.plot(np.hypot(goal[0], goal[1]), goal[2], "k*", ms=10, label="target")
    ax.set(xlabel="horizontal reach (mm)", ylabel="z (mm)", title="visual servoing: side view")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig15 = save_figure(fig, out_dir, "fig15_popup_visual_servoing_paths", made_from, tight=True)
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.2), sharex=True, layout="constrained")
    for k, ax in enumerate(axes):
        ax.plot(rigid.t, np.degrees(rigid.q[:, k]), "--", label="RBM-based control")
        ax.plot(servoed.t, np.degrees(servoed.q[:, k]), label="visual servoing")
        ax.set(xlabel="time (s)", ylabel=f"q{k + 1} (deg)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig16 = save_figure(fig, out_dir, "fig16_popup_visual_servoing_joints", made_from, tight=True)
    final = 1e3 * np.linalg.norm(servoed.prbm[-1] - servoed.target)
    return {"png": [fig15, fig16], "final_error_mm": final, "q_rigid": rigid.q, "q_servoed": servoed.q}


def figures_12_13(result: Reach, out_dir: Path, made_from: dict | None = None) -> dict:
    """Fig. 12: the RBM and PRBM tip paths (top and side views); Fig. 13: their difference over time, with
    the paper's values marked. Returns the PNGs and the plotted arrays."""
    import matplotlib.pyplot as plt

    fig, (top, side) = plt.subplots(1, 2, figsize=(9.5, 4.0), layout="constrained")
    for path, label, style in (
        (result.rbm, "RBM (rigid links)", "-"),
        (result.prbm, "PRBM (soft links)", "--"),
    ):
        top.plot(1e3 * path[:, 0], 1e3 * path[:, 1], style, label=label)
        side.plot(1e3 * np.hypot(path[:, 0], path[:, 1]), 1e3 * path[:, 2], style, label=label)
    goal = 1e3 * result.target
    top.plot(goal[0], goal[1], "k*", ms=10, label="target")
    side.plot(np.hypot(goal[0], goal[1]), goal[2], "k*", ms=10, label="target")
    for ax in (top, side):
        ax.grid(alpha=0.3)
    top.set(xlabel="x (mm)", ylabel="y (mm)", title="top view", aspect="equal")
    side.set(xlabel="horizontal reach (mm)", ylabel="z (mm)", title="side view")
    side.legend(fontsize=8)
    fig12 = save_figure(fig, out_dir, "fig12_popup_reach_paths", made_from, tight=True)
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.plot(result.t, result.difference_mm, label="this twin (PRBM − RBM)")
    ax.axhline(PAPER["difference_start_mm"], color="grey", ls=":", label="paper: 6.6 mm at the start")
    ax.axhline(PAPER["difference_target_mm"], color="grey", ls="--", label="paper: 24.4 mm at the target")
    ax.set(xlabel="time (s)", ylabel="end-effector difference (mm)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig13 = save_figure(fig, out_dir, "fig13_popup_reach_difference", made_from, tight=True)
    return {"png": [fig12, fig13], "t": result.t, "difference_mm": result.difference_mm}
