"""Embed kvtracker in an app's camera loop: push frames, read poses, react to callbacks.

    python examples/camera_loop.py                       # offline: a simulated hand-held camera
    python examples/camera_loop.py --weights pi3.safetensors --source path/to/tum_sequence

The app below stands in for yours: it draws content at the camera pose when the pose is valid and
tells the user what to do when it is not. Callbacks run on the thread that called ``push_frame``
(after the tracker released its lock), so they may touch the app's state directly.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from kvtracker_sdk import Backend, Pose, TrackerConfig, TrackingState
from kvtracker_sdk.runs import TrackingInput, open_tracker
from kvtracker_sdk.tracking.core.events import KeyframeEvent, StateChangeEvent

HINTS = {
    TrackingState.INIT: "point the camera at the scene",
    TrackingState.MAPPING: "building the map: hold still",
    TrackingState.TRACKING: "unsure about this frame: move more slowly",  # a low-confidence frame
    TrackingState.RELOCALIZING: "lost: go back to where you were",
}


@dataclass
class App:
    """A stand-in for an AR app: a renderer and a status line."""

    frames_drawn: int = 0
    hints_shown: int = 0
    last_pose: Pose | None = None
    log: list[str] = field(default_factory=list)

    def on_state_change(self, event: StateChangeEvent) -> None:
        self.log.append(f"frame {event.frame_index}: {event.previous.value} -> {event.state.value}"
                        f" ({event.reason.value})")

    def on_keyframe(self, event: KeyframeEvent) -> None:
        self.log.append(f"frame {event.frame_index}: keyframe {event.keyframe_id} added")

    def draw(self, pose: Pose) -> None:
        self.frames_drawn += 1  # a real app renders its virtual content with pose.T_world_cam
        self.last_pose = pose

    def show_hint(self, state: TrackingState) -> None:
        self.hints_shown += 1  # a real app would display HINTS[state] and keep the last pose


Camera = Iterator[tuple[np.ndarray, float]]  # (RGB uint8 [H, W, 3], timestamp in seconds)


def simulated_camera(frames: int) -> tuple[Backend, Camera, None]:
    """A simulated backend and its camera: 1 s of lost tracking two thirds of the way in."""
    from kvtracker_sdk import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    lost = (2 * frames // 3, 2 * frames // 3 + 30)
    backend = SimulatedBackend(orbit(frames, radius=1.2), loss_segments=[lost])
    images = ((f.image, f.timestamp) for f in backend.frames((240, 320), textured=False))
    return backend, images, None


def real_camera(weights: str, source: str, frames: int) -> tuple[Backend, Camera, TrackingInput]:
    """The PyTorch backend and the frames of a video or an image sequence, with their camera
    (a dataset's published intrinsics: TUM frames are undistorted by the tracker)."""
    from kvtracker_sdk.runs import open_backend, open_input

    run_input = open_input(source)
    frames_iter = ((f.image, f.timestamp) for f in run_input.source)
    limited = (item for _, item in zip(range(frames), frames_iter, strict=False))
    return open_backend("torch", weights), limited, run_input


def main(argv: list[str] | None = None) -> App:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=300, help="frames to run")
    parser.add_argument("--weights", help="a Pi3 .safetensors checkpoint (default: simulated)")
    parser.add_argument("--source", help="with --weights: a video or an image-sequence folder")
    args = parser.parse_args(argv)
    if args.weights and not args.source:
        parser.error("--weights needs --source (the frames to track)")

    if args.weights:
        backend, camera, run_input = real_camera(args.weights, args.source, args.frames)
        config = TrackerConfig(resolution=224, keyframing={"interval_frames": 5})
    else:
        backend, camera, run_input = simulated_camera(args.frames)
        config = TrackerConfig(keyframing={"interval_frames": 30})

    app = App()
    with open_tracker(config, backend, run_input) as tracker:  # the input's camera, if known
        tracker.events.on_state_change(app.on_state_change)
        tracker.events.on_keyframe(app.on_keyframe)
        for image, timestamp in camera:  # the app's camera loop
            result = tracker.push_frame(image, timestamp=timestamp)
            if result.pose_valid and result.pose is not None:
                app.draw(result.pose)
            else:
                app.show_hint(result.state)
    backend.close()

    print("\n".join(app.log))
    print(f"drew {app.frames_drawn} frames, showed a hint on {app.hints_shown}")
    if app.last_pose is not None:
        print(f"last camera position (world frame): {np.round(app.last_pose.translation, 3)}")
    return app


if __name__ == "__main__":
    main()
