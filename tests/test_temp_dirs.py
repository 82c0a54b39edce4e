"""Owned temp dirs: a staging dir is removed however its block ends, and the next one removes
those of dead writers only."""

import logging
import os
import subprocess
import sys

import pytest

from mmf_rl.temp_dirs import StagingError, owned_temp_prefix, staging_dir

PREFIX = ".out.partial-"


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", ""])
    process.wait()
    return process.pid


def test_a_staging_dir_is_named_after_its_owner_and_removed_however_its_block_ends(tmp_path):
    with staging_dir(tmp_path / "made", PREFIX, "choose another --out") as work:
        assert work.parent == tmp_path / "made" and work.is_dir()
        assert work.name.startswith(owned_temp_prefix(PREFIX)) and f"-{os.getpid()}-" in work.name
        (work / "shard-0").mkdir()
    assert list((tmp_path / "made").iterdir()) == []
    with pytest.raises(RuntimeError, match="boom"), staging_dir(tmp_path, PREFIX, "") as work:
        raise RuntimeError("boom")
    assert not work.exists()


def test_the_next_staging_removes_dead_writers_dirs_and_keeps_live_ones(tmp_path, caplog):
    host = owned_temp_prefix("").split("-")[1]
    dead = tmp_path / f"{PREFIX}{_dead_pid()}-{host}-left"
    live = tmp_path / f"{owned_temp_prefix(PREFIX)}running"
    other = tmp_path / ".other.partial-1-host-x"
    for directory in (dead, live, other):
        (directory / "shard-0").mkdir(parents=True)
    with caplog.at_level(logging.INFO, logger="mmf_rl"), staging_dir(tmp_path, PREFIX, "") as work:
        assert sorted(tmp_path.iterdir()) == sorted([live, other, work])
    assert f"removed {dead}" in caplog.text


def test_an_unwritable_parent_names_the_directory_and_the_fix(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    with (
        pytest.raises(StagingError) as raised,
        staging_dir(blocker / "out", PREFIX, "choose a writable --out"),
    ):
        pytest.fail("no staging dir under a file")
    assert (
        str(raised.value) == f"cannot write in {blocker / 'out'} (Not a directory); choose a writable --out"
    )
