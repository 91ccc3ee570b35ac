"""Scan an object, save its map, and relocalise against the saved map in a second session.

    python examples/object_scan_and_relocalise.py                  # offline: a simulated orbit
    python examples/object_scan_and_relocalise.py --weights pi3.safetensors \\
        --source path/to/frames --bbox 200,120,440,360              # a real model, a box per frame

Session 1 walks part of the way around the object in object mode (a mask, or a box, per frame),
then saves the map: keyframes, their K/V cache and the world frame, in one ``.kvmap`` file.
Session 2, in a new tracker (in a real app: the next day), loads the file and starts in
RELOCALIZING; once the camera sees the object from a mapped side it is TRACKING again, and its
poses are in the *same* world frame as session 1's: content anchored to the object stays put.
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kvtracker_sdk import Backend, Tracker, TrackerConfig
from kvtracker_sdk.geometry.sim3 import umeyama_alignment
from kvtracker_sdk.runs import open_tracker

ORBIT_FRAMES = 720  # the simulated camera circles the object twice, 1 degree per frame


@dataclass(frozen=True)
class View:
    image: np.ndarray  # RGB uint8 [H, W, 3]
    timestamp: float
    mask: np.ndarray | None = None  # bool [H, W]: the object's pixels
    bbox: tuple[float, float, float, float] | None = None
    true_position: np.ndarray | None = None  # ground-truth camera centre, when known


@dataclass(frozen=True)
class Outcome:
    keyframes_saved: int
    frames_to_relocalise: int  # frames of session 2 before its first valid pose
    relocalised_error_m: float | None  # session-2 position RMSE in session 1's frame (aligned)


Positions = list[tuple[np.ndarray, np.ndarray | None]]  # (estimate, ground truth) per valid pose


def run(tracker: Tracker, views: Iterator[View]) -> tuple[int, Positions]:
    """Push ``views``; returns the index of the first valid pose (-1: none) and the positions."""
    first_valid, positions = -1, []
    for k, view in enumerate(views):
        result = tracker.push_frame(view.image, view.timestamp, mask=view.mask, bbox=view.bbox)
        if result.pose_valid and result.pose is not None:
            first_valid = k if first_valid < 0 else first_valid
            positions.append((result.pose.translation.copy(), view.true_position))
    return first_valid, positions


def scan(map_path: Path, backend: Backend, views: Iterator[View]) -> tuple[int, Positions]:
    """Session 1: track the object over ``views`` and save the map."""
    with open_tracker(TrackerConfig(mode="object"), backend) as tracker:
        _, positions = run(tracker, views)
        info = tracker.save_map(map_path)
    print(f"session 1: saved {info.num_keyframes} keyframes to {map_path} "
          f"({info.file_size / 1e6:.1f} MB, model fingerprint {info.fingerprint})")
    return info.num_keyframes, positions


def relocalise(map_path: Path, backend: Backend, views: Iterator[View]) -> tuple[int, Positions]:
    """Session 2: a new tracker from the saved map; push frames until tracking is back."""
    with open_tracker(None, backend, load_map=map_path) as tracker:  # the map's saved config
        print(f"session 2: loaded the map -> {tracker.state.value} ({tracker.reason.value})")
        first_valid, positions = run(tracker, views)
        print(f"session 2: {tracker.state.value} after {first_valid + 1} frames")
    return first_valid, positions


def error_in_first_frame(scanned: Positions, relocalised: Positions) -> float | None:
    """Session 1's world frame has its own origin and scale (monocular): align it to the ground
    truth once, from session 1's poses only, and apply that alignment to session 2's poses."""
    if not scanned or not relocalised or scanned[0][1] is None:
        return None
    est1, gt1 = (np.array(column) for column in zip(*scanned, strict=True))
    est2, gt2 = (np.array(column) for column in zip(*relocalised, strict=True))
    to_truth = umeyama_alignment(est1, gt1)
    errors = np.linalg.norm(to_truth.apply_to_points(est2) - gt2, axis=1)
    return float(np.sqrt(np.mean(errors**2)))


def simulated(start: int, stop: int) -> tuple[Backend, Iterator[View]]:
    """The simulated model (the same one every session) and masked frames ``start:stop``."""
    from kvtracker_sdk import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    backend = SimulatedBackend(orbit(ORBIT_FRAMES, turns=2.0), seed=3, translation_noise_m=0.003)
    frames = backend.frames((240, 320), start=start, stop=stop, textured=False, with_mask=True)
    views = (View(f.image, f.timestamp, f.mask, None, f.T_world_cam[:3, 3]) for f in frames)
    return backend, views


def real(weights: str, source: str, bbox: str, start: int, stop: int) -> tuple[Backend, Iterator[View]]:
    """The PyTorch backend and frames ``start:stop`` of a video or a sequence, one box for all."""
    from kvtracker_sdk.io.sources.sources import open_source
    from kvtracker_sdk.runs import open_backend

    box = tuple(float(v) for v in bbox.split(","))
    frames = (f for f in open_source(source) if start <= f.frame_index < stop)
    views = (View(f.image, f.timestamp, bbox=box) for f in frames)  # type: ignore[arg-type]
    return open_backend("torch", weights), views


def main(argv: list[str] | None = None) -> Outcome:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--map", type=Path, help="where to save the map (default: a temp folder)")
    parser.add_argument("--scan-frames", type=int, default=180, help="frames of session 1")
    parser.add_argument("--relocalise-frames", type=int, default=60, help="frames of session 2")
    parser.add_argument("--weights", help="a Pi3 .safetensors checkpoint (default: simulated)")
    parser.add_argument("--source", help="with --weights: the frames (scan first, then relocalise)")
    parser.add_argument("--bbox", help="with --weights: the object's box x0,y0,x1,y1 (pixels)")
    args = parser.parse_args(argv)
    if args.weights and not (args.source and args.bbox):
        parser.error("--weights needs --source and --bbox")

    session: Callable[[int, int], tuple[Backend, Iterator[View]]]
    if args.weights:
        second = args.scan_frames  # real frames: relocalise on the frames right after the scan
        session = lambda a, b: real(args.weights, args.source, args.bbox, a, b)  # noqa: E731
    else:
        second = ORBIT_FRAMES // 2 + 20  # the second lap, 20 degrees into the scanned side
        session = simulated
    with tempfile.TemporaryDirectory() as tmp:
        map_path = args.map or Path(tmp) / "object.kvmap"
        backend, views = session(0, args.scan_frames)
        keyframes, scanned = scan(map_path, backend, views)
        backend.close()
        backend, views = session(second, second + args.relocalise_frames)
        waited, relocalised = relocalise(map_path, backend, views)
        backend.close()

    error = error_in_first_frame(scanned, relocalised)
    if error is not None:
        print(f"session 2 poses in session 1's world frame: position RMSE {error * 100:.2f} cm")
    return Outcome(keyframes, waited, error)


if __name__ == "__main__":
    main()
