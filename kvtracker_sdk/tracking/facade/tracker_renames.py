"""The ``Tracker`` members renamed when its API was grouped (``events``, ``live``, ``object``,
``world``, ``export``, the ``camera`` property): the old spellings keep working for one release,
each access warning with the new one.

``RENAMED`` is the one table; ``Tracker.__getattr__`` (reached only for names the class does
not define, so the old names stay out of ``dir()``) resolves an old name through it. Removing
the old names next release: delete this module and that ``__getattr__``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from types import MappingProxyType
from typing import Any

__all__ = ["RENAMED", "renamed_member"]

_ASSIGNED = " = ..."  # the new spelling assigns a property: the old name was its set_ method

# old name -> the new spelling, relative to the tracker
RENAMED = MappingProxyType({
    "on_state_change": "events.on_state_change",
    "on_keyframe": "events.on_keyframe",
    "on_keyframe_rejected": "events.on_keyframe_rejected",
    "on_map_updated": "events.on_map_updated",
    "on_backend_failed": "events.on_backend_failed",
    "on_world_frame_changed": "events.on_world_frame_changed",
    "on_result": "events.on_result",
    "on_frame_error": "events.on_frame_error",
    "unregister": "events.unregister",
    "latest": "live.latest",
    "stats": "live.stats",
    "wait_idle": "live.wait_idle",
    "object_frame": "object.frame",
    "object_region": "object.region",
    "set_segmenter": "object.set_segmenter",
    "set_known_distance": "world.set_known_distance",
    "set_object_height": "world.set_object_height",
    "export_point_cloud": "export.point_cloud",
    "export_trajectory": "export.trajectory",
    "set_camera": "camera" + _ASSIGNED,
})


def renamed_member(tracker: Any, name: str) -> Any:
    """What the old ``tracker.<name>`` gave, found by its new spelling, with a
    ``DeprecationWarning`` naming that spelling; AttributeError for any other name."""
    new = RENAMED.get(name)
    if new is None:
        raise AttributeError(f"{type(tracker).__name__!r} object has no attribute {name!r}")
    warnings.warn(f"Tracker.{name} is deprecated and will be removed in the next release; "
                  f"use tracker.{new}", DeprecationWarning, stacklevel=3)
    if new.endswith(_ASSIGNED):
        return _setter(tracker, new.removesuffix(_ASSIGNED))
    value = tracker
    for part in new.split("."):
        value = getattr(value, part)
    return value


def _setter(tracker: Any, attribute: str) -> Callable[..., None]:
    """The old ``set_<attribute>(<attribute>)`` method: assigns its one argument."""

    def assign(*args: Any, **kwargs: Any) -> None:
        values = [*args, *kwargs.values()]
        if len(values) != 1 or set(kwargs) - {attribute}:
            raise TypeError(f"set_{attribute}() takes one argument, {attribute}")
        setattr(tracker, attribute, values[0])

    return assign
