"""SIGKILL during `mmf-rl record`: the partial output is never read as a dataset and is cleaned next time."""

import logging
import tempfile
from pathlib import Path

import pytest

from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.record import RecordConfig, partial_prefix, record
from mmf_rl.temp_dirs import owned_temp_prefix
from tests.reliability.conftest import background, cli_command, wait_for


@pytest.mark.slow
def test_killed_recording_is_never_read_and_the_next_recording_removes_it(tmp_path, caplog):
    out = tmp_path / "push"
    partials = lambda: sorted(tmp_path.glob(f"{partial_prefix(out)}*"))  # noqa: E731
    command = cli_command(
        "record", "--out", str(out), "--episodes", "30", "--steps", "10", "--image-size", "32"
    )
    with background(command) as process:
        # Mid-way: at least one episode encoded, many to go.
        wait_for(lambda: any(p.rglob("*.mp4") for p in partials()), process, 300, "a recorded episode")
        process.kill()
        process.wait()
    assert not out.exists()
    [partial] = partials()
    assert f"-{process.pid}-" in partial.name, (
        "the temp dir names its owner, so a later run can tell it is dead"
    )
    with pytest.raises(FileNotFoundError, match="does not exist"):
        WindowDataset(
            DataConfig.from_dict(
                {
                    "root": str(out),
                    "cache_dir": str(tmp_path / "cache"),
                    "modalities": {"force": "observation.force"},
                    "target": {"feature": "observation.object_pose"},
                }
            )
        )

    # A recording in progress beside the same --out (here: this live process) is left alone.
    live = Path(tempfile.mkdtemp(prefix=owned_temp_prefix(partial_prefix(out)), dir=tmp_path))
    with caplog.at_level(logging.INFO, logger="mmf_rl"):
        record(RecordConfig(out=out, episodes=1, steps=3, image_size=32))
    assert f"removed {partial}" in caplog.text
    assert partials() == [live]
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    assert LeRobotDataset("local/mmf-push", root=out).num_frames == 3
