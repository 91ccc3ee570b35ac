"""``Segmenter``: how an app plugs its own segmentation model (SAM 2, an on-device network) into
object mode.

Object mode needs the object's pixels in every frame. Without a segmenter the tracker uses the
region it predicts from the map (``object_region``); with one, it asks the segmenter first, giving
it the frame and that predicted region as a prompt (a box, a context box and a coarse mask), and
uses the mask it returns. A KV-Tracker-style system runs SAM 2 beside the tracker this way.

The contract is one method; anything with it qualifies (no base class, no registration)::

    class MySegmenter:
        def segment(self, image: np.ndarray, prompt: ObjectRegion) -> np.ndarray | None:
            ...  # bool [H, W] mask of the object in ``image``, or None: "use the prediction"

It runs on the thread of ``push_frame`` (or the live worker), inside the tracker's frame step, so
its time adds to the frame's (``FrameResult.timings_ms["segment"]``). A segmenter that raises, or
returns a mask of the wrong shape or with no pixel, is logged as a warning and the frame goes on
with the predicted region: an app's model must not stop tracking. A sketch of a SAM 2 adapter is
in ``docs/object_tracking.md``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from kvtracker_sdk.errors import MaskError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking.core.object_masks import check_mask
from kvtracker_sdk.types import ObjectRegion

__all__ = ["Segmenter", "ask_segmenter"]

_log = get_logger(__name__)


@runtime_checkable
class Segmenter(Protocol):
    """Turns a frame and a predicted region into the object's mask (see the module docstring)."""

    def segment(self, image: np.ndarray, prompt: ObjectRegion) -> np.ndarray | None:
        """bool/int [H, W] mask (non-zero = object) of ``image`` ([H, W, 3] RGB as pushed), or
        None to use ``prompt`` (the predicted region) as it is."""
        ...


def ask_segmenter(
    segmenter: Segmenter, image: np.ndarray, prompt: ObjectRegion, index: int
) -> np.ndarray | None:
    """The segmenter's checked bool [H, W] mask for frame ``index``, or None (it declined,
    failed or answered with an unusable mask: logged)."""
    try:
        answer = segmenter.segment(image, prompt)
    except Exception as exc:  # the app's code: never stops the frame loop
        _log.warning("segmenter failed; using the predicted region", frame_index=index,
                     error=f"{type(exc).__name__}: {exc}")
        return None
    if answer is None:
        return None
    try:
        return check_mask(answer, prompt.image_size)
    except MaskError as exc:
        _log.warning("segmenter mask unusable; using the predicted region", frame_index=index,
                     error=str(exc))
        return None
