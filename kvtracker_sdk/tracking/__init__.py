"""Layer 5, the SDK's brain: ``Tracker`` (``tracker.py``) over the state table (``states``),
keyframe policies (``keyframes``), world-frame continuity (``gauge``), confidence (``quality``),
events (``events``), frame validation (``frame_input``) and rebuilds (``map_keeper``,
``map_builder``, ``mapper``).

``Tracker`` is loaded on first access, so importing a small module of this package (the state
table, say) does not import the tracker and its dependencies.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.tracking.tracker import Tracker

__all__ = ["Tracker"]


def __getattr__(name: str) -> Any:
    if name == "Tracker":
        return importlib.import_module("kvtracker_sdk.tracking.tracker").Tracker
    raise AttributeError(f"module 'kvtracker_sdk.tracking' has no attribute {name!r}")
