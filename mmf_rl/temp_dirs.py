"""Temp dirs named after the process that writes them, so a later run can remove those a killed
writer left behind and never one that is still being written.

A temp dir is named ``<prefix><pid>-<host>-<random>`` (`owned_temp_prefix`): a process on the same
host whose PID is gone left it for good. It sits beside what it becomes (the same file system),
so the finished result is renamed into place and a killed writer never leaves a half-written one.
The window cache's builds and the sharded dataset writers (`staging_dir`) name theirs this way.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

logger = logging.getLogger(__name__)

# A temp dir of another host (a shared directory) or of an unknown owner is stale once nothing
# in it has been written for this long; a live writer writes continuously. One of this host
# whose PID is alive is stale only after a day without writes (the PID was reused).
STALE_AGE_S = 3600
STALE_REUSED_PID_AGE_S = 24 * 3600


class StagingError(OSError):
    """A staging dir that could not be created; the message names the directory and the fix."""


def _host() -> str:
    """This host's name as it appears in temp dir names (no '-', which separates the fields)."""
    return re.sub(r"[^A-Za-z0-9_.]", "_", socket.gethostname())


def owned_temp_prefix(prefix: str) -> str:
    """``prefix`` followed by this process's PID and host, which `remove_stale_temp_dirs` reads back."""
    return f"{prefix}{os.getpid()}-{_host()}-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, owned by another user
        return True
    return True


def _last_write(directory: Path) -> float:
    times = [directory.stat().st_mtime]
    for parent, _, files in os.walk(directory):
        times.extend(os.stat(os.path.join(parent, f)).st_mtime for f in files)
    return max(times)


def is_stale(directory: Path, prefix: str) -> bool:
    """A temp dir whose writer is gone (same host) or that has not been written for long."""
    owner = re.match(rf"{re.escape(prefix)}(\d+)-([^-]+)-", directory.name)
    idle = time.time() - _last_write(directory)
    if owner is not None and owner[2] == _host():
        return not _pid_alive(int(owner[1])) or idle > STALE_REUSED_PID_AGE_S
    # Another host's writer (no PID to ask), or one named before PIDs were recorded.
    return idle > STALE_AGE_S


def remove_stale_temp_dirs(parent: Path, prefix: str) -> list[Path]:
    """Delete the ``prefix*`` dirs in ``parent`` that killed writers left behind (never a live
    one's); return them. Their names come from `owned_temp_prefix`."""
    removed = []
    if not parent.is_dir():
        return removed
    for directory in parent.glob(f"{glob.escape(prefix)}*"):
        try:
            stale = directory.is_dir() and is_stale(directory, prefix)
        except FileNotFoundError:  # removed meanwhile by its writer or another cleaner
            continue
        if stale:
            shutil.rmtree(directory, ignore_errors=True)
            removed.append(directory)
    return removed


@contextlib.contextmanager
def staging_dir(parent: Path, prefix: str, fix: str) -> Iterator[Path]:
    """A new temp dir ``parent/<prefix><pid>-<host>-*`` (``parent`` created if missing), removed
    with all it holds on exit, however the ``with`` block ends; those that killed writers left in
    ``parent`` are removed first. Unwritable ``parent``: `StagingError` ending with ``fix``."""
    for stale in remove_stale_temp_dirs(parent, prefix):
        logger.info("removed %s, left by a writer that is no longer running", stale)
    try:
        parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=owned_temp_prefix(prefix), dir=parent))
    except OSError as error:
        raise StagingError(f"cannot write in {parent} ({error.strerror}); {fix}") from None
    try:
        yield work
    finally:
        shutil.rmtree(work, ignore_errors=True)
