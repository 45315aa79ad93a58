"""Seed 000's Figures 5, 6, 7a/b from small twin datasets: the plotted numbers against numbers computed here
from the DataFrames, the files, and the record of versions."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.image import imread

from acquisition.plans import experiments
from acquisition.recorder.sessions import SessionStore
from analysis import vsl_figures, vsl_paths
from models import kinematics, trajectories
from models.hybrid import FORWARD_INPUTS, preset
from models.robot import load_robot
from pipeline.build import build
from pipeline.dataset_store import DatasetStore
from pipeline.lab import Lab
from pipeline.train import TrainConfig, train
from twin.runner import simulate_experiment

pytestmark = pytest.mark.slow  # module fixtures of seconds each: the whole module is slow-tier

N = 50  # resampled points per path: small, the check is exact
SMALL = {"repetitions": 2, "points_per_segment": 20, "settle_s": 1.0, "rest_s": 0.5, "speed_m_s": 0.1}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A campaign (for the tracker registration), a subset of Experiment 1 (the curve at 25/75 g, 0.5/1.5 bar
    and the rigid arm) and Experiment 2 (75 g / 0.5 bar: ik, static, rigid), two repetitions each."""
    lab = tmp_path_factory.mktemp("lab")
    simulate_experiment(
        "campaign", SessionStore(lab / "campaign"), seed=2, benches=2, overrides={"points": 48}
    )
    campaign = build(sorted((lab / "campaign").iterdir()), Lab(lab), "campaign")
    borrowed = {"registration": {"from_dataset": f"campaign@{campaign.version}"}}
    e1 = {"trajectories": ["curve"], "payloads_g": [25, 75], "pressures_bar": [0.5, 1.5]} | SMALL
    simulate_experiment("experiment1", SessionStore(lab / "e1"), seed=4, overrides=e1)
    e2 = {"cases": [{"payload_g": 75, "pressure_bar": 0.5}], "commands": ["ik", "static"], "rigid_arm": True}
    simulate_experiment("experiment2", SessionStore(lab / "e2"), seed=3, overrides=e2 | SMALL)
    out = {}
    for name, folder in (("experiment1", "e1"), ("experiment2", "e2")):
        report = build(sorted((lab / folder).iterdir()), Lab(lab), name, borrowed)
        out[name] = DatasetStore(lab / "datasets").load(name, report.version, table="trajectories")[0]
        out[f"{name}_version"] = f"{name}@{report.version}"
    d, _ = DatasetStore(lab / "datasets").load("experiment1", out["experiment1_version"].split("@")[1])
    net = preset("forward", "small-residual")
    out["forward"] = train(d[d["robot"] == "vsl"], TrainConfig(net=net, max_epochs=15, seed=0)).model
    return lab, out


def _mean_std(rows, cols, n=N):
    """Independent resampling: per repetition, interpolate at equal fractions of its duration."""
    stacks = []
    for (_, _), g in rows.groupby(["session", "repetition"]):
        g = g.sort_values("t")
        frac = (g["t"] - g["t"].iloc[0]) / (g["t"].iloc[-1] - g["t"].iloc[0])
        stacks.append(np.column_stack([np.interp(np.linspace(0, 1, n), frac, g[c]) for c in cols]))
    stacks = np.array(stacks)
    return stacks.mean(0), stacks.std(0), len(stacks)


def _files_ok(result, stems, versions):
    for stem in stems:
        for ext in ("pdf", "png", "json"):
            path = next(p for p in result.paths if p.name == f"{stem}.{ext}")
            assert path.stat().st_size > 1000 or ext == "json"
        image = imread(result.paths[[p.name for p in result.paths].index(f"{stem}.png")])
        assert image.shape[0] > 300 and image.shape[1] > 500 and image[..., :3].std() > 0.05  # not blank
        record = json.loads(next(p for p in result.paths if p.name == f"{stem}.json").read_text())
        assert record["made_from"] == versions and record["code_version"]


def test_fig5_means_and_stds_match_the_repetitions(lab, tmp_path):
    _, ds = lab
    df = ds["experiment1"]
    versions = {"experiment1": ds["experiment1_version"]}
    result = vsl_figures.fig5(df, tmp_path, versions, n=N)
    _files_ok(result, ["fig5"], versions)
    curve = result.data["curve"]
    assert set(curve) == {25.0, 75.0} and set(curve[75.0]) == {"servo", "rigid", 0.5, 1.5}
    xs = ["x_0", "x_1", "x_2"]
    for line, plan in ((0.5, "vsl-0.5bar"), (1.5, "vsl-1.5bar"), ("rigid", "vsl_rigid")):
        mean, std, reps = _mean_std(df[df["plan"] == f"experiment1/curve/{plan}/75g"], xs, N)
        np.testing.assert_allclose(curve[75.0][line]["mean"], mean, atol=1e-12)
        np.testing.assert_allclose(curve[75.0][line]["std"], std, atol=1e-12)
        assert curve[75.0][line]["repetitions"] == reps == 2
    servo = _mean_std(df[df["plan"].str.endswith("/25g")], ["fk_0", "fk_1", "fk_2"], N)
    np.testing.assert_allclose(curve[25.0]["servo"]["mean"], servo[0], atol=1e-12)
    assert servo[2] == 6  # three arms × two repetitions pooled
    # the soft arm at low pressure and heavy payload sags below the rigid arm, which follows the servos
    sag = {
        k: (curve[75.0]["servo"]["mean"][:, 2] - curve[75.0][k]["mean"][:, 2]).mean() for k in (0.5, "rigid")
    }
    assert sag[0.5] > sag["rigid"] + 2e-3 and abs(sag["rigid"]) < 3e-3


def test_fig6_forward_prediction_is_the_models_on_the_rows(lab, tmp_path):
    _, ds = lab
    df, model = ds["experiment1"], ds["forward"]
    versions = {"experiment1": ds["experiment1_version"], "forward": "forward@test"}
    result = vsl_figures.fig6(df, model, tmp_path, versions, n=N)
    _files_ok(result, ["fig6"], versions)
    assert list(result.data) == ["25g/1.5bar", "75g/0.5bar"]
    rows = df[df["plan"] == "experiment1/curve/vsl-0.5bar/75g"]
    pred = model.predict(rows[list(FORWARD_INPUTS)].to_numpy(np.float32))
    rows = rows.assign(h_0=pred[:, 0], h_1=pred[:, 1], h_2=pred[:, 2])
    lines = result.data["75g/0.5bar"]
    for line, cols in (("forward", ["h_0", "h_1", "h_2"]), ("actual", ["x_0", "x_1", "x_2"]),
                       ("model", ["fk_0", "fk_1", "fk_2"])):  # fmt: skip
        mean, std, _ = _mean_std(rows, cols, N)
        np.testing.assert_allclose(lines[line]["mean"], mean, atol=1e-9)
        np.testing.assert_allclose(lines[line]["std"], std, atol=1e-9)
    gap = {
        k: np.linalg.norm(lines[k]["mean"] - lines["actual"]["mean"], axis=1).mean()
        for k in ("model", "forward")
    }
    assert gap["forward"] < gap["model"]  # the hybrid forward model predicts the sagging tip better
    with pytest.raises(ValueError, match="no curve rows"):
        vsl_figures.fig6(df, model, tmp_path, versions, cases=((100, 2.0),))


def test_fig7_paths_boxes_and_path_errors(lab, tmp_path):
    _, ds = lab
    df = ds["experiment2"]
    versions = {"experiment2": ds["experiment2_version"]}
    result = vsl_figures.fig7(df, tmp_path, versions, n=N)
    _files_ok(result, ["fig7a", "fig7b"], versions)
    vsl = load_robot("vsl")
    desired = trajectories.experiment1("curve", experiments.arm_lengths(vsl), 0.02, 400).x
    np.testing.assert_allclose(result.data["desired"], desired)
    lines = result.data["paths"]["75g/0.5bar"]
    assert set(lines) == {"ik", "static", "static/commanded"}
    static = df[df["plan"] == "experiment2/curve/vsl-0.5bar/75g/static"]
    commanded = kinematics.vsl_fk(static[["qc_0", "qc_1", "qc_2"]].to_numpy(), experiments.arm_lengths(vsl))
    static_c = static.assign(c_0=commanded[:, 0], c_1=commanded[:, 1], c_2=commanded[:, 2])
    np.testing.assert_allclose(
        lines["static/commanded"]["mean"], _mean_std(static_c, ["c_0", "c_1", "c_2"])[0]
    )
    np.testing.assert_allclose(lines["static"]["mean"], _mean_std(static, ["x_0", "x_1", "x_2"])[0])
    boxes = {b["label"].split("\n")[1]: b for b in result.data["boxes"]}
    assert list(boxes) == ["VSL ik", "VSL static", "rigid ik"]
    plans = {
        "VSL ik": "vsl-0.5bar/75g/ik",
        "VSL static": "vsl-0.5bar/75g/static",
        "rigid ik": "vsl_rigid/75g/ik",
    }
    table = vsl_paths.path_errors(df)
    for label, plan in plans.items():
        rows = df[df["plan"] == f"experiment2/curve/{plan}"]
        e = trajectories.distance_to_path(rows[["x_0", "x_1", "x_2"]].to_numpy(), desired)
        b = boxes[label]
        np.testing.assert_allclose([b["q1"], b["med"], b["q3"]], np.percentile(e, [25, 50, 75]))
        assert (b["whislo"], b["whishi"], b["mean"], b["n"]) == (
            e.min(),
            e.max(),
            pytest.approx(e.mean()),
            len(e),
        )
        row = table[table["session"] == rows["session"].iloc[0]].iloc[0]
        np.testing.assert_allclose(
            row[["mean_mm", "median_mm", "p95_mm", "max_mm"]].to_numpy(float),
            1e3 * np.array([e.mean(), np.median(e), np.percentile(e, 95), e.max()]),
        )
    assert boxes["VSL static"]["mean"] < 0.5 * boxes["VSL ik"]["mean"]  # compensation helps the soft arm
