"""Maps through the Tracker: save, reload (also in a new process), relocalise, grow, refuse.

The saved sessions and the child process live in ``saved_maps``. The file format's own
guarantees (atomic writes, fuzzing, crash safety) are tested in ``tests/io``; here only what they
mean for a tracker.
"""

from __future__ import annotations

import errno
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import (
    ConfigError,
    MapCorruptedError,
    MapError,
    MapIOError,
    MapModelMismatchError,
    StateError,
)
from kvtracker_sdk.geometry.sim3 import umeyama_alignment
from kvtracker_sdk.io.files.trajectory import read_tum
from kvtracker_sdk.io.map_file import map_file
from kvtracker_sdk.io.map_file.map_file import MapInfo, load_map, read_map_info
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import StateReason, TrackingState
from tests.helpers import dev_dependency
from tests.io.map_factory import map_digest
from tests.tracking.gated_backend import GatedBackend
from tests.tracking.saved_maps import (
    SIM,
    Saved,
    reload_in_new_process,
    save_pi3_session,
    save_simulated_session,
    sim_backend,
)
from tests.tracking.sim_session import SIZE, WAIT_S, Session, drive, make_tracker

_S, _R = TrackingState, StateReason


@pytest.fixture(scope="module")
def sim_saved(tmp_path_factory: pytest.TempPathFactory) -> Saved:
    return save_simulated_session(tmp_path_factory.mktemp("sim"))


@pytest.fixture(scope="module")
def pi3_saved(tmp_path_factory: pytest.TempPathFactory) -> Saved:
    return save_pi3_session(tmp_path_factory.mktemp("pi3"))


# ---------------------------------------------------------------------------------- round trip
ROUND_TRIP = "test_round_trip_in_a_new_process"


@pytest.fixture(scope="module")
def reloaded() -> Callable[[str, pytest.FixtureRequest], dict[str, Any]]:
    """``reloaded(saved_fixture, request)``: that session's report from ``reload_in_new_process``. The
    first call reloads, in ONE child, every saved session a selected round-trip test needs
    (a child with torch costs ~2 s of CPU); a session whose fixture skips is left out."""
    reports: dict[str, dict[str, Any]] = {}

    def report(wanted: str, request: pytest.FixtureRequest) -> dict[str, Any]:
        if wanted not in reports:
            names = [wanted] + [
                name for name in ("sim_saved", "pi3_saved")
                if name != wanted
                and any(item.name == f"{ROUND_TRIP}[{name}]" for item in request.session.items)
            ]  # fmt: skip
            sessions: dict[str, Saved] = {}
            for name in names:
                try:
                    sessions[name] = request.getfixturevalue(name)
                except pytest.skip.Exception:
                    if name == wanted:
                        raise
            reports.update(zip(sessions, reload_in_new_process(*sessions.values()), strict=True))
        return reports[wanted]

    return report


@pytest.mark.parametrize(
    "saved_fixture", ["sim_saved", pytest.param("pi3_saved", marks=pytest.mark.slow)]
)
def test_round_trip_in_a_new_process(
    saved_fixture: str,
    reloaded: Callable[[str, pytest.FixtureRequest], dict[str, Any]],
    request: pytest.FixtureRequest,
) -> None:
    saved: Saved = request.getfixturevalue(saved_fixture)
    report = reloaded(saved_fixture, request)
    assert report["digest"] == map_digest(saved.keyframe_map)  # bit-identical K/V and keyframes
    assert report["config"] == saved.config.to_dict()  # the saved configuration by default
    assert report["status"] == ["RELOCALIZING", "MAP_LOADED"]
    assert report["states"] == ["RELOCALIZING"] * saved.keyframe_map.num_keyframes
    # the saved gauge is restored: the same world poses as against the map before saving
    np.testing.assert_allclose(
        np.array(report["poses"]), np.stack(saved.tracked), rtol=0, atol=1e-6
    )


def test_simulated_keyframe_images_track_to_their_saved_poses(sim_saved: Saved) -> None:
    """Without pass jitter a keyframe image tracks exactly to its pose: with the round trip
    above, a reloaded map returns the saved keyframe poses themselves (Pi3's small random
    weights track a keyframe image ~0.02 away from its mapped pose, so there the reference is
    the pose tracked before saving)."""
    saved_poses = sim_saved.keyframe_map.poses()
    np.testing.assert_allclose(np.stack(sim_saved.tracked), saved_poses, rtol=0, atol=1e-6)


# ---------------------------------------------------------------------------------- after loading
def test_a_loaded_map_relocalises_then_grows_in_the_saved_world_frame(tmp_path: Path) -> None:
    options = {"seed": 7, "translation_noise_m": 0.01, "pass_jitter": 0.1}
    backend = sim_backend(**options)
    path = tmp_path / "scene.kvmap"
    with make_tracker(backend, keyframing={"interval_frames": 40}) as first:
        original = drive(first, backend, stop=121)  # keyframes 0-3 at frames 0, 40, 80, 120
        first.save_map(path)
    estimate = np.array([r.pose.translation for r in original.results])
    truth = np.array([t[:3, 3] for t in original.truth])
    to_truth = umeyama_alignment(estimate, truth)  # the saved world frame -> ground truth, once

    twin = sim_backend(**options)  # another instance of the same function
    with Tracker.from_map(path, twin) as second:
        assert (second.state, second.reason) == (_S.RELOCALIZING, _R.MAP_LOADED)
        session = drive(second, twin, start=100, stop=200, session=Session().listen(second))
        final_ids = second.map_status.keyframe_ids
    assert session.moves()[0] == ("RELOCALIZING", "TRACKING", "RELOCALIZED", 2)  # 3rd frame
    assert [r.pose_valid for r in session.results[:3]] == [False, False, True]
    # new keyframes: full rebuilds from the stored keyframe images, ids after the saved ones; the
    # interval counts from the first confident frame (not a keyframe at once)
    assert [r.frame_index for r in session.results if r.is_keyframe] == [42, 82]
    assert session.results[42].keyframe_id == 4 and final_ids[:5] == (0, 1, 2, 3, 4)
    rebuild = session.maps[0]
    assert rebuild.cause == "keyframe" and set(rebuild.corrections) == {0, 1, 2, 3}
    assert rebuild.max_translation_correction < 0.03  # the world frame stays where it was
    # every pose, relocalising ones included, is in the saved world frame: the original
    # alignment maps them onto the ground truth within 1.5x the injected noise (RMS 1.7 cm;
    # measured 2.0 cm: the alignment fitted on frames 0-120 is extrapolated up to frame 200)
    moved = to_truth.apply_to_points(np.array([r.pose.translation for r in session.results]))
    errors = np.linalg.norm(moved - np.array([t[:3, 3] for t in session.truth]), axis=1)
    assert np.sqrt(np.mean(errors**2)) < 1.5 * backend.expected_translation_rmse


@pytest.mark.slow
def test_an_fp32_map_loads_into_a_bf16_backend_of_the_same_weights(pi3_saved: Saved) -> None:
    from kvtracker_sdk.backends.torch_backend import TorchBackend

    bf16 = TorchBackend.from_pretrained(pi3_saved.spec["weights"], dtype=torch.bfloat16)
    assert bf16.info.fingerprint == pi3_saved.info.fingerprint
    with Tracker.from_map(pi3_saved.path, bf16) as tracker:
        loaded = tracker.keyframe_map
        assert loaded is not None and loaded.cache.dtype == torch.bfloat16  # converted on loading
        saved_keys = pi3_saved.keyframe_map.cache.keys(3)
        assert torch.equal(loaded.cache.keys(3), saved_keys.to(torch.bfloat16))
        pose = tracker.push_frame(loaded.keyframes[1].image).pose
    bf16.close()
    assert pose is not None
    # bf16 rounding (8 bits of mantissa) moves the pose a little, not wholesale
    assert np.abs(pose.T_world_cam - pi3_saved.tracked[1]).max() < 0.05  # measured 0.009


@pytest.mark.slow
def test_a_map_of_another_family_is_refused_naming_both(pi3_saved: Saved) -> None:
    simulated = sim_backend()
    with pytest.raises(MapModelMismatchError) as refused:
        Tracker.from_map(pi3_saved.path, simulated)
    message = str(refused.value)
    assert pi3_saved.info.fingerprint in message and simulated.info.fingerprint in message
    assert "family 'pi3' vs 'simulated'" in message


# ---------------------------------------------------------------------------------- refusals
def _flip_a_data_byte(data: bytes) -> bytes:
    damaged = bytearray(data)
    damaged[-1000] ^= 0x10  # inside the tensor data: only the checksums can tell
    return bytes(damaged)


DAMAGES: dict[str, Callable[[bytes], bytes]] = {
    "flipped byte": _flip_a_data_byte,
    "truncated": lambda data: data[: len(data) // 2],
    "none": lambda data: data,
}


@pytest.mark.parametrize(
    ("damage", "tracker_seed", "error"),
    [
        ("flipped byte", 4, MapCorruptedError),
        ("truncated", 4, MapCorruptedError),
        pytest.param("none", 5, MapModelMismatchError, id="another model"),
    ],
)
def test_a_refused_map_leaves_the_tracker_untouched(
    sim_saved: Saved, tmp_path: Path, damage: str, tracker_seed: int, error: type[MapError]
) -> None:
    bad = tmp_path / "bad.kvmap"
    bad.write_bytes(DAMAGES[damage](sim_saved.path.read_bytes()))
    backend = sim_backend(seed=tracker_seed)
    with make_tracker(backend, keyframing={"interval_frames": 20}) as tracker:
        session = drive(tracker, backend, stop=30)
        before = (tracker.state, tracker.reason, tracker.keyframe_map, tracker.get_pose())
        events = len(session.states) + len(session.maps)
        with pytest.raises(error):
            tracker.initialize(map=bad)
        after = (tracker.state, tracker.reason, tracker.keyframe_map, tracker.get_pose())
        assert all(x is y for x, y in zip(before, after, strict=True))
        assert len(session.states) + len(session.maps) == events
        result = drive(tracker, backend, start=30, stop=31, session=session).results[-1]
        assert result.state is _S.TRACKING and result.pose_valid
    with pytest.raises(error):
        Tracker.from_map(bad, backend)


def test_the_config_is_the_saved_one_unless_overridden(sim_saved: Saved) -> None:
    backend, path = sim_backend(), sim_saved.path
    with Tracker.from_map(path, backend) as tracker:
        assert tracker.config == sim_saved.config
    changes = {"relocalization": {"recover_after": 7}}
    with Tracker.from_map(path, backend, config=changes) as tracker:
        assert tracker.config.relocalization.recover_after == 7
        assert tracker.config.keyframing == sim_saved.config.keyframing  # the rest is kept
    explicit = TrackerConfig(resolution=224)
    with Tracker.from_map(path, backend, config=explicit) as tracker:
        assert tracker.config is explicit
    with pytest.raises(ConfigError, match="saved in scene mode"):
        Tracker.from_map(path, backend, config={"mode": "object"})
    with pytest.raises(MapModelMismatchError, match=r"resolution 224 \(model input 196x252\)"):
        Tracker.from_map(path, backend, config={"resolution": 308})
    with pytest.raises(ConfigError):
        Tracker.from_map(path, backend, config={"no_such_field": 1})


def test_initialize_with_a_map_relocalises_a_running_tracker(sim_saved: Saved) -> None:
    backend = sim_backend()
    with make_tracker(backend, relocalization={"recover_after": 2}) as tracker:
        session = drive(tracker, backend, stop=5)  # its own map: keyframe 0
        tracker.initialize(map=sim_saved.path)
        assert session.moves()[-1] == ("TRACKING", "RELOCALIZING", "MAP_LOADED", None)
        loaded = tracker.keyframe_map
        assert loaded is not None and map_digest(loaded) == map_digest(sim_saved.keyframe_map)
        assert tracker.get_pose() is None and session.maps[-1].cause == "loaded"
        assert tracker.config.relocalization.recover_after == 2  # the tracker keeps its config
        drive(tracker, backend, start=70, stop=72, session=session)
        # relocalised; the keyframe interval counts from here (no keyframe at once)
        assert tracker.state is _S.TRACKING and session.results[-1].keyframe_id is None
        tracker.initialize()
        assert (tracker.state, tracker.reason, tracker.keyframe_map) == (_S.INIT, _R.RESET, None)


# ---------------------------------------------------------------------------------- saving
def test_save_map_refuses_without_a_map_and_waits_for_a_pending_rebuild(tmp_path: Path) -> None:
    backend = GatedBackend(orbit(**SIM["orbit"]), **SIM["options"])
    backend.hold(2)  # keyframe 1's mapping pass waits until the test releases it
    path = tmp_path / "scene.kvmap"
    config = {"threading": {"async_mapping": True}, "keyframing": {"interval_frames": 10}}
    with make_tracker(backend, **config) as tracker:
        with pytest.raises(StateError, match="no map"):
            tracker.save_map(path)
        with pytest.raises(StateError, match="no map"):
            tracker.export.trajectory(tmp_path / "keyframes.txt")
        assert os.listdir(tmp_path) == []
        frames = backend.frames(SIZE, stop=12, textured=False)
        tracker.push_frame(next(frames).image)
        assert tracker.wait_for_map(timeout=WAIT_S)  # the first map (pass 1) is installed
        for frame in frames:  # frame 10 proposes keyframe 1: pass 2, held at the gate
            tracker.push_frame(frame.image)
        assert backend.started(2)
        status = tracker.map_status
        assert status.rebuilding and status.keyframe_ids == (0,)

        saved: list[MapInfo] = []
        saver = threading.Thread(target=lambda: saved.append(tracker.save_map(path)))
        saver.start()
        saver.join(timeout=0.2)  # not synchronisation: only shows the save is still waiting
        assert saver.is_alive() and not path.exists()
        backend.release(2)
        saver.join(timeout=WAIT_S)
        assert not saver.is_alive() and not tracker.map_status.rebuilding
    assert saved[0].keyframe_ids == (0, 1) and read_map_info(path).keyframe_ids == (0, 1)


def test_a_failed_save_keeps_the_previous_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend = sim_backend()
    path = tmp_path / "scene.kvmap"

    def disk_full(handle: BinaryIO, tensors: object, metadata: object, **_: object) -> int:
        handle.write(b"half a map")
        raise OSError(errno.ENOSPC, "No space left on device")

    with make_tracker(backend, keyframing={"interval_frames": 10}) as tracker:
        drive(tracker, backend, stop=11)
        first = tracker.save_map(path)
        drive(tracker, backend, start=11, stop=21)
        with monkeypatch.context() as patch:
            patch.setattr(map_file, "write_safetensors", disk_full)
            with pytest.raises(MapIOError, match="No space left"):
                tracker.save_map(path)
        assert os.listdir(tmp_path) == ["scene.kvmap"]  # no temporary file left behind
        kept = load_map(path)  # checksums verified
        assert kept.info.keyframe_ids == first.keyframe_ids == (0, 1)
        assert tracker.save_map(path).keyframe_ids == (0, 1, 2)


# ---------------------------------------------------------------------------------- exports
def test_exports_write_the_map_in_its_world_frame(sim_saved: Saved, tmp_path: Path) -> None:
    plyfile = dev_dependency("plyfile")
    with make_tracker(sim_backend()) as tracker:
        with pytest.raises(StateError, match="no map"):
            tracker.export.point_cloud(tmp_path / "none.ply")
        tracker.initialize(map=sim_saved.path)
        poses = tracker.export.trajectory(tmp_path / "keyframes.txt")
        points = tracker.export.point_cloud(tmp_path / "cloud.ply", min_confidence=0.75)
    trajectory = read_tum(tmp_path / "keyframes.txt")
    assert poses == len(trajectory) == 4
    np.testing.assert_allclose(trajectory.poses, sim_saved.keyframe_map.poses(), atol=1e-12)
    vertices = plyfile.PlyData.read(str(tmp_path / "cloud.ply"))["vertex"]
    assert 0 < points == len(vertices) < 4 * SIZE[0] * SIZE[1]  # low confidence filtered out
