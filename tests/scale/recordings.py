"""Two simulated sequences written to disk as an app's recordings are: frames a real backend
tracks (textured renders of a known orbit), with their ground truth; one with a camera file."""

from __future__ import annotations

import json
from pathlib import Path

import cv2

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.io.files.trajectory import Trajectory, write_tum

SIZE = (196, 252)  # Pi3's model size at d = 224 for 4:3 frames
# a lens with distortion: the run must undistort its frames the same way on every entry point
CAMERA = {"fx": 180.0, "fy": 181.0, "cx": 125.0, "cy": 97.0, "width": 252, "height": 196,
          "distortion": [0.05, -0.02, 0.001, 0.0005, 0.0]}


def write_tum_layout(folder: Path, frames: int, seed: int) -> Path:
    """``folder``: ``rgb.txt``, ``rgb/*.png``, ``groundtruth.txt`` of a simulated orbit."""
    backend = SimulatedBackend(orbit(frames, turns=0.2), seed=seed)
    (folder / "rgb").mkdir(parents=True)
    lines = ["# timestamp filename"]
    for frame in backend.frames(SIZE, textured=True):
        name = f"rgb/{frame.index:06d}.png"
        cv2.imwrite(str(folder / name), frame.image[:, :, ::-1])
        lines.append(f"{frame.timestamp!r} {name}")
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    truth = backend.ground_truth
    write_tum(folder / "groundtruth.txt", Trajectory(truth.timestamps, truth.poses))
    return folder


def write_image_folder(folder: Path, frames: int, seed: int) -> tuple[Path, Path]:
    """``folder/*.png`` stamped index / 30 (an image folder's stamps), and its ground truth."""
    backend = SimulatedBackend(orbit(frames, turns=0.3, radius=1.5), seed=seed)
    folder.mkdir(parents=True)
    for frame in backend.frames(SIZE, textured=True):
        cv2.imwrite(str(folder / f"{frame.index}.png"), frame.image[:, :, ::-1])
    truth = backend.ground_truth
    stamps = truth.timestamps - truth.timestamps[0]
    gt = folder.parent / f"{folder.name}_groundtruth.txt"
    write_tum(gt, Trajectory(stamps, truth.poses))
    return folder, gt


def write_camera(path: Path) -> Path:
    path.write_text(json.dumps(CAMERA))
    return path
