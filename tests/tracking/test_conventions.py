"""The image and time conventions, guarded: frames are HxWx3 uint8 RGB unless ``color="bgr"``
says they are OpenCV's order; timestamps never go backwards within a session; each
``T_cam_object`` names the object frame it refers to."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import InputError
from tests.tracking.sim_session import SIZE, WAIT_S, drive, make_tracker


class _Recording(SimulatedBackend):
    """The simulated backend, keeping every image the tracker handed it."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.seen: list[np.ndarray] = []

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> Any:
        self.seen.extend(np.array(images))
        return super().map(images, masks)

    def track(self, image: np.ndarray, cache: Any, **kwargs: Any) -> Any:
        self.seen.append(np.array(image))
        return super().track(image, cache, **kwargs)


def _frames(count: int) -> list[Any]:
    backend = SimulatedBackend(orbit(60), seed=4)
    return list(backend.frames(SIZE, stop=count, textured=True))


def test_bgr_frames_with_color_bgr_reach_the_model_as_rgb() -> None:
    frames = _frames(8)
    runs = {}
    for color in ("rgb", "bgr"):
        backend = _Recording(orbit(60), seed=4)
        with make_tracker(backend, keyframing={"interval_frames": 4}) as tracker:
            results = [
                tracker.push_frame(f.image if color == "rgb" else f.image[..., ::-1].copy(),
                                   timestamp=f.timestamp, color=color)
                for f in frames
            ]
        runs[color] = (backend.seen, [r.pose.T_world_cam if r.pose else None for r in results])
    (seen_rgb, poses_rgb), (seen_bgr, poses_bgr) = runs["rgb"], runs["bgr"]
    assert len(seen_rgb) == len(seen_bgr) > len(frames)  # mapping passes and tracking steps
    assert not np.array_equal(frames[0].image, frames[0].image[..., ::-1])  # colours differ
    for a, b in zip(seen_rgb, seen_bgr, strict=True):
        np.testing.assert_array_equal(a, b)  # exactly the same model input
    for a, b in zip(poses_rgb, poses_bgr, strict=True):
        assert (a is None and b is None) or np.array_equal(a, b)


def test_submit_takes_the_color_order_too() -> None:
    frame = _frames(1)[0]
    backend = _Recording(orbit(60), seed=4)
    with make_tracker(backend) as tracker:
        tracker.submit(frame.image[..., ::-1].copy(), timestamp=frame.timestamp, color="bgr")
        assert tracker.live.wait_idle(WAIT_S)
    reference = _Recording(orbit(60), seed=4)
    with make_tracker(reference) as tracker:
        tracker.push_frame(frame.image, timestamp=frame.timestamp)
    np.testing.assert_array_equal(backend.seen[0], reference.seen[0])


def test_an_unknown_color_order_is_an_input_error_and_changes_nothing() -> None:
    frame = _frames(1)[0]
    with make_tracker(SimulatedBackend(orbit(60), seed=4)) as tracker:
        with pytest.raises(InputError, match='"rgb" or "bgr"'):
            tracker.push_frame(frame.image, timestamp=0.0, color="BGRA")
        assert tracker.push_frame(frame.image, timestamp=0.0).frame_index == 0


def test_timestamps_going_backwards_are_refused_and_change_nothing() -> None:
    backend = SimulatedBackend(orbit(60), seed=4)
    frames = _frames(6)
    with make_tracker(backend, keyframing={"interval_frames": 2}) as tracker:
        drive(tracker, backend, stop=4)
        before = tracker.snapshot()
        last = before.timestamp
        assert last is not None
        with pytest.raises(InputError, match="must not go backwards"):
            tracker.push_frame(frames[4].image, timestamp=last - 0.001)
        assert tracker.snapshot() == before  # state, frame counter, pose: untouched
        same = tracker.push_frame(frames[4].image, timestamp=last)  # equal stamps are accepted
        assert same.frame_index == before.frame_index + 1
        assert tracker.push_frame(frames[5].image).timestamp is None  # no stamp: no order
        tracker.reset()  # a new session may restart its clock
        assert tracker.push_frame(frames[0].image, timestamp=0.0).timestamp == 0.0


def test_each_t_cam_object_names_its_object_frame() -> None:
    backend = SimulatedBackend(orbit(720), seed=2, translation_noise_m=0.003,
                               rotation_noise_deg=0.1)
    with make_tracker(backend, mode="object", keyframing={"view_angle_deg": 5.0}) as tracker:
        session = drive(tracker, backend, stop=40, with_mask=True)
    with_object = [r for r in session.results if r.T_cam_object is not None]
    assert len(with_object) > 30
    generations = {r.object_frame.map_generation for r in with_object if r.object_frame}
    assert len(generations) >= 2  # rebuilt maps: the object frame moved, and each frame says which
    for r in session.results:
        if r.T_cam_object is None:
            assert r.object_frame is None
            continue
        assert r.object_frame is not None and r.pose is not None
        expected = np.linalg.inv(r.pose.T_world_cam) @ r.object_frame.T_world_object
        np.testing.assert_allclose(r.T_cam_object, expected, rtol=0, atol=1e-12)  # same float64 ops
