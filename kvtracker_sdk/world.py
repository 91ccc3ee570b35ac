"""What the tracker's world frame measures in and which way is up: value types shared by every layer.

A monocular map has an arbitrary scale (the first mapping pass's) and arbitrary axes (keyframe 0's
camera). Three inputs make it an AR-ready world (``tracking/world/world_alignment.py`` applies them):

* depth frames registered to the colour frames (``push_frame(depth=...)``): the map's predicted
  depth is aligned to the sensor's at every keyframe, and the world is in metres;
* a known length (``tracker.world.set_object_height`` / ``set_known_distance``): the world is
  rescaled once so that the length measures what the app says;
* gravity (``push_frame(gravity=...)``): the world is rotated so that its z axis points up (its x
  axis is keyframe 0's viewing direction made horizontal, y = z x x: REP 103's x forward, y left,
  z up).

``MapWorld`` is what a map records (the map file's ``world`` header field); ``ScaleEstimate`` and
``GravityEstimate`` are what ``MapStatus`` reports per source.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["GravityEstimate", "MapWorld", "ScaleEstimate", "ScaleSource", "WorldAlignment"]


class ScaleSource(str, enum.Enum):
    """Where the world frame's unit comes from."""

    NONE = "none"  # the first mapping pass's arbitrary unit
    DEPTH = "depth"  # sensor depth frames, aligned at the keyframes (metres)
    KNOWN_SIZE = "known_size"  # a length the app stated (metres)


class WorldAlignment(str, enum.Enum):
    """Why a world frame was re-expressed (``WorldFrameChangedEvent.reason`` with a transform)."""

    METRIC_SCALE = "METRIC_SCALE"  # the world was rescaled to metres
    GRAVITY = "GRAVITY"  # the world was rotated so that its z axis points up


@dataclass(frozen=True)
class MapWorld:
    """The units and axes of a map's world frame (saved in map files; absent = the defaults).

    ``scale_source``: NONE (arbitrary units) or how the world became metric;
    ``scale_uncertainty``: relative 1-sigma of the metric scale when metric (None otherwise);
    ``gravity_aligned``: the world's z axis points up (to ``gravity_uncertainty_deg``, 1-sigma).
    """

    scale_source: ScaleSource = ScaleSource.NONE
    scale_uncertainty: float | None = None
    gravity_aligned: bool = False
    gravity_uncertainty_deg: float | None = None

    @property
    def metric(self) -> bool:
        """Whether world units are metres."""
        return self.scale_source is not ScaleSource.NONE

    @property
    def is_default(self) -> bool:
        """Arbitrary units and axes (what a map without the header field has)."""
        return self == MapWorld()

    def to_dict(self) -> dict[str, object]:
        return {
            "scale_source": self.scale_source.value,
            "scale_uncertainty": self.scale_uncertainty,
            "gravity_aligned": self.gravity_aligned,
            "gravity_uncertainty_deg": self.gravity_uncertainty_deg,
        }


@dataclass(frozen=True)
class ScaleEstimate:
    """One scale source's latest measurement of the world's unit.

    ``metres_per_unit``: what one unit of the world frame *as it is now* measures in metres by
    this source (about 1 once the world is metric by it; a second source checks the first);
    ``relative_uncertainty``: its 1-sigma relative error; ``samples``: what it rests on (valid
    depth pixels, or 1 per stated length); ``applied``: this source sets the world's scale;
    ``frame_index``: the latest frame it measured at (None: no frame, e.g. a loaded map).
    """

    source: ScaleSource
    metres_per_unit: float
    relative_uncertainty: float
    samples: int
    applied: bool
    frame_index: int | None = None


@dataclass(frozen=True)
class GravityEstimate:
    """The world's up direction as measured from the gravity readings so far.

    ``up``: unit [3] vector in the world frame (about (0, 0, 1) once ``aligned``);
    ``uncertainty_deg``: 1-sigma angular error of ``up``; ``tilt_deg``: the angle between ``up``
    and the world's z axis; ``samples``: readings averaged; ``aligned``: the world frame was
    rotated to it.
    """

    up: np.ndarray
    uncertainty_deg: float
    tilt_deg: float
    samples: int
    aligned: bool

    def __post_init__(self) -> None:
        up = np.array(self.up, dtype=np.float64, copy=True).reshape(3)
        up.setflags(write=False)
        object.__setattr__(self, "up", up)
