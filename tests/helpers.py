"""Helpers shared by tests (importable as ``tests.helpers``)."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = PROJECT_ROOT.parent / "shared"


def shared_path(*parts: str) -> Path:
    """Path inside ``../shared``; skips the test (fails under CI=true) if it is missing."""
    path = SHARED_DIR.joinpath(*parts)
    if not path.exists():
        message = f"{path} is missing: tests that read ../shared need it beside the checkout"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " (CI=true: this is a failure, not a skip)")
        pytest.skip(message)
    return path


def dev_dependency(module: str) -> ModuleType:
    """Import a development-only dependency (evo, plyfile); skip without it, fail under CI=true.

    CI installs the ``[dev]`` extra, so a missing module there is a broken install, and the
    cross-checks that need it must not go green by skipping.
    """
    if os.environ.get("CI", "").lower() == "true":
        try:
            return importlib.import_module(module)
        except ImportError as exc:
            pytest.fail(f"{module} is missing under CI=true (is it in the [dev] extra?): {exc}")
    return pytest.importorskip(module)
