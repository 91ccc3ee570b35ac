"""The camera path of ``kvtracker demo``: a person walking once around an object, phone in hand.

A perfect circle (``simulated_scene.orbit``) is too easy and looks synthetic. A hand-held orbit
has, on top of the circle (all seeded, smooth, in metres and degrees):

- an uneven walk: the angular speed varies by about ±30 % (people slow down to look);
- a breathing radius (±12 cm, ``breathing``) and a rising and sinking hand (±10 cm, ``lift``);
- hand shake and walking bounce: a few sinusoids between 0.5 and 3 Hz, about 5 mm RMS;
- an unsteady aim: the look-at point wanders about 5 cm around the object, plus a few degrees of
  roll, so the camera's optical axis is never exactly on the object centre.

The world frame has z up and the object at the origin, like ``orbit``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kvtracker_sdk.backends.simulated_scene import GroundTruth, look_at

__all__ = ["default_loss_segment", "desk_orbit", "handheld_orbit"]

_SHAKE_HZ = (0.5, 3.0)  # band of the hand tremor and walking bounce
_SHAKE_TERMS = 4


def _smooth_noise(
    rng: np.random.Generator, seconds: np.ndarray, amplitude: float, dims: int
) -> np.ndarray:
    """[F, dims] band-limited noise: random sinusoids in ``_SHAKE_HZ``, RMS about ``amplitude``."""
    out = np.zeros((len(seconds), dims))
    for _ in range(_SHAKE_TERMS):
        freq = rng.uniform(*_SHAKE_HZ, size=dims)
        phase = rng.uniform(0, 2 * np.pi, size=dims)
        out += np.sin(2 * np.pi * freq * seconds[:, None] + phase)
    return out * amplitude * np.sqrt(2.0 / _SHAKE_TERMS)  # each unit sinusoid has RMS 1/sqrt(2)


def handheld_orbit(
    num_frames: int = 600,
    *,
    rate_hz: float = 30.0,
    radius: float = 1.2,
    height: float = 0.35,
    turns: float = 1.0,
    seed: int = 0,
    lift: float = 0.10,
    breathing: float = 0.12,
    arc_deg: tuple[float, float] | None = None,
) -> GroundTruth:
    """``num_frames`` poses ``T_world_cam`` (OpenCV axes) of a hand-held walk around the origin.

    ``lift``: amplitude (metres) of the rising and sinking hand, i.e. of the elevation changes;
    ``breathing``: amplitude (metres) of the walk's distance to the object.
    ``arc_deg``: instead of full turns, walk ``turns`` times to and fro over the azimuths from
    ``arc_deg[0]`` to ``arc_deg[1]`` (degrees; e.g. in front of a wall), starting in the middle.
    """
    rng = np.random.default_rng(seed)
    seconds = np.arange(num_frames) / rate_hz
    progress = np.linspace(0.0, 1.0, num_frames, endpoint=False)
    # uneven walk: speed 1 + 0.3 sin(...) integrated, then normalised to `turns` full turns
    speed = 1.0 + 0.3 * np.sin(2 * np.pi * (2.0 * progress + rng.uniform()))
    angle = np.concatenate([[0.0], np.cumsum(speed[:-1])])
    angle *= 2 * np.pi * turns / max(angle[-1] + speed[-1], 1e-9)
    if arc_deg is not None:  # from the arc's middle to one end, the other, and back
        start, stop = np.radians(arc_deg)
        angle = start + (stop - start) * (1.0 + np.sin(angle / turns)) / 2.0
    ring = radius + breathing * np.sin(2 * np.pi * (1.5 * progress + rng.uniform()))
    hand = height + lift * np.sin(2 * np.pi * (1.0 * progress + rng.uniform()))
    centres = np.stack([ring * np.cos(angle), ring * np.sin(angle), hand], axis=1)
    centres += _smooth_noise(rng, seconds, 0.005, 3)
    targets = _smooth_noise(rng, seconds / 4.0, 0.05, 3)  # slower wander of the aim
    roll_deg = _smooth_noise(rng, seconds / 2.0, 2.0, 1)[:, 0]
    up = np.array([0.0, 0.0, 1.0])
    poses = np.empty((num_frames, 4, 4))
    for i in range(num_frames):
        pose = look_at(centres[i], targets[i], up)
        roll = Rotation.from_euler("z", roll_deg[i], degrees=True).as_matrix()  # about the axis
        pose[:3, :3] = pose[:3, :3] @ roll
        poses[i] = pose
    return GroundTruth(seconds, poses)


def default_loss_segment(num_frames: int, rate_hz: float = 30.0) -> tuple[int, int] | None:
    """Frames [start, stop) where the demo's "camera is covered": 1.5 s from 55 % of the walk.

    None when the run is too short to show a loss and a recovery (under 4 s).
    """
    length = round(1.5 * rate_hz)
    if num_frames < 4 * rate_hz:
        return None
    start = int(0.55 * num_frames)
    return start, min(start + length, num_frames)


def desk_orbit(num_frames: int = 720, *, seed: int = 0, wall: bool = False) -> GroundTruth:
    """A hand-held walk around an object on a desk (``SimulatedScene.desk``): 0.5 m away (±10 %),
    looking down 13 to 39 degrees (the hand rises and sinks 12 cm around 25 cm above the object's
    centre); with ``wall``, to and fro over the 140 degrees in front of the wall."""
    return handheld_orbit(num_frames, radius=0.5, height=0.25, lift=0.12, breathing=0.05,
                          seed=seed, arc_deg=(200.0, 340.0) if wall else None)
