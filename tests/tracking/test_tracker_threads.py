"""Stress: reader threads calling get_pose() (and map_status) while frames are tracked and maps
are rebuilt on the worker; every pose read must be one the tracker published, rigid, and never
older than a pose the same reader saw before."""

from __future__ import annotations

import threading
from functools import partial

import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.types import Pose, TrackingState
from tests.tracking.sim_session import SIZE, WAIT_S, make_tracker


@pytest.mark.parametrize("async_mapping", [False, True], ids=["sync", "async"])
def test_readers_see_no_torn_or_out_of_order_poses(async_mapping: bool) -> None:
    backend = SimulatedBackend(orbit(600, turns=1.0), seed=11)
    config = {"threading": {"async_mapping": async_mapping}, "keyframing": {"interval_frames": 15}}
    stop = threading.Event()
    seen = threading.Condition()  # a reader saw a new pose
    reads: list[list[Pose]] = [[] for _ in range(3)]
    statuses: list[int] = []

    with make_tracker(backend, **config) as tracker:

        def reader(out: list[Pose]) -> None:
            # Not synchronisation: the short wait only yields the GIL between reads (three
            # spinning readers would starve the camera loop); the checkpoints below synchronise.
            while not stop.wait(0.0002):
                pose = tracker.get_pose()
                if pose is not None and (not out or out[-1] is not pose):
                    with seen:
                        out.append(pose)
                        seen.notify_all()
                statuses.append(tracker.map_status.num_keyframes)

        def every_reader_saw(pose: Pose) -> bool:
            return all(out and out[-1] is pose for out in reads)

        threads = [threading.Thread(target=reader, args=(out,)) for out in reads]
        for thread in threads:
            thread.start()
        published: dict[bytes, int] = {}
        try:
            for frame in backend.frames(SIZE, textured=False):
                result = tracker.push_frame(frame.image, timestamp=frame.timestamp)
                if result.pose_valid:
                    published[result.pose.T_world_cam.tobytes()] = result.frame_index
                    if result.frame_index % 60 == 0:  # checkpoint: every reader reads this pose
                        latest = tracker.get_pose()
                        assert latest is not None
                        with seen:
                            assert seen.wait_for(partial(every_reader_saw, latest), timeout=WAIT_S)
                # paced like tests.tracking.sim_session.drive: rebuilds overlap the frame loop,
                # but how many frames get poses and which become keyframes is machine-independent
                if result.state is TrackingState.MAPPING or tracker.map_status.keyframe_waiting:
                    assert tracker.wait_for_map(timeout=WAIT_S)
        finally:
            stop.set()
            for thread in threads:
                thread.join(timeout=30)
        keyframes = tracker.map_status.num_keyframes

    # every frame after the first map is valid (frame 0's pose depends on the worker's speed);
    # 40 candidates at one per 15 frames, the map capped by the 32-keyframe budget
    assert len(published) >= 599 and keyframes == 32
    for out in reads:
        assert len(out) >= 9  # the readers interleaved with the writer (checkpoints)
        order = []
        for pose in out:
            assert pose.is_rigid(atol=1e-9)  # not torn
            index = published.get(pose.T_world_cam.tobytes())
            assert index is not None  # exactly a pose the tracker published
            order.append(index)
        assert order == sorted(order)  # never out of order
    assert statuses and max(statuses) <= 32
    assert not any(thread.is_alive() for thread in threads)
