"""SIGKILL during `mmf-rl import ethucy`: no dataset at --out, the workers end with their parent, and
the next conversion removes the staging dir and completes."""

import json
import logging
from pathlib import Path

import pytest

from mmf_rl.datasets import ethucy
from tests.datasets.conftest import SHARED_DATA, cut_ethucy_raw
from tests.reliability.conftest import background, cli_command, kill_parent_and_check_workers_end, wait_for

pytestmark = pytest.mark.skipif(
    not (SHARED_DATA / "ethucy" / "trajectories" / "all_data" / "biwi_eth.txt").is_file(),
    reason=f"ETH/UCY data not at {SHARED_DATA / 'ethucy'} (set MMF_RL_SHARED_DATA)",
)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``, from /proc."""
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        if int(fields[1]) == pid:
            children.append(int(stat.parent.name))
    return children


def _episodes(root: Path) -> int:
    """The episodes a dataset's info.json counts; 0 when a worker was stopped while lerobot rewrote
    it (lerobot writes it in place, so a killed write leaves it empty or cut)."""
    try:
        return json.loads((root / "meta" / "info.json").read_text())["total_episodes"]
    except json.JSONDecodeError:
        return 0


def _shards_started(out: Path) -> bool:
    """Both workers have created their shard dataset in the staging dir."""
    return len(list(out.glob(f"{ethucy.STAGING_PREFIX}*/shard-*/meta/info.json"))) == 2


@pytest.mark.slow
def test_killed_conversion_leaves_no_dataset_and_the_next_one_completes(tmp_path, caplog):
    raw, out = cut_ethucy_raw(tmp_path, steps=40, agents=8), tmp_path / "out"
    command = cli_command("import", "ethucy", str(raw), "--out", str(out), "--fold", "eth", "--workers", "2")
    with background(command) as process:
        wait_for(lambda: _shards_started(out), process, 300, "two started shards")
        workers = _children(process.pid)
        assert len(workers) >= 2
        kill_parent_and_check_workers_end(process, workers, "conversion")
    assert not (out / ethucy.DATASET_NAME).exists() and not (out / "eth.yaml").exists()
    [partial] = out.glob(f"{ethucy.STAGING_PREFIX}*")
    assert f"-{process.pid}-" in partial.name, "the staging dir names its owner"
    written = sum(_episodes(shard) for shard in partial.glob("shard-*"))

    with caplog.at_level(logging.INFO, logger="mmf_rl"):
        assert ethucy.convert(raw, ["eth"], out, workers=1) == [out / "eth.yaml"]
    assert f"removed {partial}" in caplog.text
    assert not list(out.glob(f"{ethucy.STAGING_PREFIX}*"))
    # The workers stopped with their parent, before writing every episode (they had just begun).
    assert written < _episodes(out / ethucy.DATASET_NAME)
