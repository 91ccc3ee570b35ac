"""The CLI's logging: the one place in the SDK that configures logging handlers.

The library logs through ``kvtracker_sdk.log.get_logger``: structlog key/values carried on stdlib
``LogRecord``s under the ``kvtracker_sdk`` logger, silent by default. Here a handler on that logger
renders them with structlog's ``ProcessorFormatter``: readable ``key=value`` lines through the rich
console (so they print above a live progress bar instead of tearing it), or, with ``--log-json``,
one JSON object per line on stderr for log collectors.

Levels: ``-q`` errors only; default warnings; ``-v`` info (state changes, keyframes, map saves);
``-vv`` debug (one line per frame with its timings).
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from typing import Any

import structlog
from rich.console import Console

__all__ = ["CliState", "configure_logging", "level_for"]

_PACKAGE_LOGGER = "kvtracker_sdk"
_HANDLER_NAME = "kvtracker-cli"


@dataclass
class CliState:
    """Global options shared by every command (stored as the root click context's ``obj``)."""

    verbosity: int = 0  # -v count minus -q count
    log_json: bool = False
    console: Console = field(default_factory=lambda: Console(stderr=True))

    @property
    def quiet(self) -> bool:
        return self.verbosity < 0

    @property
    def chatty(self) -> bool:
        """Human-only stderr output (progress bar, notes) is wanted: not -q, not --log-json
        (stderr then carries JSON lines only)."""
        return not (self.quiet or self.log_json)


def level_for(verbosity: int) -> int:
    """Stdlib level of a -v/-q count: -1 ERROR, 0 WARNING, 1 INFO, >=2 DEBUG."""
    if verbosity < 0:
        return logging.ERROR
    return (logging.WARNING, logging.INFO)[verbosity] if verbosity < 2 else logging.DEBUG


class _ConsoleHandler(logging.Handler):
    """Writes formatted records through a rich console (cooperates with live displays)."""

    def __init__(self, console: Console) -> None:
        super().__init__()
        self.console = console

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.console.print(self.format(record), markup=False, highlight=False, soft_wrap=True)
        except Exception:  # logging must never break the run (stdlib convention)
            self.handleError(record)


def configure_logging(state: CliState) -> logging.Handler:
    """Attach the CLI's handler to the ``kvtracker_sdk`` logger (replacing an earlier one).

    Idempotent, so that several invocations in one process (tests, notebooks) do not stack
    handlers. Records of other libraries are left to their own configuration.
    """
    pre_chain: list[Any] = [
        structlog.stdlib.ExtraAdder(),  # the library's key/values travel in LogRecord extras
        structlog.stdlib.add_log_level,
        structlog.stdlib.add_logger_name,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    renderer: Any
    if state.log_json:
        handler: logging.Handler = logging.StreamHandler(sys.stderr)
        renderer = structlog.processors.JSONRenderer()
        pre_chain.append(structlog.processors.format_exc_info)
    else:
        handler = _ConsoleHandler(state.console)
        renderer = structlog.dev.ConsoleRenderer(colors=state.console.is_terminal)
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, renderer],
            foreign_pre_chain=pre_chain,
        )
    )
    handler.set_name(_HANDLER_NAME)
    logger = logging.getLogger(_PACKAGE_LOGGER)
    for old in [h for h in logger.handlers if h.get_name() == _HANDLER_NAME]:
        logger.removeHandler(old)
    logger.addHandler(handler)
    logger.setLevel(level_for(state.verbosity))
    logger.propagate = False  # the CLI owns this output; no duplicates through the root logger
    return handler
