"""The twin of the lab's own robot (issue 33, its static part): `vslab twin fit` and ``pipeline.twin_fit``.

A lab robot the fit is not told about (`bench/lab_arm.yaml`: upper link ×0.8, lower ×1.25, l2 +2 mm,
l3 −2 mm, joint offsets ±0.3°, links that lengthen 0.1 % per bar, hoses across q2 and q3, masses ×1.15, the
servos' torque constant ×0.95, their stiffness ×0.8 and backlash ×2, the lower link's hysteresis slower) is
simulated, built and fitted from the nominal description; the fit finds it within its standard errors. The
command writes a description that extends the nominal one and the twin loads; what it is handed wrong ends
in one `error:` line and exit status 2.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from models.robot import load_robot
from pipeline.servo_fit import BACKLASH, ServoFit
from pipeline.servo_fit import STIFFNESS as SERVO_STIFFNESS
from pipeline.twin_check import twin_check
from pipeline.twin_fit import TwinFitError, VslStaticFit
from vslab.cli import app

runner = CliRunner()

LAB_ROBOT = (Path(__file__).resolve().parents[1] / "bench" / "lab_arm.yaml").read_text()


def _campaign(lab: Path, robot: Path, seed: int, points: int, **overrides):
    """The settled points of a 16-bench campaign of the description at ``robot``, simulated and built in
    ``lab``."""
    from acquisition.recorder.sessions import SessionStore
    from pipeline.build import build
    from pipeline.lab import Lab
    from twin.runner import simulate_experiment

    simulate_experiment("campaign", SessionStore(lab / "sessions"), seed=seed, benches=16,
                        overrides={"points": points, "robot": str(robot), **overrides})  # fmt: skip
    report = build(sorted((lab / "sessions").iterdir()), Lab(lab), "campaign")
    return Lab(lab).datasets.load("campaign", report.version)[0]


def _moves(lab: Path):
    """The moves into the points of the campaign ``_campaign`` built in ``lab`` (the links' swings)."""
    from pipeline.lab import Lab

    return Lab(lab).datasets.load("campaign", table="moves")[0]


# the lab arm's values (bench/lab_arm.yaml) by the fit's names, but its links'
LAB_TRUTH = {"creep.fraction@2s": 0.0, "creep.fraction@60s": 0.0,  # the lab arm does not creep
             "l2_m": 0.252, "l3_m": 0.248, "q2.offset_rad": 0.005236, "q3.offset_rad": -0.005236,
             "elongation.strain_per_bar": 0.001, "upper_vsl.mass_scale": 1.15, "lower_vsl.mass_scale": 1.15,
             "servo.torque_constant_nm_per_a": 1.71, "servo.stiffness_per_p_gain_nm_per_rad": 0.08,
             "servo.backlash_rad": 0.00872, "q2.hose_stiffness_nm_per_rad": 0.05, "q2.hose_slack_rad": 0.8,
             "q3.hose_stiffness_nm_per_rad": 0.05, "q3.hose_slack_rad": -1.2}  # fmt: skip


def _links_truth(truth) -> dict[str, float]:
    """Each link's stiffness at its table's pressures and its loop, by the fit's names, in ``truth``."""
    true = {}
    for link in truth.links:
        table = truth.link_table(link.name)
        true |= {
            f"{link.name}.k@{p / 1e5:g}bar": k
            for p, k in zip(table.pressure_pa, table.stiffness_nm_per_rad, strict=True)
        }
        true |= {
            f"{link.name}.delta_h_rad": link.hysteresis.delta_h_rad,
            f"{link.name}.tau_y_nm": link.hysteresis.tau_y_nm,
        }
    return true


def _held_out(tmp_path: Path, robot: Path, written: Path):
    """`twin check`'s table (per cell, and "all") for the nominal and the ``written`` (fitted) descriptions
    on a held-out 500-point campaign of the arm at ``robot`` and its shuffled repeat (the floor)."""
    drawn, shuffled = (_campaign(tmp_path / order, robot, seed=7, points=500, visit_order=order)
                       for order in ("drawn", "shuffled"))  # fmt: skip
    return twin_check({"nominal": load_robot("vsl"), "fitted": load_robot(written)}, drawn, shuffled)


@pytest.mark.slow
def test_a_lab_robot_the_fit_is_not_told_about(tmp_path):
    """3,000 settled points of the lab's arm: every fitted value within 2 standard errors of the truth
    (measured: every one within 1.31), the lengths within 0.3 mm, the offsets within 0.1°, the upper link's
    stiffness within 3 %, the masses within 1 %, the torque constant within 0.5 %, the servos' stiffness
    within
    3 % and backlash within 5 %, the hoses' stiffness within 5 % and slack within 0.02 rad. The hysteresis is
    followed through the arm's own moves (``pipeline.move_paths``): along straight lines between the points
    the upper loop's δ_h and τ_y came out 13–15 % low (3.2 errors); through the moves, 5–6 % (1.2 errors).
    The lower link (stiffer, and carrying only the forearm, the tool and the payload) is within its errors
    but not within 3 %: measured 1.4–10 % low at 0.9–1.3 errors, its standard error at 3,000 points 6–11 %
    (at 17,568 points, `bench/twin_fit.py`, it is within 2 %)."""
    (tmp_path / "lab_robot.yaml").write_text(LAB_ROBOT)
    truth = load_robot(tmp_path / "lab_robot.yaml")
    data = _campaign(tmp_path / "lab", tmp_path / "lab_robot.yaml", seed=3, points=3000)

    fit = VslStaticFit("vsl").fit(data, _moves(tmp_path / "lab"))
    # the lab arm's damping: the upper link's the papers', the lower's ×1.5625 (its table is the lab's upper
    # table ×1.5625, damping and stiffness alike)
    damping = {"upper_vsl.damping_scale": 1.0, "lower_vsl.damping_scale": 1.5625}
    true = LAB_TRUTH | _links_truth(truth) | damping
    # l1-l3, 3 offsets, lengthening, creep's 2, 2 masses, K_t, the servos' 2, 2 hoses' 2; 6 stiffness, 2
    # loop values and the damping a link (its table scaled as a whole, from the swings after the moves)
    assert len(fit.values_) + len(fit.not_identifiable_) == 36
    assert not set(fit.values_) & set(fit.not_identifiable_)
    for name, value in fit.values_.items():
        assert abs(value - true[name]) <= 2 * fit.stderr_[name], (name, value, true[name], fit.stderr_[name])
    assert fit.move_speed_rad_s_ == pytest.approx(1.0, rel=0.02)  # the campaign's, read from its times
    assert fit.field_ is None  # the lab's tracker field is not distorted, and the fit finds none
    for body in ("upper_vsl", "lower_vsl"):
        assert abs(fit.values_[f"{body}.mass_scale"] / 1.15 - 1) < 0.01
    assert abs(fit.values_["servo.torque_constant_nm_per_a"] / 1.71 - 1) < 0.005
    assert abs(fit.values_["servo.stiffness_per_p_gain_nm_per_rad"] / 0.08 - 1) < 0.03
    assert abs(fit.values_["servo.backlash_rad"] / 0.00872 - 1) < 0.05
    for joint in ("q2", "q3"):  # the hoses: their stiffness within 5 %, where they hang slack within 0.02 rad
        assert abs(fit.values_[f"{joint}.hose_stiffness_nm_per_rad"] / 0.05 - 1) < 0.05
        assert abs(fit.values_[f"{joint}.hose_slack_rad"] - true[f"{joint}.hose_slack_rad"]) < 0.02
    assert abs(fit.values_["l2_m"] - 0.252) < 0.3e-3 and abs(fit.values_["l3_m"] - 0.248) < 0.3e-3
    for joint in ("q2", "q3"):  # the encoders' zeros, within 0.1°
        assert abs(fit.values_[f"{joint}.offset_rad"] - true[f"{joint}.offset_rad"]) < np.radians(0.1)
    for p, k in zip((0.5, 1, 1.5, 2), (32.0, 64.0, 96.0, 128.0), strict=True):
        assert abs(fit.values_[f"upper_vsl.k@{p:g}bar"] / k - 1) < 0.03
    # what 0.5-2 bar points cannot tell: the table's ends, and l1 (the registration's vertical offset); the
    # lower (less loaded) link's loop may be too small to time (its τ_y)
    links = ("upper", "lower")
    assert set(fit.not_identifiable_) - {"lower_vsl.tau_y_nm"} == {"l1_m", "q1.offset_rad"} | {
        f"{k}_vsl.k@{p}bar" for k in links for p in ("0.1", "2.5")
    }
    # the damping from 300 moves' swings (measured: the upper link's 1.0015 ± 0.0033, the lower's 1.559 ±
    # 0.039): within 1 % and 5 %; the swings leave the tracker's noise (0.25 mm per axis)
    assert abs(fit.values_["upper_vsl.damping_scale"] - 1) < 0.01
    assert abs(fit.values_["lower_vsl.damping_scale"] / 1.5625 - 1) < 0.05
    assert fit.damping_.n_moves_ >= 290 and fit.damping_.residual_rms_mm_ < 0.28
    assert (
        "registration" in fit.not_identifiable_["l1_m"]
        and "2.5 bar" in fit.not_identifiable_["upper_vsl.k@2.5bar"]
    )

    # a held-out campaign of the lab's arm and its repeat (the floor): the fitted twin predicts it within
    # 1.3× the floor (measured: 0.97×); the nominal twin, the papers' arm, 4.3× off (500 points each)
    written = tmp_path / "fitted.yaml"
    written.write_text(yaml.safe_dump(fit.description("vsl_fitted", "vsl", "campaign", "test")))
    assert load_robot(written).effects.elongation.strain_per_bar == pytest.approx(
        fit.values_["elongation.strain_per_bar"]
    )  # the twin of the fitted description lengthens its links as the lab's arm does
    hoses = load_robot(written).effects.hoses.joints  # and its hoses pull as the lab's do
    assert hoses["q3"].slack_rad == pytest.approx(fit.values_["q3.hose_slack_rad"])
    table = _held_out(tmp_path, tmp_path / "lab_robot.yaml", written)
    overall = table[table["pressure_bin"] == "all"].iloc[0]
    print(f"\nheld out: fitted {overall['fitted_mm_mean']:.3f} mm, nominal "
          f"{overall['nominal_mm_mean']:.3f} mm, floor {overall['floor_mm_mean']:.3f} mm")  # fmt: skip
    assert overall["n"] == 500 and len(table) == 16  # 3 pressure bins × 5 payloads, and all
    assert overall["fitted_mm_mean"] <= 1.3 * overall["floor_mm_mean"], overall.to_dict()
    assert overall["nominal_mm_mean"] > 2 * overall["fitted_mm_mean"], overall.to_dict()


@pytest.mark.slow
def test_fixing_what_the_points_cannot_tell_does_not_shrink_the_others_errors(tmp_path):
    """A draw of the lab arm's campaign whose points do not show the lower link's loop (the arm has one,
    0.00087 rad): the fit names it and fits the rest without it. Their errors are those of the solve that
    still had the loop free, not of the one that fixed it: fixing a value the points cannot tell adds no
    information. (With the errors of the fixed solve, q3's offset fell 4.3 errors from the truth and the
    lower link's stiffness 3.0 and 3.3 at 1 and 1.5 bar; across six draws 15 % of all values fell beyond 2
    errors, now 10 %.) Measured here: every value within 1.8 errors."""
    (tmp_path / "lab_robot.yaml").write_text(LAB_ROBOT)
    truth = load_robot(tmp_path / "lab_robot.yaml")
    data = _campaign(tmp_path / "lab", tmp_path / "lab_robot.yaml", seed=9, points=3000)
    fit = VslStaticFit("vsl").fit(data)
    assert {"lower_vsl.delta_h_rad", "lower_vsl.tau_y_nm"} <= set(fit.not_identifiable_)
    true = LAB_TRUTH | _links_truth(truth)
    for name, value in fit.values_.items():
        assert abs(value - true[name]) <= 2 * fit.stderr_[name], (name, value, true[name], fit.stderr_[name])


@pytest.mark.slow
def test_a_loop_too_loose_to_fit_is_left_nominal_not_taken_as_none(tmp_path):
    """The quick campaign (600 points of the papers' arm over 128 sessions, 4–5 each) cannot fit the lower
    link's loop: its δ_h came out 0.0068 ± 0.012 rad. That is not a loop the points show to be none (the
    rule for δ_h within two errors of zero), it is one they cannot tell: named not identifiable and left at
    the nominal 0.00087. Taken as none, the other values absorbed it: the upper loop's δ_h 30 % wide (3.7
    errors), the upper link's stiffness at 1.5 bar 10 % soft (3.5 errors). Measured now: the upper loop
    within 0.8 errors, every value within 2.4."""
    from pipeline.build import build
    from pipeline.lab import Lab
    from twin.runner import simulate_experiment

    lab = Lab(tmp_path / "lab")
    simulate_experiment("campaign", lab.sessions, seed=0, overrides={"points": 600})
    report = build(sorted((tmp_path / "lab" / "sessions").iterdir()), lab, "campaign")
    fit = VslStaticFit("vsl").fit(lab.datasets.load("campaign", report.version)[0])
    assert "do not constrain" in fit.not_identifiable_["lower_vsl.delta_h_rad"]
    true = _links_truth(load_robot("vsl"))
    assert abs(fit.values_["upper_vsl.delta_h_rad"] - 0.00087) <= 2 * fit.stderr_["upper_vsl.delta_h_rad"]
    for name, value in fit.values_.items():
        if name in true:
            assert abs(value - true[name]) <= 2.5 * fit.stderr_[name], (name, value, true[name])
    written = fit.description("vsl_fitted", "vsl", "campaign", "test")
    assert written["links"][1]["hysteresis"]["delta_h_rad"] == 0.00087  # nominal, not none


@pytest.fixture(scope="module")
def lab(campaign_dataset, tmp_path_factory):
    """A copy of the small twin campaign's lab (the command writes into its twin/ folder)."""
    source, version, _ = campaign_dataset
    copy = tmp_path_factory.mktemp("fit-lab") / "lab"
    shutil.copytree(source / "datasets", copy / "datasets")
    return copy, version


def test_the_command_writes_a_description_the_twin_loads(lab):
    path, version = lab
    result = runner.invoke(app, ["--lab", str(path), "twin", "fit", "--dataset", "campaign"])
    assert result.exit_code == 0, result.output
    written = path / "twin" / "vsl_fitted.yaml"
    assert f"written: {written}" in result.output.replace("\n", "")
    assert "not identifiable, left nominal: l1_m" in result.output
    assert "the loops followed through the arm's moves on its twin at" in result.output.replace("\n", " ")
    assert "the links' damping from their swings after" in result.output.replace("\n", " ")
    data = yaml.safe_load(written.read_text())
    assert data["extends"] == "vsl" and data["fitted"]["dataset"] == f"campaign@{version}"
    robot = load_robot(written)
    assert robot.name == "vsl_fitted" and robot.fitted is not None
    fitted = robot.fitted.parameters
    assert {"l2_m", "l3_m", "upper_vsl.k@1bar", "lower_vsl.tau_y_nm"} <= set(fitted)
    assert robot.kinematics.l2_m == pytest.approx(fitted["l2_m"].value, abs=1e-6)
    k = robot.link_table("upper_vsl").stiffness_nm_per_rad
    assert (
        k[2] == pytest.approx(fitted["upper_vsl.k@1bar"].value, abs=1e-3) and k[0] == 8.0
    )  # 0.1 bar: nominal
    nominal = load_robot("vsl")
    assert robot.pneumatics == nominal.pneumatics  # what was not fitted is the nominal description's
    scale = fitted["upper_vsl.mass_scale"].value  # the masses a link's body carries scale together
    assert robot.masses[0].mass_kg == pytest.approx(0.1 * scale, abs=1e-6) and robot.masses[0].frame == "d2"
    assert all(np.isfinite(v.stderr) and v.stderr > 0 for v in fitted.values())
    assert robot.servo.backlash_rad == pytest.approx(fitted[BACKLASH].value, abs=1e-7)
    assert "no hose torque shows on q2" in robot.fitted.not_identifiable["q2.hose_slack_rad"]
    assert robot.effects.hoses is None and fitted["q3.hose_stiffness_nm_per_rad"].value == 0.0
    assert robot.servo.stiffness_per_p_gain_nm_per_rad == pytest.approx(
        fitted[SERVO_STIFFNESS].value, abs=1e-6
    )


def test_the_check_tables_each_description_per_cell(lab):
    path, _ = lab
    fitted = path / "twin" / "vsl_fitted.yaml"
    if not fitted.exists():
        assert runner.invoke(app, ["--lab", str(path), "twin", "fit", "--dataset", "campaign"]).exit_code == 0
    result = runner.invoke(app, ["--lab", str(path), "twin", "check", "--robot", str(fitted),
                                 "--dataset", "campaign"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "vsl_fitted mm" in result.output and "vsl mm" in result.output and "│ all" in result.output
    result = runner.invoke(app, ["--lab", str(path), "twin", "check", "--robot", str(fitted),
                                 "--dataset", "campaign", "--repeat", "nothing"])  # fmt: skip
    assert result.exit_code == 2 and result.output.startswith("error: --repeat")


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--dataset", "nothing"], "--dataset"),
        (["--dataset", "campaign@0000000000000000"], "--dataset"),
        (["--dataset", "campaign", "--robot", "popup"], "fitted to its link tests"),
        ([], "--dataset: the VSL arm is fitted to a dataset"),
        (["--dataset", "campaign", "--robot", "no_such_robot"], "no such robot description"),
    ],
)
def test_what_the_command_cannot_use_is_one_error_line(lab, args, says):
    path, _ = lab
    result = runner.invoke(app, ["--lab", str(path), "twin", "fit", *args])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines[0].startswith("error:") and says in result.output and "Traceback" not in result.output


def test_moves_that_cannot_be_read_are_one_error_line_before_any_fit(lab, tmp_path):
    path, version = lab
    broken = tmp_path / "lab"
    shutil.copytree(path / "datasets", broken / "datasets")
    (broken / "datasets" / "campaign" / version / "moves.parquet").write_bytes(b"not parquet")
    result = runner.invoke(app, ["--lab", str(broken), "twin", "fit", "--dataset", "campaign"])
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: --dataset campaign@")
    assert "its moves cannot be read" in result.output
    assert "Traceback" not in result.output and not (broken / "twin").exists()


def test_data_a_fit_cannot_use_is_refused_with_why(campaign_dataset):
    data = campaign_dataset[2]
    with pytest.raises(TwinFitError, match="no settled points"):
        VslStaticFit("vsl").fit(data.iloc[:0])
    with pytest.raises(TwinFitError, match="of robot popup, not vsl"):
        VslStaticFit("vsl").fit(data.assign(robot="popup"))
    with pytest.raises(TwinFitError, match="no column x_0"):
        VslStaticFit("vsl").fit(data.drop(columns=["x_0"]))
    with pytest.raises(TwinFitError, match="at least 10"):
        VslStaticFit("vsl").fit(data.iloc[:5])


def test_the_servos_stiffness_and_backlash_are_the_twin_s_within_two_errors(campaign_dataset):
    """600 points of the papers' arm: its servos' 80 N·m/rad (P = 800) and 0.25° of backlash found within 2
    standard errors, the stiffness within 3 % and the backlash within 10 %; least squares through the same
    points takes the stiffness 8.6 % off (where a point rests in the play follows its pose)."""
    data = campaign_dataset[2]
    fit = ServoFit("vsl").fit(data)
    assert not fit.not_identifiable_ and fit.n_sessions_ == 8 and fit.n_points_ == len(data)
    for name, true in ((SERVO_STIFFNESS, 0.1), (BACKLASH, 0.00436)):
        assert abs(fit.values_[name] - true) <= 2 * fit.stderr_[name], (name, fit.values_[name], fit.stderr_)
    assert abs(fit.values_[SERVO_STIFFNESS] / 0.1 - 1) < 0.03
    assert abs(fit.values_[BACKLASH] / 0.00436 - 1) < 0.10
    servo = load_robot("vsl").servo  # least squares of the droop on the torque, as the module says
    amps = data[["i_0", "i_1"]].to_numpy()
    torque = (servo.torque_constant_nm_per_a * (amps - servo.idle_current_a * np.sign(amps))).ravel()
    droop = (data[["qc_1", "qc_2"]].to_numpy() - data[["q_1", "q_2"]].to_numpy()).ravel()
    slope = np.linalg.lstsq(np.c_[torque, np.ones_like(torque)], droop, rcond=None)[0][0]
    assert abs(1 / (slope * servo.p_gain) / 0.1 - 1) > 0.05  # 8.6 % here


def _servo_points(rng: np.random.Generator, sessions: int, per_session: int) -> pd.DataFrame:
    """Settled points of the papers' servos as the servo fit's model has them: each holds a torque drawn in
    ±0.4 N·m, stands τ/k short of its goal (80 N·m/rad), rests anywhere in its 0.25° of play, and its
    encoder rounds to a count; its current is the torque's, plus the idle current, plus 7 counts of noise."""
    servo = load_robot("vsl").servo
    count, n = 2 * np.pi / 4096, sessions * per_session
    torque = rng.uniform(-0.4, 0.4, (n, 2))
    goal = rng.integers(1000, 3000, (n, 2)) * count
    rest = goal - torque / servo.stiffness_nm_per_rad + rng.uniform(-0.5, 0.5, (n, 2)) * servo.backlash_rad
    amps = torque / servo.torque_constant_nm_per_a + servo.idle_current_a * np.sign(torque)
    amps = amps + rng.normal(0.0, 7 * 2.69e-3, (n, 2))
    return pd.DataFrame({"qc_1": goal[:, 0], "qc_2": goal[:, 1], "q_1": np.round(rest[:, 0] / count) * count,
                         "q_2": np.round(rest[:, 1] / count) * count, "i_0": amps[:, 0], "i_1": amps[:, 1],
                         "session": np.repeat([f"s{k}" for k in range(sessions)], per_session)})  # fmt: skip


@pytest.mark.slow
def test_the_servos_stiffness_lands_within_its_errors_as_errors_should():
    """Over 20 seeded draws of 16 sessions the servos' stiffness is off by its standard errors as errors
    should be (rms of error / standard error near 1, none beyond 3). The slope is set by a few extreme
    points: a delete-one-session jackknife, which keeps them whenever it leaves out another session, gave
    these draws rms 7 and 34 errors at worst (and put a lab-arm campaign's 14 errors off)."""
    rng = np.random.default_rng(33)
    z = []
    for _ in range(20):
        fit = ServoFit("vsl").fit(_servo_points(rng, sessions=16, per_session=20))
        z.append((fit.values_[SERVO_STIFFNESS] - 0.1) / fit.stderr_[SERVO_STIFFNESS])
    z = np.abs(z)
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6 and z.max() < 3, z.round(2)


def test_what_the_servos_cannot_tell_is_named_and_left_nominal(campaign_dataset):
    data = campaign_dataset[2]
    passive = ServoFit("vsl").fit(data.assign(qc_1=np.nan, qc_2=np.nan))
    assert not passive.values_ and set(passive.not_identifiable_) == {SERVO_STIFFNESS, BACKLASH}
    assert "passive recording" in passive.not_identifiable_[BACKLASH]
    blind = ServoFit("vsl").fit(data.drop(columns=["i_0", "i_1"]))
    assert "no joint currents" in blind.not_identifiable_[SERVO_STIFFNESS] and not blind.values_
    steppers = load_robot("vsl").model_copy(update={"servo": None})  # no servo at all: named, no traceback
    assert "no servos" in ServoFit(steppers).fit(data).not_identifiable_[BACKLASH]
    still = data[data["payload_kg"] == 0].iloc[:12].assign(i_0=0.061, i_1=-0.061)  # no torque to speak of
    assert "encoder count" in ServoFit("vsl").fit(still).not_identifiable_[SERVO_STIFFNESS]
    fit = VslStaticFit("vsl").fit(data.assign(qc_1=np.nan, qc_2=np.nan))  # the static fit goes on without
    assert "passive recording" in fit.not_identifiable_[BACKLASH] and "l2_m" in fit.values_
    # without the moves into the points (a dataset built before vslab kept them), no damping: named
    assert "keeps no moves" in fit.not_identifiable_["upper_vsl.damping_scale"] and fit.damping_ is None


def test_damping_the_moves_cannot_tell_is_named_not_guessed(campaign_dataset):
    """Too few moves (a dataset of a few points), moves without their points, or nonsense settings: the
    damping is named not identifiable, with why, or the settings are refused; never a number."""
    from pipeline.damping_fit import DampingFitError, VslDampingFit
    from pipeline.dataset_store import DatasetStore

    lab, version, data = campaign_dataset
    moves, _ = DatasetStore(lab / "datasets").load("campaign", version, table="moves")
    arm = load_robot("vsl")
    few = data[data["point"] < 15]  # the first 15 points: fewer moves than the fit needs (20)
    fit = VslDampingFit(arm).fit(moves, few)
    assert not fit.values_ and "moves with their swings recorded (the fit needs 20)" in (
        fit.not_identifiable_["upper_vsl.damping_scale"])  # fmt: skip
    elsewhere = VslDampingFit(arm).fit(moves.assign(session="another"), data)  # no point of theirs
    assert not elsewhere.values_ and set(elsewhere.not_identifiable_) == {
        "upper_vsl.damping_scale", "lower_vsl.damping_scale"}  # fmt: skip
    assert not VslDampingFit(arm).fit(moves.drop(columns="t_command"), data).values_
    straight = VslStaticFit("vsl", moves="straight").fit(data, moves)  # no move speed read: none assumed
    assert straight.damping_ is None
    assert "no move speed" in straight.not_identifiable_["lower_vsl.damping_scale"]
    for bad in ({"move_speed_rad_s": 0.0}, {"ring_s": -1.0}, {"max_moves": 0}):
        with pytest.raises(DampingFitError, match="must be positive"):
            VslDampingFit(arm, **bad).fit(moves, data)


def test_a_campaign_dataset_keeps_the_moves_into_its_points(campaign_dataset):
    """Each point's move: the timeline's rows from its goal's command to its settled window, in the base
    frame; the tip swings there (it travels between the points and rings after), where it holds still in
    the settled window."""
    from pipeline.dataset_store import DatasetStore

    lab, version, data = campaign_dataset
    moves, _ = DatasetStore(lab / "datasets").load("campaign", version, table="moves")
    assert set(moves.columns) == {"t", "t_command", "session", "point", "x_0", "x_1", "x_2", "q_0", "q_1",
                                  "q_2", "p_0", "p_1"}  # fmt: skip
    assert (moves["t"] >= moves["t_command"]).all()
    settled = data.set_index(["session", "point"])["t"]
    ends = settled.reindex(pd.MultiIndex.from_frame(moves[["session", "point"]])).to_numpy()
    assert np.isfinite(ends).mean() > 0.95 and (moves["t"].to_numpy() < np.nan_to_num(ends, nan=np.inf)).all()
    per_move = moves.groupby(["session", "point"]).size()
    assert len(per_move) >= 0.95 * len(data) and per_move.min() >= 35  # about 1 s to settle, at 40 Hz
    last = moves.groupby(["session", "point"])[["x_0", "x_1", "x_2"]].last()
    here = data.set_index(["session", "point"]).loc[last.index, ["x_0", "x_1", "x_2"]]
    assert np.median(np.linalg.norm(last.to_numpy() - here.to_numpy(), axis=1)) < 1e-3  # arrived


NO_LOOP = """\
extends: vsl
name: vsl
description: the papers' arm without hysteresis
links:
  - {name: upper_vsl, after_joint: q2, virtual_joints: [d2], hinge_fraction: 0.15, pressure_channel: 0,
     table: {pressure_pa: [10000, 50000, 100000, 150000, 200000, 250000],
             stiffness_nm_per_rad: [8.0, 40.0, 80.0, 120.0, 160.0, 200.0],
             damping_nms_per_rad: [0.118, 0.264, 0.374, 0.458, 0.529, 0.591]},
     hysteresis: {delta_h_rad: 0.0, tau_y_nm: 0.18}}
  - {name: lower_vsl, after_joint: q3, virtual_joints: [d3], hinge_fraction: 0.15, pressure_channel: 1,
     table: {from_link: upper_vsl, factor: 1.0}, hysteresis: {delta_h_rad: 0.0, tau_y_nm: 0.18}}
"""


@pytest.mark.slow
def test_an_arm_without_hysteresis_is_fitted_without_a_loop(tmp_path):
    """The nominal description has a loop on each link; an arm without one gets δ_h = 0, not the nominal
    loop left in place (which took its upper link's stiffness 6–21 % low), and τ_y named as not identifiable.
    (Measured: the upper link's stiffness within 2 %, the lower's within 8 %, 3.8 errors at 1 bar.)"""
    from pipeline.build import build
    from pipeline.lab import Lab
    from twin.runner import simulate_experiment

    (tmp_path / "arm.yaml").write_text(NO_LOOP)
    lab = Lab(tmp_path / "lab")
    simulate_experiment("campaign", lab.sessions, seed=22, overrides={"points": 3000,
                        "robot": str(tmp_path / "arm.yaml")})  # fmt: skip
    report = build(sorted((tmp_path / "lab" / "sessions").iterdir()), lab, "campaign")
    fit = VslStaticFit("vsl").fit(lab.datasets.load("campaign", report.version)[0])
    for link in ("upper_vsl", "lower_vsl"):
        assert fit.values_[f"{link}.delta_h_rad"] == 0.0 and fit.stderr_[f"{link}.delta_h_rad"] > 0
        assert "no hysteresis loop" in fit.not_identifiable_[f"{link}.tau_y_nm"]
    for p in (0.5, 1, 1.5, 2):
        assert abs(fit.values_[f"upper_vsl.k@{p:g}bar"] / (80.0 * p) - 1) < 0.03
    written = fit.description("vsl_fitted", "vsl", "campaign", "test")
    assert [link["hysteresis"]["delta_h_rad"] for link in written["links"]] == [0.0, 0.0]


def test_the_compiled_hysteresis_steps_each_session_as_the_links_bouc_wen_law_does():
    """``hysteresis_states`` (compiled) against the law stepped in numpy over every session at once: each
    point's state after the moves into it, sessions apart, interleaved in the rows and of unequal lengths."""
    from models.prbm import bouc_wen_step
    from pipeline.arm_history import hysteresis_states, session_order

    rng = np.random.default_rng(7)
    n = 400
    sessions, t = rng.integers(0, 6, n), rng.uniform(0, 100, n)
    order = session_order(sessions, t)
    assert (order < 0).any()  # sessions of unequal lengths: padded
    path = np.cumsum(rng.normal(0, 0.3, (n, 8, 2)), axis=1)  # torques along each move, two links
    tau_y = np.array([0.4, 0.9])
    expected = np.zeros((n, 2))
    state, prev = np.zeros((len(order), 2)), np.zeros((len(order), 2))
    for step in order.T:
        now = step >= 0
        for sub in range(path.shape[1]):
            state[now] = bouc_wen_step(state[now], path[step[now], sub] - prev[now], tau_y)
            prev[now] = path[step[now], sub]
        expected[step[now]] = state[now]
    got = hysteresis_states(path, tau_y, order)
    assert np.abs(got).max() > 0.5  # the loops were driven well into their saturation
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)  # expm1: the C library's, not numpy's


CREEPING = """\
extends: vsl
name: vsl
description: the papers' arm whose links creep (unmodelled-effects.md's placeholder sizes)
effects:
  creep: {fractions: [0.03, 0.05], time_constants_s: [2.0, 60.0]}
"""


@pytest.mark.slow
def test_links_that_creep_are_fitted_with_their_creep(tmp_path):
    """The papers' arm whose links creep (3 % of their bending with τ = 2 s, 5 % with 60 s), 3,000 points:
    with creep left out of the fit the links' stiffness came out 3–7 % soft (2–4.5 errors off;
    `bench/twin_fit.py`'s draw); fitted beside it at those time constants (the description's, or
    unmodelled-effects.md's where it has none), both fractions within 2 errors (measured 4.8 ± 1.1 % and
    5.3 ± 0.7 %), the upper link's stiffness within 3 % (+1.7 to +2.4 %: 1.1–2.5 errors) and the lower
    link's within 2 errors (−0.2 to −8.6 %, up to 1.6), and written into the description the twin runs."""
    from pipeline.build import build
    from pipeline.lab import Lab
    from twin.runner import simulate_experiment

    (tmp_path / "arm.yaml").write_text(CREEPING)
    lab = Lab(tmp_path / "lab")
    simulate_experiment("campaign", lab.sessions, seed=3, benches=16, overrides={"points": 3000,
                        "robot": str(tmp_path / "arm.yaml")})  # fmt: skip
    report = build(sorted((tmp_path / "lab" / "sessions").iterdir()), lab, "campaign")
    fit = VslStaticFit("vsl").fit(lab.datasets.load("campaign", report.version)[0])
    for time, fraction in ((2, 0.03), (60, 0.05)):
        name = f"creep.fraction@{time}s"
        assert abs(fit.values_[name] - fraction) <= 2 * fit.stderr_[name], (name, fit.values_[name])
    for p in (
        0.5,
        1,
        1.5,
        2,
    ):  # the upper link's stiffness within 3 %, the lower (less loaded) within 2 errors
        upper, lower = fit.values_[f"upper_vsl.k@{p:g}bar"], fit.values_[f"lower_vsl.k@{p:g}bar"]
        assert abs(upper / (80.0 * p) - 1) < 0.03, (p, upper)
        assert abs(lower - 80.0 * p) <= 2 * fit.stderr_[f"lower_vsl.k@{p:g}bar"], (p, lower)
    written = tmp_path / "fitted.yaml"
    written.write_text(yaml.safe_dump(fit.description("vsl_fitted", "vsl", "campaign", "test")))
    creep = load_robot(written).effects.creep
    assert creep.time_constants_s == (2.0, 60.0)
    assert creep.fractions == pytest.approx(
        (fit.values_["creep.fraction@2s"], fit.values_["creep.fraction@60s"])
    )


@pytest.mark.slow
def test_a_distorted_tracker_field_is_fitted_beside_the_arm(tmp_path):
    """The lab arm tracked through a field bent by metal (0.7 mm over 50 mm, vsl_unmodelled's): left out, it
    took the stiffness ×0.45 to ×1.5 at 4–30 standard errors. The fit finds the field in its residuals
    (``pipeline.tracker_field``), profiles it out and names the lengths and offsets, which move the tip
    through the field as its bias does, not identifiable: with them fitted beside a field (even the exact
    Gaussian process at the true size) they came 1–2.5 mm and 0.4° off at 3–5 errors. Measured (seed 3):
    the upper link's stiffness within 1.7 %, the lower link's within 11 % (1.25 errors), every stiffness,
    loop, hose and lengthening within 2 errors. Not within 2 errors: the lower link's mass (−1.4 %, 5.8
    errors) and the torque constant (+0.3 %, 4.1): the currents weigh the arm with the nominal lengths'
    moment arms."""
    distorted = LAB_ROBOT.replace(
        "effects:\n", "effects:\n  tracker_distortion: {rms_m: 0.0007, length_scale_m: 0.05, seed: 0}\n"
    )
    assert distorted != LAB_ROBOT
    (tmp_path / "lab_robot.yaml").write_text(distorted)
    truth = load_robot(tmp_path / "lab_robot.yaml")
    data = _campaign(tmp_path / "lab", tmp_path / "lab_robot.yaml", seed=3, points=3000)

    fit = VslStaticFit("vsl").fit(data)
    assert fit.field_ is not None
    per_axis = 0.7 / np.sqrt(3)  # the field's RMS per axis (its realisation over the arm's reach: 0.31)
    assert per_axis / 2 < fit.field_.rms_mm < 2.5 * per_axis
    assert 0.025 < fit.field_.length_scale_m < 0.1
    assert fit.field_.noise_mm < 0.2  # what the field leaves: the tracker's noise (undistorted fit: 0.12)
    assert fit.residual_rms_mm_ < 0.15
    for name in ("l2_m", "l3_m", "q2.offset_rad", "q3.offset_rad"):
        assert "field is distorted" in fit.not_identifiable_[name]
    true = {"elongation.strain_per_bar": 0.001, "q2.hose_stiffness_nm_per_rad": 0.05,
            "q2.hose_slack_rad": 0.8, "q3.hose_stiffness_nm_per_rad": 0.05,
            "q3.hose_slack_rad": -1.2}  # fmt: skip
    true |= _links_truth(truth)
    fitted = {name: value for name, value in fit.values_.items() if name in true}
    assert len(fitted) >= 17  # 8 stiffness, 4 loop values, the lengthening, 2 hoses' 2
    for name, value in fitted.items():
        assert abs(value - true[name]) <= 2 * fit.stderr_[name], (name, value, true[name], fit.stderr_[name])
    for p, k in zip((0.5, 1, 1.5, 2), (32.0, 64.0, 96.0, 128.0), strict=True):
        assert abs(fit.values_[f"upper_vsl.k@{p:g}bar"] / k - 1) < 0.03
    for body in ("upper_vsl", "lower_vsl"):  # the masses within 4 % (measured 3.3 and 1.4 %)
        assert abs(fit.values_[f"{body}.mass_scale"] / 1.15 - 1) < 0.04

    # the fitted description carries the field's map: its twin tracks through the lab's field, and predicts
    # a held-out campaign within 1.3× the floor (measured 0.98×: 0.193 mm, the floor 0.196 mm, the true
    # description 0.186 mm) where the nominal twin is 0.87 mm off
    written = tmp_path / "fitted.yaml"
    written.write_text(yaml.safe_dump(fit.description("vsl_fitted", "vsl", "campaign", "test")))
    field = load_robot(written).effects.tracker_distortion
    assert field is not None and len(field.weights_m) == field.features
    table = _held_out(tmp_path, tmp_path / "lab_robot.yaml", written)
    overall = table[table["pressure_bin"] == "all"].iloc[0]
    assert overall["fitted_mm_mean"] <= 1.3 * overall["floor_mm_mean"], overall.to_dict()
    assert overall["nominal_mm_mean"] > 3 * overall["fitted_mm_mean"], overall.to_dict()
