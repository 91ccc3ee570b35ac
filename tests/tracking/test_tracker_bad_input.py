"""Property test: hundreds of generated bad frames give only typed InputErrors and leave the
tracker's state, keyframes, cache, pose and frame counter untouched."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import InputError
from kvtracker_sdk.tracking.facade.tracker import Tracker
from tests.tracking.sim_session import SIZE, drive, make_tracker

H, W = SIZE


VALID = object()  # stands for the valid session image in calls whose mask/bbox/timestamp is bad


@dataclass
class Bad:
    """A bad push_frame call."""

    image: Any
    mask: Any = None
    bbox: Any = None
    timestamp: Any = None


@pytest.fixture(scope="module")
def tracker_and_image() -> Iterator[tuple[Tracker, np.ndarray]]:
    backend = SimulatedBackend(orbit(200), seed=9)
    with make_tracker(backend, keyframing={"interval_frames": 5}) as tracker:
        drive(tracker, backend, stop=12)  # TRACKING with 3 keyframes
        image = backend.camera(SIZE, textured=False).render(12).image
        yield tracker, image


def _with_pixel(dtype: str, value: float, row: int, col: int) -> np.ndarray:
    """A valid-looking float image with one bad value."""
    image = np.full((H, W, 3), 0.5, dtype=dtype)
    image[row % H, col % W, row % 3] = value
    return image


positions = st.tuples(st.integers(0, H - 1), st.integers(0, W - 1))

bad_shapes = hnp.arrays(
    np.uint8,
    st.one_of(
        hnp.array_shapes(min_dims=1, max_dims=4, min_side=1, max_side=20),
        st.sampled_from(
            [(H, W), (H, W, 1), (H, W, 4), (3, H, W), (H, W, 3, 1), (10, W, 3), (H, 13, 3)]
        ),
    ).filter(lambda s: not (len(s) == 3 and s[2] == 3 and min(s[:2]) >= 14)),
    elements=st.integers(0, 255),
).map(Bad)

bad_dtypes = st.sampled_from(
    [np.int8, np.int16, np.int32, np.int64, np.uint16, np.uint32, np.bool_, np.complex64, object]
).map(lambda dtype: Bad(np.zeros((H, W, 3), dtype=dtype)))

non_finite = st.builds(
    lambda dtype, value, pos: Bad(_with_pixel(dtype, value, *pos)),
    st.sampled_from(["float16", "float32", "float64"]),
    st.sampled_from([np.nan, np.inf, -np.inf]),
    positions,
)

out_of_range = st.builds(
    lambda dtype, value, pos: Bad(_with_pixel(dtype, value, *pos)),
    st.sampled_from(["float32", "float64"]),
    st.one_of(st.floats(1.001, 1e6), st.floats(-1e6, -0.001)),
    positions,
)

not_arrays = st.one_of(
    st.none(), st.integers(), st.text(max_size=5), st.lists(st.integers(), max_size=4)
).map(Bad)

wrong_sizes = (
    st.tuples(st.integers(14, 300), st.integers(14, 300))
    .filter(lambda s: s != SIZE)
    .map(lambda s: Bad(np.zeros((*s, 3), dtype=np.uint8)))
)


bad_masks = st.one_of(
    st.just(np.zeros((H, W), dtype=bool)),
    st.just(np.zeros((H, W), dtype=np.uint8)),
    st.tuples(st.integers(1, 300), st.integers(1, 300))
    .filter(lambda s: s != SIZE)
    .map(lambda s: np.ones(s, bool)),
    st.just(np.ones((H, W), dtype=np.float32)),
    st.just(np.ones((H, W, 2), dtype=bool)),
    st.sampled_from(["mask", 1, [1, 0]]),
).map(lambda mask: Bad(VALID, mask=mask))

coordinates = st.floats(-1e4, 1e4, allow_nan=False)
bad_boxes = st.one_of(
    st.tuples(coordinates, coordinates, coordinates, coordinates).filter(
        lambda b: not (0 <= b[0] < b[2] <= W and 0 <= b[1] < b[3] <= H)
    ),
    st.lists(st.floats(0, 10), min_size=0, max_size=6).filter(lambda b: len(b) != 4),
    st.tuples(st.just(0.0), st.just(0.0), st.sampled_from([np.nan, np.inf]), st.just(5.0)),
    st.sampled_from(["box", b"box", {"x": 1}]),
).map(lambda bbox: Bad(VALID, bbox=bbox))

bad_timestamps = st.sampled_from([np.nan, np.inf, -np.inf, "noon", [1.0], object()]).map(
    lambda t: Bad(VALID, timestamp=t)
)

bad_calls = st.one_of(
    bad_shapes,
    bad_dtypes,
    non_finite,
    out_of_range,
    not_arrays,
    wrong_sizes,
    bad_masks,
    bad_boxes,
    bad_timestamps,
)


@settings(
    max_examples=600,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(bad=bad_calls)
def test_bad_frames_raise_typed_errors_and_change_nothing(
    tracker_and_image: tuple[Tracker, np.ndarray], bad: Bad
) -> None:
    tracker, valid_image = tracker_and_image
    kf_map = tracker.keyframe_map
    assert kf_map is not None
    before = (tracker.state, tracker.reason, tracker.map_status, tracker.get_pose())
    snapshot = kf_map.cache.clone()
    image = valid_image if bad.image is VALID else bad.image
    with pytest.raises(InputError):
        tracker.push_frame(image, timestamp=bad.timestamp, mask=bad.mask, bbox=bad.bbox)
    assert (tracker.state, tracker.reason, tracker.map_status, tracker.get_pose()) == before
    assert tracker.keyframe_map is kf_map and kf_map.cache.equals(snapshot)


def test_tracking_continues_after_the_bad_frames(
    tracker_and_image: tuple[Tracker, np.ndarray],
) -> None:
    tracker, image = tracker_and_image
    result = tracker.push_frame(image)
    assert result.pose_valid and result.frame_index == 12  # no index was spent on bad frames
