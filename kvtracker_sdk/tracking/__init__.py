"""Layer 5, the SDK's brain: ``Tracker`` (``facade/``: the tracker and its member groups) over
subpackages by concern, in the order ``pyproject.toml``'s import contract enforces (each imports only those below it):

* ``live`` and ``persistence``: live intake on a worker thread; the tracker's side of map files;
* ``loop``: the per-frame loop and the tracking state table;
* ``mapping`` and ``world``: the keyframe map and its rebuilds; the map's world frame and scale;
* ``object``: object mode (the object's region per frame, the object model);
* ``core``: frame validation, intrinsics, confidence, world-frame continuity, events.

``Tracker`` is loaded on first access, so importing a small module of this package (the state
table, say) does not import the tracker and its dependencies.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["Tracker"]


def __getattr__(name: str) -> Any:
    if name == "Tracker":
        return importlib.import_module("kvtracker_sdk.tracking.facade.tracker").Tracker
    raise AttributeError(f"module 'kvtracker_sdk.tracking' has no attribute {name!r}")
