"""Session metadata is schema-versioned JSON (acquisition/schemas/session_card.py): what a writer records
reads back the same, a version-1 session (parameters written by ``repr``) still reads, and a newer schema is
refused in one line."""

from __future__ import annotations

import json

import pytest

from acquisition.recorder.sessions import SessionError, read_card
from acquisition.recorder.writer import SessionWriter
from acquisition.schemas.session_card import (
    SCHEMA_VERSION,
    SessionCardError,
    as_metadata,
    session_parameters,
)
from models.robot import load_robot
from pipeline.ingest import ingest_session

PARAMETERS = {
    "experiment": "popup_static",
    "pressure_pa": 20_000.0,
    "order": [2, 0, 1],
    "box": {"min": [0, 1]},
}


def test_what_a_session_records_reads_back_from_its_card_and_its_parts(tmp_path):
    with SessionWriter(tmp_path, load_robot("vsl"), "s1", metadata={"parameters": PARAMETERS, "seed": 3}):
        pass
    card = read_card(tmp_path)
    assert card["schema_version"] == SCHEMA_VERSION == 2
    assert json.loads(card["parameters"]) == PARAMETERS and card["seed"] == "3"
    tables = ingest_session(tmp_path)
    assert tables.parameters == PARAMETERS  # the same through the pipeline, from the MCAP metadata


def test_version_one_metadata_still_reads():
    old = {"parameters": repr({"pressure_pa": 20_000.0, "order": (2, 0, 1)}), "robot": "popup"}
    assert session_parameters(old) == {"pressure_pa": 20_000.0, "order": (2, 0, 1)}
    assert session_parameters({"robot": "vsl"}) == {}
    # a v1 repr is read as literals only: nothing in it runs
    with pytest.raises(SessionCardError, match="unreadable parameters"):
        session_parameters({"parameters": "__import__('os').getcwd()"})


def test_v2_parameters_are_json_not_python():
    fields = as_metadata({"schema_version": 2, "parameters": {"a": (1, 2)}})
    assert fields == {"schema_version": "2", "parameters": '{"a": [1, 2]}'}
    assert session_parameters(fields) == {"a": [1, 2]}
    with pytest.raises(SessionCardError, match="unreadable parameters"):
        session_parameters({"schema_version": "2", "parameters": "{'a': 1}"})


def test_a_newer_schema_is_refused_in_one_line(tmp_path):
    with SessionWriter(tmp_path, load_robot("vsl"), "s1"):
        pass
    card = tmp_path / "session.json"
    card.write_text(card.read_text().replace('"schema_version": 2', '"schema_version": 3'))
    with pytest.raises(SessionError, match=r"session\.json: written by a newer vslab \(session schema 3"):
        read_card(tmp_path)


def test_a_version_one_card_reads_with_the_current_keys(tmp_path):
    with SessionWriter(tmp_path, load_robot("vsl"), "s1", experiment="campaign"):
        pass
    card = tmp_path / "session.json"
    old = json.loads(card.read_text())
    del old["schema_version"]
    old["protocol"] = old.pop("experiment")  # as vslab wrote it before schema 2
    card.write_text(json.dumps(old))
    assert read_card(tmp_path)["experiment"] == "campaign"
    assert "protocol" not in read_card(tmp_path)
