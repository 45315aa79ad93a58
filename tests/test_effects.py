"""The twin's unmodelled effects (models.effects, issue 19): each is switched on by a robot description and
leaves its signature in what the twin's sensors record — the tracker's frames, read as a session reads them.

- Field distortion: the tracker's error at a place repeats on every visit and changes from place to place.
- Creep: after a load change the tracked tip keeps sinking for a minute; two arms at the same joint
  readings, pressures and currents hold their tips apart by the loads they carried before; and the loop
  under a cycled load depends on the cycling's rate.
- Hoses: the joints' currents carry a torque that depends on the pose.
- Elongation: at the same joints the tracked tip moves out along the links in proportion to their pressure.
"""

from __future__ import annotations

import numpy as np
import pytest

from models import kinematics
from models.effects import Creep, EffectsSpec, Elongation, Hoses, JointHoses, TrackerDistortion, tracker_bias
from models.robot import RobotDescriptionError, load_robot
from twin import streams
from twin.sensors import CURRENT_A_PER_COUNT
from twin.world import World

POSES = np.array([[-0.3, 0.5, -0.8], [0.0, 0.7, -1.2], [0.3, 0.9, -1.4], [0.2, 0.4, -0.5], [-0.2, 1.0, -1.7],
                  [0.1, 0.6, -0.6]])  # fmt: skip
DISTORTION = TrackerDistortion(rms_m=0.0007, length_scale_m=0.05, seed=0)
CREEP = Creep(fractions=(0.03, 0.05), time_constants_s=(2.0, 60.0))
HOSES = Hoses(joints={"q2": JointHoses(stiffness_nm_per_rad=0.05, slack_rad=0.8),
                      "q3": JointHoses(stiffness_nm_per_rad=0.05, slack_rad=-1.2)})  # fmt: skip


def _vsl_with(**effects):
    """configs/robots/vsl.yaml with only the named effects on."""
    return load_robot("vsl").model_copy(update={"effects": EffectsSpec(**effects)})


def _tracked(world: World, seconds: float, window_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Run ``seconds`` and return (B, 3) mean tracked tip over the last ``window_s`` in the base frame (the
    tracker frame mapped back with the tracker's placement) and (B, 3) the true tip at the end."""
    trace = world.run_for(seconds)
    frames = world.read(trace)["tracker"]
    transform = streams.tracker_spec(world.robot).base_to_tracker
    base = (frames["position"] - transform[:3, 3]) @ transform[:3, :3]
    late = frames["t_true"] > trace.t[-1] - window_s
    mean = np.array([np.nanmean(base[late & (frames["robot"] == b)], axis=0) for b in range(world.batch)])
    return mean, trace.tip_pos[:, -1]


def _tracker_errors(robot, order: list[int]) -> np.ndarray:
    """The tracker's error (mean reading − true tip, m) at each visit of POSES in ``order``."""
    world = World(robot, batch=1, seed=3, q0=POSES[order[0]], pressure_pa=100000.0)
    errors = []
    for i in order:
        world.command_joints(POSES[i])
        mean, true = _tracked(world, 2.0)
        errors.append(mean[0] - true[0])
    return np.array(errors)


@pytest.mark.parametrize("on", [True, False])
def test_field_distortion_repeats_at_each_place(on):
    """With the distortion on, each pose's tracker error is the same on both visits (within the 0.25 mm
    tracker noise averaged over 20 frames) and differs between poses by about its configured RMS; with it
    off the error is that noise only."""
    robot = _vsl_with(tracker_distortion=DISTORTION) if on else _vsl_with()
    order = [0, 1, 2, 3, 4, 5, 3, 0, 5, 2, 4, 1]
    errors = _tracker_errors(robot, order)
    first, second = {}, {}
    for i, e in zip(order, errors, strict=True):
        (second if i in first else first)[i] = e
    repeat = np.array([first[i] - second[i] for i in range(len(POSES))])
    spread = np.array([first[i] for i in range(len(POSES))])
    assert np.abs(repeat).max() < 0.2e-3  # the same place, the same error
    if on:
        assert np.sqrt(np.mean(np.sum(spread**2, axis=1))) > 0.3e-3  # a place-dependent bias of ~0.7 mm
        assert np.linalg.norm(spread - spread.mean(axis=0), axis=1).max() > 0.3e-3  # not one offset
    else:
        assert np.abs(spread).max() < 0.2e-3


def test_field_distortion_is_smooth_and_scaled():
    grid = np.random.default_rng(0).uniform([-0.25, -0.25, 0.05], [0.25, 0.25, 0.55], (20000, 3))
    bias = tracker_bias(DISTORTION, grid)
    assert np.sqrt(np.mean(np.sum(bias**2, axis=1))) == pytest.approx(0.0007, rel=0.2)
    moved = tracker_bias(DISTORTION, grid + np.array([0.001, 0.0, 0.0]))
    assert np.abs(moved - bias).max() < 0.1e-3  # 1 mm of motion moves the bias by < 0.1 mm: a smooth field
    far = tracker_bias(DISTORTION, grid + np.array([0.2, 0.0, 0.0]))
    assert abs(np.corrcoef(far[:, 0], bias[:, 0])[0, 1]) < 0.3  # 4 length scales away: nearly independent
    other = tracker_bias(DISTORTION.model_copy(update={"seed": 1}), grid)
    assert abs(np.corrcoef(other[:, 0], bias[:, 0])[0, 1]) < 0.3  # each seed its own field
    np.testing.assert_array_equal(tracker_bias(DISTORTION, grid), bias)  # the same place, the same bias


def test_creep_keeps_the_tip_sinking_after_a_load():
    """100 g hung at the tip at 0.5 bar: from 3 s to two minutes after, the tracked tip of the nominal twin is
    still; with creep it sinks a further ~0.25 mm (8 % of the links' elastic bending, τ = 2 s and 60 s).
    Both twins draw the same noise (creep draws none), so their difference is creep alone."""
    sinking = {}
    for name, robot in (("creep", _vsl_with(creep=CREEP)), ("none", _vsl_with())):
        world = World(robot, batch=1, seed=5, q0=POSES[1], pressure_pa=50000.0)
        world.run_for(3.0)
        world.set_payload(0.1)
        early, _ = _tracked(world, 3.0, window_s=2.0)
        world.run_for(115.0)
        late, _ = _tracked(world, 2.0, window_s=2.0)
        sinking[name] = early[0, 2] - late[0, 2]
    assert abs(sinking["none"]) < 0.1e-3  # the tracker's noise over two 2 s windows
    assert 0.15e-3 < sinking["creep"] - sinking["none"] < 0.5e-3


def test_creep_makes_the_tip_depend_on_the_load_history():
    """Two arms at the same pose and pressure: one carried 100 g for four minutes, the other nothing. Ten
    seconds after the load comes off they stand apart already on the nominal twin (the servos' backlash and
    the links' hysteresis, which the joint readings show). Creep moves the loaded arm's tip a further
    ≥ 0.12 mm while its joint readings stay where they were: a history no static map of (q, p, i) sees."""
    gaps, joints = {}, {}
    for name, robot in (("creep", _vsl_with(creep=CREEP)), ("none", _vsl_with())):
        world = World(robot, batch=2, seed=5, q0=POSES[1], pressure_pa=50000.0)
        world.set_payload(np.array([0.1, 0.0]))
        world.run_for(240.0)
        world.set_payload(0.0)
        trace = world.run_for(9.5)
        tip, _ = _tracked(world, 0.5)
        gaps[name] = tip[0] - tip[1]
        joints[name] = trace.q[:, -1]  # the encoders' angles (the servos' output shafts)
    assert np.linalg.norm(gaps["creep"] - gaps["none"]) > 0.12e-3  # ~0.19 mm: the same noise in both twins
    np.testing.assert_allclose(joints["creep"], joints["none"], atol=1e-5)


def _load_loop_area(robot, period_s: float, steps: int = 100) -> float:
    """The area (mm·kg) of the loop the true tip's height draws against a payload cycled 0 → 100 g → 0 with
    ``period_s``, over the second of two cycles (the shoelace formula)."""
    world = World(robot, batch=1, seed=5, q0=POSES[1], pressure_pa=50000.0)
    world.run_for(3.0)
    loads, heights = [], []
    for k in range(2 * steps):
        loads.append(0.05 * (1 - np.cos(2 * np.pi * k / steps)))
        world.set_payload(loads[-1])
        heights.append(world.run_for(period_s / steps).tip_pos[0, -1, 2] * 1e3)
    m, z = np.array(loads[steps:]), np.array(heights[steps:])
    return 0.5 * abs(m @ np.roll(z, -1) - z @ np.roll(m, -1))


def test_creep_makes_the_hysteresis_depend_on_the_rate():
    """Rate-dependent hysteresis: the creep's Prony terms are Maxwell branches, beside the links' rate-
    independent Bouc–Wen loop. The loop they add to the tip's height against a cycled payload is largest near
    a period of 2πτ (τ = 2 s: 12 s) and much smaller at 2 s, where the branch has no time to move."""
    added = {}
    for period in (2.0, 12.0):
        added[period] = _load_loop_area(_vsl_with(creep=CREEP), period) - _load_loop_area(_vsl_with(), period)
    print(f"\nloop area added by creep: {added} mm·kg")
    assert added[12.0] > 2 * added[2.0] > 0


def test_hoses_pull_the_joints_by_their_pose():
    """Tubes and cables across J2 and J3 pull each joint by −K (q − q_slack). At each pose, unloaded, the
    servos' measured currents differ from the nominal twin's by the torque that holds it, K (q − q_slack) /
    k_t (linear in the pose, zero where they hang slack), and the encoders show the joints giving way to the
    pull by its torque over the servo's stiffness."""
    currents, angles = {}, {}
    for name, robot in (("hoses", _vsl_with(hoses=HOSES)), ("none", _vsl_with())):
        world = World(robot, batch=len(POSES), seed=5, q0=POSES, pressure_pa=100000.0)
        trace = world.run_for(3.0)
        servo = world.read(trace)["servo_bus"]
        late = servo["t_true"] > trace.t[-1] - 1.0
        counts = [servo["current"][late & (servo["robot"] == b)].mean(axis=0) for b in range(len(POSES))]
        currents[name] = np.array(counts) * CURRENT_A_PER_COUNT
        angles[name] = trace.q[:, -1, 1:]
    servo = load_robot("vsl").servo
    slack = np.array([HOSES.joints[j].slack_rad for j in ("q2", "q3")])
    pull = -0.05 * (angles["hoses"] - slack)  # N·m on J2, J3 at each pose; the servo holds −pull
    held = currents["hoses"] - currents["none"]
    np.testing.assert_allclose(held, -pull / servo.torque_constant_nm_per_a, atol=2e-3)  # the noise over 1 s
    droop = angles["hoses"] - angles["none"]
    np.testing.assert_allclose(droop, pull / servo.stiffness_nm_per_rad, atol=2.5e-4)  # ¼ of the play


def test_pressurised_links_lengthen():
    """Two arms at the same pose, at 0.5 and 2 bar, on twins with and without the links' elongation (0.25 %
    per bar) and the same noise: the tracked tips differ by the links' stretch, ε p along each link — the
    rigid arm's tip with L₂ and L₃ lengthened by ε p — four times as much at 2 bar as at 0.5. Within 0.1 mm:
    the longer arm also bends a little more under its own weight (61 µm lower at 2 bar here)."""
    strain, bars = 0.0025, np.array([0.5, 2.0])
    tips = {}
    for name, robot in (
        ("on", _vsl_with(elongation=Elongation(strain_per_bar=strain))),
        ("off", _vsl_with()),
    ):
        world = World(
            robot, batch=2, seed=7, q0=POSES[1], pressure_pa=np.repeat(bars[:, None] * 1e5, 2, axis=1)
        )
        world.command_joints(POSES[1])
        world.run_for(4.0)
        tips[name], _ = _tracked(world, 1.0, window_s=1.0)
    kin = load_robot("vsl").kinematics
    stretch = []
    for bar in bars:
        longer = kinematics.ArmLengths(kin.l1_m, kin.l2_m * (1 + strain * bar), kin.l3_m * (1 + strain * bar))
        nominal = kin.arm()
        stretch.append(kinematics.vsl_fk(POSES[1], longer) - kinematics.vsl_fk(POSES[1], nominal))
    moved = tips["on"] - tips["off"]
    print(f"\nmoved {moved * 1e3} mm, expected {np.array(stretch) * 1e3} mm")
    np.testing.assert_allclose(moved, np.array(stretch), atol=0.1e-3)
    assert np.linalg.norm(moved[1]) > 0.5e-3  # 2 bar: most of a millimetre, above the tracker's noise
    assert 3.5 < np.linalg.norm(moved[1]) / np.linalg.norm(moved[0]) < 4.5


def test_descriptions_switch_effects_on_and_extend_others(tmp_path):
    robot = load_robot("vsl_unmodelled")
    assert robot.effects.active == ["tracker_distortion", "creep", "hoses", "elongation"]
    assert robot.effects.tracker_distortion == DISTORTION and robot.effects.creep == CREEP
    assert robot.effects.hoses == HOSES and robot.effects.elongation == Elongation(strain_per_bar=0.001)
    nominal = load_robot("vsl")
    assert nominal.effects.active == []
    same = {"name", "description", "effects"}
    assert robot.model_dump(exclude=same) == nominal.model_dump(exclude=same)
    # a description says what differs from its base; mappings merge, other values replace
    (tmp_path / "soft.yaml").write_text("extends: vsl_unmodelled\nname: soft\neffects: {creep: null}\n")
    soft = load_robot(tmp_path / "soft.yaml")
    assert (
        soft.effects.active == ["tracker_distortion", "hoses", "elongation"] and soft.servo == nominal.servo
    )
    hose = "{stiffness_nm_per_rad: 1, slack_rad: 0}"
    cases = {
        "loop.yaml": ("extends: loop.yaml\n", "a cycle"),
        "unknown.yaml": ("extends: no_such_robot\n", "no such robot description"),
        "number.yaml": ("extends: 3\n", "expected a robot name or a path"),
        "sum.yaml": ("extends: vsl\neffects: {creep: {fractions: [0.6, 0.5], time_constants_s: [1, 2]}}\n",
                     "fractions sum to 1.1"),
        "pairs.yaml": ("extends: vsl\neffects: {creep: {fractions: [0.1], time_constants_s: [1, 2]}}\n",
                       "time_constants_s has 2"),
        "rms.yaml": ("extends: vsl\neffects: {tracker_distortion: {rms_m: -1}}\n", "rms_m"),
        "typo.yaml": ("extends: vsl\neffects: {creeep: {}}\n", "creeep"),
        "hose.yaml": (f"extends: vsl\neffects: {{hoses: {{joints: {{q7: {hose}}}}}}}\n",
                      "are not actuated joints of this robot"),
    }  # fmt: skip
    for file, (text, says) in cases.items():
        (tmp_path / file).write_text(text)
        with pytest.raises(RobotDescriptionError, match=says) as caught:
            load_robot(tmp_path / file)
        assert "\n" not in str(caught.value)


def test_the_statics_lengthen_the_links_as_the_twin_does():
    """``RobotDescription.row_lengths`` (the fit's and the statics' model of the elongation) gives each D-H
    row the length the twin's kernel gives it, and the chain with those lengths puts the tip where the
    rigid arm with L₂ and L₃ stretched by ε p puts it."""
    from twin import kernel

    robot = _vsl_with(elongation=Elongation(strain_per_bar=0.0025))
    channel, strain = robot.elongating_rows()
    a0 = np.array([r.a_m for r in robot.dh_rows()])
    for p in ([0.5e5, 2e5], [2e5, 1e5]):
        twin_rows = np.empty_like(a0)
        kernel._row_lengths(a0, channel, strain, np.array(p), twin_rows)
        np.testing.assert_array_equal(robot.row_lengths(np.array(p)), twin_rows)
    p = np.array([[1.5e5, 1.5e5]])
    kin = robot.kinematics
    longer = kinematics.ArmLengths(kin.l1_m, kin.l2_m * 1.00375, kin.l3_m * 1.00375)
    tip = robot.chain().position(POSES[1][None], None, robot.row_lengths(p))
    np.testing.assert_allclose(tip[0], kinematics.vsl_fk(POSES[1], longer), atol=1e-12)
    assert not load_robot("vsl").elongating_rows()[1].any()  # the papers' arm does not lengthen
