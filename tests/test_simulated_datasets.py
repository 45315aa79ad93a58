"""Experiments simulated side by side and built (``pipeline.simulated``): what the main job, the unmodelled
study and pretraining make their datasets with."""

from __future__ import annotations

import pytest

from pipeline.lab import Lab
from pipeline.simulated import TwinExperiment, simulated_dataset, simulated_datasets

SMALL_CAMPAIGN = {"points": 60}
ONE_PATH = {"trajectories": ["linear"], "payloads_g": [25], "pressures_bar": [1.0], "repetitions": 1,
            "rigid_arm": False}  # fmt: skip


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A campaign and Experiment 1 built (Experiment 1 borrowing the registration of the campaign the same
    call built) and the POPUP deployment simulated beside them, not built; the phases as they were called."""
    lab = Lab(tmp_path_factory.mktemp("simulated") / "lab")
    phases: list[str] = []
    experiments = [
        TwinExperiment("campaign", SMALL_CAMPAIGN, dataset="campaign"),
        TwinExperiment("experiment1", ONE_PATH, dataset="experiment1", registration_from="campaign"),
        TwinExperiment("popup_deploy"),
    ]
    reports = simulated_datasets(lab, experiments, seed=4, phase=phases.append)
    return lab, reports, phases


def test_each_experiment_naming_a_dataset_is_built_in_order_and_the_others_only_simulated(made):
    lab, (campaign, experiment1, deploy), phases = made
    assert deploy is None
    assert phases == ["simulated", "campaign", "experiment1"]
    assert campaign.built and experiment1.built and campaign.rows == 60
    assert sorted(lab.datasets.resolve(n)[1] for n in ("campaign", "experiment1")) == sorted(
        [campaign.version, experiment1.version]
    )
    made = {lab.sessions.card(d).get("experiment") for d in lab.sessions.root.iterdir()}
    assert made == {"campaign", "experiment1", "popup_deploy"}  # the deployment simulated all the same


def test_a_registration_borrowed_from_a_dataset_the_same_call_built_is_pinned_to_that_version(made):
    lab, (campaign, experiment1, _), _ = made
    _, card = lab.datasets.load("experiment1", experiment1.version, table=None)
    assert card["parameters"]["registration"]["from_dataset"] == f"campaign@{campaign.version}"
    # only the sessions of its own plans: none of the campaign's or the deployment's
    assert all(s.startswith("sim-experiment1-") for s in card["made_from"])


def test_a_second_call_keeps_every_session_and_version(made):
    lab, (campaign, _, _), _ = made
    again = simulated_datasets(lab, [TwinExperiment("campaign", SMALL_CAMPAIGN, dataset="campaign")], seed=4)
    assert again[0].version == campaign.version and not again[0].built


def test_one_experiment_must_name_its_dataset(tmp_path):
    with pytest.raises(ValueError, match="names no dataset"):
        simulated_dataset(Lab(tmp_path), TwinExperiment("popup_deploy"))
