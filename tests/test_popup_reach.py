"""Seed 001 Figs. 12–13: the velocity-law reach planned on the rigid model, evaluated on the soft one."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.popup_reach import TASK, figures_12_13, figures_15_16, reach
from models.robot import load_robot
from models.statics import static_deflection


def test_reach_follows_the_law_and_the_soft_arm_sags_more_along_the_way(tmp_path):
    popup = load_robot("popup")
    result = reach(popup, dt=0.02)
    chain = popup.chain()
    assert np.linalg.norm(result.rbm[-1] - result.target) < 1e-3  # the RBM plan reaches the target
    speed = np.linalg.norm(np.diff(result.rbm, axis=0), axis=1) / np.diff(result.t)
    assert speed.max() <= TASK["v0_m_s"] * 1.02  # the law's cruise speed is never exceeded
    assert speed[:5].max() < 0.01  # it starts from rest (a0·t)
    # at the start: the static deflection at q0 computed here independently
    q0 = np.radians(TASK["q0_deg"])
    delta, _ = static_deflection(popup, q0, np.full(2, TASK["pressure_pa"]), TASK["payload_kg"])
    start = 1e3 * np.linalg.norm(chain.position(q0, delta) - chain.position(q0))
    assert abs(result.difference_mm[0] - start) < 1e-9
    assert result.difference_mm[-1] > result.difference_mm[0]  # as in the paper: larger at the target
    out = figures_12_13(result, tmp_path)
    np.testing.assert_array_equal(out["difference_mm"], result.difference_mm)
    assert all(p.stat().st_size > 5000 for p in out["png"])


@pytest.mark.slow
def test_visual_servoing_lands_the_soft_arm_on_the_target(tmp_path):
    """With the tip measured on the soft arm (a camera at the end-effector), the same RBM Jacobian brings the
    soft arm to the target; controlled as rigid, it misses by the link sag."""
    popup = load_robot("popup")
    rigid, servoed = reach(popup), reach(popup, visual_servoing=True)
    miss_rigid = np.linalg.norm(rigid.prbm[-1] - rigid.target)
    miss_servoed = np.linalg.norm(servoed.prbm[-1] - servoed.target)
    assert miss_servoed < 1e-3 < 0.01 < miss_rigid
    assert np.linalg.norm(servoed.rbm[-1] - servoed.target) > 0.01  # the RBM would have overshot instead
    out = figures_15_16(rigid, servoed, tmp_path)
    assert abs(out["final_error_mm"] - 1e3 * miss_servoed) < 1e-9
    np.testing.assert_array_equal(out["q_servoed"], servoed.q)
    assert all(p.stat().st_size > 5000 for p in out["png"])
