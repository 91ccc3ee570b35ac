"""Run the ``kvtracker`` app in-process and leave no global state behind."""

from __future__ import annotations

import logging
import sys

from typer.testing import CliRunner, Result

from kvtracker_sdk.cli.app import app


def invoke(*args: object) -> Result:
    """``kvtracker ARGS`` through typer's runner (stdout and stderr captured separately).

    Afterwards the CLI's log handler is removed and torch's thread count restored: ``--threads``
    and the logging setup are process-wide, as they should be in a real CLI process.
    """
    threads = sys.modules["torch"].get_num_threads() if "torch" in sys.modules else None
    try:
        return CliRunner().invoke(app, [str(a) for a in args])
    finally:
        logger = logging.getLogger("kvtracker_sdk")
        for handler in [h for h in logger.handlers if h.get_name() == "kvtracker-cli"]:
            logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
        logger.propagate = True
        if threads is not None:
            sys.modules["torch"].set_num_threads(threads)
