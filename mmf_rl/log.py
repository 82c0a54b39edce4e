"""Where the ``mmf_rl`` loggers' records go: :func:`configure_logging` sends them to stderr.

The lowest layer, so that any entry point (the CLI, a comparison's worker process, a benchmark
script) sets logging up the same way without importing the layers above it.
"""

from __future__ import annotations

import logging
import sys

from tqdm.auto import tqdm

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class _ProgressSafeHandler(logging.Handler):
    """Writes each record to the current ``sys.stderr`` through ``tqdm.write``, so that a message
    does not tear a progress bar drawn there."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:
            self.handleError(record)


def configure_logging(level: int | None = None) -> None:
    """Show the ``mmf_rl`` loggers' records of ``level`` and above on stderr (other libraries'
    logging is left as it is). Calling it again only changes the level; ``None`` is INFO, or the
    level of an earlier call (a benchmark script run by ``mmf-rl bench`` keeps the CLI's)."""
    logger = logging.getLogger("mmf_rl")
    configured = any(isinstance(handler, _ProgressSafeHandler) for handler in logger.handlers)
    if level is not None or not configured:
        logger.setLevel(logging.INFO if level is None else level)
    if not configured:
        handler = _ProgressSafeHandler()
        handler.setFormatter(logging.Formatter(LOG_FORMAT, datefmt="%H:%M:%S"))
        logger.addHandler(handler)
        _root_handler_without_mmf_rl()


def _root_handler_without_mmf_rl() -> None:
    """A library that logs on the root logger (``logging.info(...)``, as some of lerobot does) makes
    Python give the root a default handler, which would print every ``mmf_rl`` record a second
    time: give it that default handler now, minus the records the ``mmf_rl`` handler prints. A root
    logger already configured (by the user, or pytest) is left as it is."""
    root = logging.getLogger()
    if root.handlers:
        return
    logging.basicConfig()
    for handler in root.handlers:
        handler.addFilter(lambda record: record.name != "mmf_rl" and not record.name.startswith("mmf_rl."))
