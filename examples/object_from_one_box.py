"""Track an object from one box: tap it once, the tracker finds it in every next frame.

    python examples/object_from_one_box.py                  # offline: a hand-held walk around a ball
    python examples/object_from_one_box.py --segmenter      # the same, with a (fake) SAM 2 plugged in
    python examples/object_from_one_box.py --weights pi3.safetensors --source frames/ \\
        --box 200,150,440,330                               # a real model, a box on the first frame

In object mode the first frame needs the object's mask or box. From the next frame on the tracker
projects the map's object points with the tracked pose and the camera intrinsics: each result
carries ``region`` (the object's box, a context box 50 px larger, a mask; HELD while tracking is
lost) and ``T_cam_object``, the object's frame (origin at its centre, axes of keyframe 0) in the
camera's — where an AR app draws content anchored to the object. ``tracker.object.frame.extent``
is an oriented box around the object's points. A ``Segmenter`` (SAM 2, an on-device model) can
refine each predicted region into a mask: see ``docs/object_tracking.md``.
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk import Backend, Camera, ObjectRegion, TrackerConfig
from kvtracker_sdk.runs import open_tracker

# (RGB uint8 [H, W, 3], timestamp s, the true box (x0, y0, x1, y1) if known)
Frames = Iterator[tuple[np.ndarray, float, tuple[float, float, float, float] | None]]


@dataclass(frozen=True)
class Outcome:
    frames: int
    sources: dict[str, int]  # how many frames' regions were given / predicted / segmented / held
    tracked_ious: list[float]  # box IoU with the truth on tracked frames (simulation only)
    anchor_in_view: bool  # the object's origin projects inside the last frame's region


def iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - ix * iy
    return ix * iy / union


class RenderedMaskSegmenter:
    """Stands in for SAM 2 in the simulation: answers the prompt with the renderer's true mask."""

    def __init__(self, camera: object) -> None:
        self.camera = camera
        self.frame = 0

    def segment(self, image: np.ndarray, prompt: ObjectRegion) -> np.ndarray | None:
        self.frame += 1  # frame 0 came with its box
        return self.camera.render(self.frame, with_mask=True).mask  # type: ignore[attr-defined]


def simulated(frames: int) -> tuple[Backend, Frames, RenderedMaskSegmenter]:
    """A hand-held walk around a ball (the demo's path), with the ball's true box per frame."""
    from kvtracker_sdk import SimulatedBackend
    from kvtracker_sdk.cli.demo_trajectory import handheld_orbit

    size = (240, 320)
    path = handheld_orbit(frames, turns=frames / 600)  # one turn in 20 s, as the demo walks
    backend = SimulatedBackend(path, seed=5, translation_noise_m=0.003)
    stream = ((f.image, f.timestamp, backend.scene.object_box(f.T_world_cam, size))
              for f in backend.frames(size, textured=False))
    return backend, stream, RenderedMaskSegmenter(backend.camera(size, textured=False))


def real(weights: str, source: str, frames: int) -> tuple[Backend, Frames, Camera | None]:
    """The PyTorch backend and the frames of a video, folder or TUM sequence, and the camera
    its dataset publishes (if any)."""
    from kvtracker_sdk.runs import open_backend, open_input

    run_input = open_input(source)
    stream = ((f.image, f.timestamp, None) for f, _ in zip(run_input.source, range(frames),
                                                           strict=False))
    return open_backend("torch", weights), stream, run_input.camera


def main(argv: list[str] | None = None) -> Outcome:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=300, help="frames to run")
    parser.add_argument("--segmenter", action="store_true", help="plug in the fake segmenter")
    parser.add_argument("--weights", help="a Pi3 or DA3 .safetensors checkpoint (default: simulated)")
    parser.add_argument("--source", help="with --weights: the frames")
    parser.add_argument("--box", help="with --weights: x0,y0,x1,y1 of the object on frame 0")
    args = parser.parse_args(argv)
    if args.weights and not (args.source and args.box):
        parser.error("--weights needs --source and --box")

    segmenter, camera = None, None
    if args.weights:
        backend, frames, camera = real(args.weights, args.source, args.frames)
        first_box = tuple(float(v) for v in args.box.split(","))
        config = TrackerConfig(mode="object", resolution=224)
    else:
        backend, frames, fake_sam = simulated(args.frames)
        segmenter = fake_sam if args.segmenter else None
        first_box = None
        config = TrackerConfig(mode="object")

    sources: Counter[str] = Counter()
    ious: list[float] = []
    anchor_in_view = False
    with open_tracker(config, backend, camera=camera, segmenter=segmenter) as tracker:
        for index, (image, timestamp, truth) in enumerate(frames):
            box = (first_box or truth) if index == 0 else None  # one tap, then nothing
            result = tracker.push_frame(image, timestamp=timestamp, bbox=box)
            region = result.region
            assert region is not None  # object mode: every frame after the first tap has one
            sources[region.source.value] += 1
            if truth is not None and result.pose_valid:
                ious.append(iou(region.box, truth))
            if result.T_cam_object is not None and result.intrinsics is not None:
                # where an app would draw the object's anchor: its origin, projected
                u, v = result.intrinsics.project(result.T_cam_object[:3, 3]) + 0.5
                x0, y0, x1, y1 = region.box
                anchor_in_view = bool(x0 <= u <= x1 and y0 <= v <= y1)
        anchor = tracker.object.frame
    backend.close()

    print(f"{sum(sources.values())} frames, regions: {dict(sources)}")
    if ious:
        print(f"predicted box vs the true silhouette's: IoU median {np.median(ious):.2f}, "
              f">= 0.8 on {100 * np.mean(np.array(ious) >= 0.8):.0f} % of tracked frames")
    if anchor is not None:
        print(f"object frame: origin {np.round(anchor.T_world_object[:3, 3], 3)} (world), "
              f"extent {np.round(anchor.extent.size, 3)} (map units)")
    return Outcome(sum(sources.values()), dict(sources), ious, anchor_in_view)


if __name__ == "__main__":
    main()
