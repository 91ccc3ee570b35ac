"""Swap the inference backend of a running tracker, keeping its map (e.g. PyTorch -> ONNX Runtime).

    python examples/swap_backends.py                          # offline: two simulated backends
    python examples/swap_backends.py --weights pi3.safetensors --source path/to/frames

``Tracker.set_backend`` swaps between two frames. The map's K/V cache stays valid because both
backends compute the same function: their ``info.fingerprint`` (model family, configuration and
weights; not runtime, device or dtype) must agree, and the swap is refused otherwise. With
``--weights`` the second backend is ONNX Runtime when the ONNX backend is installed, else the
same weights on PyTorch in bfloat16 (the cache is converted to the new dtype on the swap).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk import Backend, Camera, TrackerConfig
from kvtracker_sdk.errors import BackendMismatchError
from kvtracker_sdk.runs import open_tracker

Frames = Iterator[tuple[np.ndarray, float]]  # (RGB uint8 [H, W, 3], timestamp in seconds)


@dataclass(frozen=True)
class Outcome:
    backends_used: list[str]  # "1:runtime/dtype" of the backend that tracked each frame
    keyframes: int
    mismatch_refused: bool  # a backend with other weights was refused
    all_poses_valid_after_swap: bool  # False when no frame ran after a swap
    swapped_at: int | None  # the frame the backends were swapped at (None: never)


# first, second, another model, frames, frames available, the frames' camera (if known)
Setup = tuple[Backend, Callable[[], Backend], Backend, Frames, int, Camera | None]


def simulated(frames: int) -> Setup:
    """Two simulated backends of one model (as torch-on-GPU and onnx-on-CPU would be) and one
    of another model (another seed: other "weights")."""
    from kvtracker_sdk import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    path = orbit(frames, radius=1.2)
    first = SimulatedBackend(path, seed=0)
    images = ((f.image, f.timestamp) for f in first.frames((240, 320), textured=False))
    return (first, lambda: SimulatedBackend(path, seed=0), SimulatedBackend(path, seed=1), images,
            len(path), None)


def real(weights: str, source: str, frames: int) -> Setup:
    """PyTorch fp32 first; ONNX Runtime second if installed (else PyTorch bf16); a simulated
    backend stands for "another model" to show the refusal."""
    from kvtracker_sdk import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit
    from kvtracker_sdk.errors import MissingDependencyError
    from kvtracker_sdk.runs import open_backend, open_input

    def second() -> Backend:
        try:
            return open_backend("onnx", weights)  # exported once into a cache folder
        except MissingDependencyError:  # the [onnx] extra is not installed
            print("ONNX backend unavailable: swapping to PyTorch bfloat16 instead")
            return open_backend("torch", weights, dtype="bfloat16")

    first = open_backend("torch", weights)
    stranger = SimulatedBackend(orbit(10))
    run_input = open_input(source)
    opened = run_input.source
    stream = ((f.image, f.timestamp) for f in opened)
    limited = (item for _, item in zip(range(frames), stream, strict=False))
    # a video may only estimate its length (0: unknown): then trust --frames
    return first, second, stranger, limited, min(frames, len(opened) or frames), run_input.camera


def main(argv: list[str] | None = None) -> Outcome:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=120, help="frames to run")
    parser.add_argument("--weights", help="a Pi3 .safetensors checkpoint (default: simulated)")
    parser.add_argument("--source", help="with --weights: a video or an image-sequence folder")
    args = parser.parse_args(argv)
    if args.weights and not args.source:
        parser.error("--weights needs --source (the frames to track)")

    if args.weights:
        first, make_second, stranger, frames, available, camera = real(
            args.weights, args.source, args.frames
        )
        config = TrackerConfig(resolution=224, keyframing={"interval_frames": 3})
    else:
        first, make_second, stranger, frames, available, camera = simulated(args.frames)
        config = TrackerConfig(keyframing={"interval_frames": 30})
    # halfway through the frames there are (a source may hold fewer than --frames)
    swap_at = min(args.frames, available) // 2
    used, valid_after, refused, swapped_at = [], [], False, None

    with open_tracker(config, first, camera=camera) as tracker:
        for k, (image, timestamp) in enumerate(frames):
            if k == swap_at:
                try:
                    tracker.set_backend(stranger)  # other weights: the cache would be garbage
                except BackendMismatchError as error:
                    refused = True
                    print(f"frame {k}: refused as expected: {str(error)[:80]}...")
                previous = tracker.set_backend(make_second())
                previous.close()  # the tracker does not close a backend it was given
                swapped_at = k
                print(f"frame {k}: swapped {previous.info.backend} -> {tracker.backend.info.backend}"
                      f" ({tracker.backend.info.dtype}), map kept: "
                      f"{tracker.map_status.num_keyframes} keyframes")
            result = tracker.push_frame(image, timestamp=timestamp)
            info = tracker.backend.info
            used.append(f"{1 + (k >= swap_at)}:{info.backend}/{info.dtype}")
            if k >= swap_at:
                valid_after.append(result.pose_valid)
        keyframes = tracker.map_status.num_keyframes
        tracker.backend.close()
    stranger.close()

    counts = ", ".join(f"{used.count(name)} frames on backend {name}" for name in dict.fromkeys(used))
    if swapped_at is None:
        print(f"{counts}; {keyframes} keyframes; NOT swapped: the source ended after "
              f"{len(used)} frames, before frame {swap_at}")
    else:
        print(f"{counts}; {keyframes} keyframes; {sum(valid_after)} of {len(valid_after)} poses "
              f"after the swap valid")
    return Outcome(used, keyframes, refused, bool(valid_after) and all(valid_after), swapped_at)


if __name__ == "__main__":
    main()
