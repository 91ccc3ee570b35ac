"""Stress: reader threads calling get_pose() (and map_status) while frames are tracked and maps
are rebuilt on the worker; every pose read must be one the tracker published, rigid, and never
older than a pose the same reader saw before."""

from __future__ import annotations

import threading

import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.types import Pose
from tests.tracking.sim_session import SIZE, make_tracker


@pytest.mark.parametrize("async_mapping", [False, True], ids=["sync", "async"])
def test_readers_see_no_torn_or_out_of_order_poses(async_mapping: bool) -> None:
    backend = SimulatedBackend(orbit(600, turns=1.0), seed=11)
    config = {"threading": {"async_mapping": async_mapping}, "keyframing": {"interval_frames": 15}}
    stop = threading.Event()
    reads: list[list[Pose]] = [[] for _ in range(3)]
    statuses: list[int] = []

    with make_tracker(backend, **config) as tracker:

        def reader(out: list[Pose]) -> None:
            while not stop.wait(0.0002):  # yield the GIL between reads: three spinning
                pose = tracker.get_pose()  # readers would starve the camera loop
                if pose is not None and (not out or out[-1] is not pose):
                    out.append(pose)
                statuses.append(tracker.map_status.num_keyframes)

        threads = [threading.Thread(target=reader, args=(out,)) for out in reads]
        for thread in threads:
            thread.start()
        published: dict[bytes, int] = {}
        try:
            for frame in backend.frames(SIZE, textured=False):
                result = tracker.push_frame(frame.image, timestamp=frame.timestamp)
                if result.pose_valid:
                    published[result.pose.T_world_cam.tobytes()] = result.frame_index
        finally:
            stop.set()
            for thread in threads:
                thread.join(timeout=30)
        keyframes = tracker.map_status.num_keyframes

    assert len(published) > 400 and keyframes > 10
    for out in reads:
        assert len(out) > 5  # the readers really interleaved with the writer
        order = []
        for pose in out:
            assert pose.is_rigid(atol=1e-9)  # not torn
            index = published.get(pose.T_world_cam.tobytes())
            assert index is not None  # exactly a pose the tracker published
            order.append(index)
        assert order == sorted(order)  # never out of order
    assert statuses and max(statuses) <= 32
    assert not any(thread.is_alive() for thread in threads)
