"""``tracker.export``: the map written out as files other tools read (a PLY point cloud, a TUM
trajectory).

A thin view over the tracker: it owns no state and no lock. Each export waits for the rebuilds
pending at the call (without the tracker's lock, so ``push_frame`` goes on) and writes that map
through ``persistence/tracker_maps.py``; StateError without a map.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from kvtracker_sdk.tracking.persistence import tracker_maps as persistence
from kvtracker_sdk.tracking.persistence.tracker_maps import PathLike

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["TrackerExport"]


class TrackerExport:
    """The map's exports (``tracker.export``)."""

    __slots__ = ("_tracker",)

    def __init__(self, tracker: Tracker) -> None:
        self._tracker = tracker

    def point_cloud(self, path: PathLike, **options: Any) -> int:
        """The map's fused, confidence-filtered point cloud as binary PLY (world frame); returns
        the point count. ``options``: ``min_confidence``, ``use_masks``, ``voxel_size``
        (``persistence.export_point_cloud``)."""
        return persistence.export_point_cloud(self._tracker._settled_map(), path, **options)

    def trajectory(self, path: PathLike) -> int:
        """The keyframes' world poses as a TUM trajectory; returns the number of poses."""
        return persistence.export_trajectory(self._tracker._settled_map(), path)
