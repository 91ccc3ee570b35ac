"""Track an object with a mask per frame (from any segmenter), or with just a bounding box.

    python examples/object_masks.py                      # offline: a simulated camera around a ball
    python examples/object_masks.py --box                # the same with boxes instead of masks
    python examples/object_masks.py --weights pi3.safetensors --source frames/ --masks masks/

In object mode the tracker sees only the object (the background is blacked out, or the frame is
cropped around it: ``TrackerConfig(object={"preprocessing": "crop"})``), so the world frame moves
with the object, and a keyframe is added whenever the camera's view direction around the object
changes by more than ``keyframing.view_angle_deg`` (10 degrees) from every keyframe's.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kvtracker_sdk import Backend, Camera, TrackerConfig
from kvtracker_sdk.runs import open_tracker

# (RGB uint8 [H, W, 3], timestamp s, bool mask [H, W] or None, box (x0, y0, x1, y1) or None)
Frames = Iterator[tuple[np.ndarray, float, np.ndarray | None, tuple[float, ...] | None]]


@dataclass(frozen=True)
class Outcome:
    frames: int
    valid_poses: int
    keyframe_frames: list[int]  # source frame of each keyframe, in order


def box_of(mask: np.ndarray) -> tuple[float, float, float, float]:
    """The tight box (x0, y0, x1, y1) around a mask's pixels."""
    rows, cols = np.nonzero(mask)
    return float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1)


def simulated(frames: int, use_box: bool) -> tuple[Backend, Frames, None]:
    """A camera orbiting a ball: ground-truth masks (as a segmenter would give) or their boxes."""
    from kvtracker_sdk import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    backend = SimulatedBackend(orbit(frames, turns=frames / 360), seed=5)  # 1 degree per frame
    rendered = backend.frames((240, 320), textured=False, with_mask=True)
    if use_box:
        return backend, ((f.image, f.timestamp, None, box_of(f.mask)) for f in rendered), None
    return backend, ((f.image, f.timestamp, f.mask, None) for f in rendered), None


def real(weights: str, source: str, masks: str, frames: int) -> tuple[Backend, Frames, Camera | None]:
    """The PyTorch backend, frames of a sequence and the mask images of a folder (same order),
    and the sequence's camera when its dataset publishes one."""
    import cv2

    from kvtracker_sdk.runs import open_backend, open_input

    run_input = open_input(source)
    mask_files = sorted(p for p in Path(masks).iterdir() if p.is_file())
    pairs = zip(run_input.source, mask_files, range(frames), strict=False)
    stream = ((f.image, f.timestamp, cv2.imread(str(m), cv2.IMREAD_GRAYSCALE) > 0, None)
              for f, m, _ in pairs)
    return open_backend("torch", weights), stream, run_input.camera


def main(argv: list[str] | None = None) -> Outcome:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=180, help="frames to run")
    parser.add_argument("--box", action="store_true", help="track with boxes instead of masks")
    parser.add_argument("--weights", help="a Pi3 .safetensors checkpoint (default: simulated)")
    parser.add_argument("--source", help="with --weights: the frames")
    parser.add_argument("--masks", help="with --weights: one mask image per frame (same order)")
    args = parser.parse_args(argv)
    if args.weights and not (args.source and args.masks):
        parser.error("--weights needs --source and --masks")

    if args.weights:
        backend, frames, camera = real(args.weights, args.source, args.masks, args.frames)
        config = TrackerConfig(mode="object", resolution=224)
    else:
        backend, frames, camera = simulated(args.frames, args.box)
        config = TrackerConfig(mode="object")

    count, valid, keyframe_frames = 0, 0, []
    with open_tracker(config, backend, camera=camera) as tracker:
        tracker.events.on_keyframe(lambda event: keyframe_frames.append(event.frame_index))
        for image, timestamp, mask, box in frames:
            result = tracker.push_frame(image, timestamp=timestamp, mask=mask, bbox=box)
            count += 1
            valid += result.pose_valid
    backend.close()

    spacing = np.diff(keyframe_frames)
    print(f"{count} frames, {valid} valid poses, {len(keyframe_frames)} keyframes at frames "
          f"{keyframe_frames}" + (f" (every {spacing.mean():.0f} frames)" if len(spacing) else ""))
    return Outcome(count, valid, keyframe_frames)


if __name__ == "__main__":
    main()
