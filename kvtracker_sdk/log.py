"""Structured logging that stays silent unless the app configures stdlib logging.

The library never calls ``structlog.configure`` (that is global state belonging to the app).
Instead each module wraps a stdlib logger under the ``kvtracker_sdk`` namespace: events become
stdlib ``LogRecord``s whose ``extra`` carries the key/value pairs, and a ``NullHandler`` on the
package logger keeps the library quiet by default. The CLI (or an app) attaches handlers and
formatters; ``structlog.stdlib.ProcessorFormatter`` renders the key/values there.
"""

from __future__ import annotations

import logging
from typing import Any

import structlog

__all__ = ["get_logger"]

_ROOT = "kvtracker_sdk"
logging.getLogger(_ROOT).addHandler(logging.NullHandler())

_PROCESSORS: list[Any] = [
    structlog.stdlib.filter_by_level,  # cheap early exit when the level is disabled
    structlog.stdlib.add_log_level,
    structlog.processors.TimeStamper(fmt="iso", utc=True),
    structlog.stdlib.render_to_log_kwargs,  # event -> msg, key/values -> extra
]


def get_logger(name: str) -> Any:
    """A structlog logger bound to the stdlib logger ``name`` (kept under ``kvtracker_sdk``)."""
    if not name.startswith(_ROOT):
        name = f"{_ROOT}.{name}"
    return structlog.wrap_logger(
        logging.getLogger(name),
        processors=_PROCESSORS,
        wrapper_class=structlog.stdlib.BoundLogger,
    )
