"""A dataset's provenance (``meta/mmf_rl_recording.json``): read back, refused when damaged, described."""

from __future__ import annotations

import json

import pytest

from mmf_rl.datasets.provenance import PROVENANCE_FILE, describe_provenance, read_recording_provenance

SCRIPTED = {
    "episodes": 300,
    "seed": 0,
    "image_size": 64,
    "steps": 50,
    "camera": "front",
    "faults": False,
    "exploration": 0.0,
    "steady": True,
    "vcodec": "libsvtav1",
    "repo_id": "local/mmf-push",
    "policy": None,
    "mmf_rl_version": "0.1.0",
}


def write(root, text: str) -> None:
    (root / PROVENANCE_FILE).parent.mkdir(parents=True, exist_ok=True)
    (root / PROVENANCE_FILE).write_text(text)


def test_a_dataset_without_the_file_has_no_provenance(tmp_path):
    assert read_recording_provenance(tmp_path) is None


def test_the_file_reads_back(tmp_path):
    write(tmp_path, json.dumps(SCRIPTED))
    assert read_recording_provenance(tmp_path) == SCRIPTED


@pytest.mark.parametrize("text, found", [("{not json", "not valid JSON"), ("[1, 2]", "a JSON list")])
def test_a_damaged_file_is_an_error_naming_it_and_the_fix(tmp_path, text, found):
    write(tmp_path, text)
    with pytest.raises(ValueError) as refused:
        read_recording_provenance(tmp_path)
    message = str(refused.value)
    assert str(tmp_path / PROVENANCE_FILE) in message and found in message
    assert "delete it" in message and "\n" not in message


def test_the_description_says_who_acted_and_how():
    steady = describe_provenance(SCRIPTED)
    assert steady.startswith(
        "recorded by mmf-rl record: 300 episodes of 50 steps, seed 0, steady scripted pusher"
    )
    assert "no faults" in steady and "front camera 64 px" in steady
    drawn = describe_provenance({**SCRIPTED, "steady": False, "faults": True})
    assert "scripted pusher, a style drawn per episode" in drawn and "steady" not in drawn
    assert ", faults," in drawn
    by_policy = describe_provenance({**SCRIPTED, "steady": False, "policy": "MPC on the world model runs/wm"})
    assert "policy MPC on the world model runs/wm" in by_policy and "pusher" not in by_policy


def test_a_merge_is_described_source_by_source():
    merged = describe_provenance({"merged": [SCRIPTED, None]})
    assert merged.startswith("merged by mmf-rl record from 2 recordings: (1) 300 episodes")
    assert merged.endswith("; (2) unknown") and "\n" not in merged
