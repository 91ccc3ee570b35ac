"""``SimulatedBackend``: the Backend contract driven by a ground-truth trajectory, for tests and
for demos without weights.

It behaves like Pi3 where the tracker can tell: every mapping pass returns its poses, local points
and depths in its own random Sim(3) frame and scale; poses carry noise; confidence can be dropped
over chosen frame ranges (loss) or in mapping passes only (keyframe rejection), and, with
``object_in_view``, on tracked frames that do not show the whole object unmasked (as a network
cannot place a camera against an object's map without seeing the object). It returns a real
``KVCache`` — the tracker exercises the same cache code as with a network — whose tokens carry
what a stateless backend needs to track against it: the pass's hidden Sim(3) and the frame index
of each keyframe.

Noise model: a frame's pose error is drawn once per frame index (a network shown the same image
answers nearly the same), so the same keyframe has the same error in every pass, plus a smaller
per-pass ``pass_jitter`` (relative to the frame noise) because a rebuild sees a different context.
``translation_noise_m`` is the standard deviation per axis: the expected translation RMSE of the
tracked poses is ``sqrt(3) * translation_noise_m`` (``expected_translation_rmse``).

Quick start::

    backend = SimulatedBackend.from_tum("groundtruth.txt", loss_segments=[(900, 960)])
    with Tracker(TrackerConfig(), backend) as tracker:
        for frame in backend.frames(size=(240, 320)):
            result = tracker.push_frame(frame.image, timestamp=frame.timestamp)
"""

from __future__ import annotations

import hashlib
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult
from kvtracker_sdk.backends.simulated_scene import (
    GroundTruth,
    SimulatedCamera,
    SimulatedFrame,
    SimulatedScene,
    camera_matrix,
    decode_frame_index,
    pixel_rays,
)
from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.errors import BackendError, CacheError, ConfigError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.types import HeadSet

__all__ = ["SimulatedBackend"]

_LAYOUT = CacheLayout(block_indices=(1, 3), num_heads=1, head_dim=16)
_PATCH = 14
_EXTRA_TOKENS = 1
_LOSS_NOISE_FACTOR = 20.0  # a lost frame's pose is garbage, as a network's would be
_DEPTH_CACHE_FRAMES = 256


def _in_segments(index: int, segments: Sequence[tuple[int, int]]) -> bool:
    return any(start <= index < stop for start, stop in segments)


class SimulatedBackend:
    """A Backend whose outputs come from ``ground_truth`` through noise and hidden Sim(3) frames."""

    def __init__(
        self,
        ground_truth: GroundTruth,
        *,
        scene: SimulatedScene | None = None,
        translation_noise_m: float = 0.01,
        rotation_noise_deg: float = 0.3,
        pass_jitter: float = 0.1,
        confidence: float = 0.8,
        loss_segments: Sequence[tuple[int, int]] = (),
        lost_confidence: float = 0.1,
        map_confidence_drops: Sequence[tuple[int, int]] = (),
        seed: int = 0,
        camera_size: tuple[int, int] | None = None,
        object_in_view: bool = False,
    ) -> None:
        if min(translation_noise_m, rotation_noise_deg, pass_jitter) < 0:
            raise ConfigError("noise levels must be >= 0")
        if not (0.0 < lost_confidence <= 1.0 and 0.0 < confidence <= 1.0):
            raise ConfigError(f"confidences must be in (0, 1], got {confidence}, {lost_confidence}")
        self.ground_truth = ground_truth
        self.scene = scene if scene is not None else SimulatedScene.around(ground_truth.poses)
        self.translation_noise_m = float(translation_noise_m)
        self.rotation_noise_rad = float(np.radians(rotation_noise_deg))
        self.pass_jitter = float(pass_jitter)
        self.confidence = float(confidence)
        self.loss_segments = tuple((int(a), int(b)) for a, b in loss_segments)
        self.lost_confidence = float(lost_confidence)
        self.map_confidence_drops = tuple((int(a), int(b)) for a, b in map_confidence_drops)
        self.seed = int(seed)
        # (H, W) of the rendered frames: model-resolution rays then follow their resize exactly
        self.camera_size = None if camera_size is None else (int(camera_size[0]), int(camera_size[1]))
        # like a network tracking against an object's map: confident only when the (unmasked)
        # image shows the whole object
        self.object_in_view = bool(object_in_view)
        # a frame's error is fixed (drawn once per frame index); passes add jitter on top
        rng = np.random.default_rng((self.seed, 0))
        self._frame_noise = rng.standard_normal((len(ground_truth), 6))
        self._lock = threading.Lock()
        self._passes = 0
        self._hidden: weakref.WeakKeyDictionary[KVCache, Sim3] = weakref.WeakKeyDictionary()
        self._depths: OrderedDict[tuple[int, int, int], np.ndarray] = OrderedDict()
        self._rays: dict[tuple[int, int], np.ndarray] = {}
        self._patterns: dict[tuple[int, int], np.ndarray] = {}
        self._pattern_means: dict[tuple[int, int], float] = {}
        self._info = self._make_info()

    @classmethod
    def from_tum(
        cls, path: str | Path, *, rate_hz: float = 30.0, **options: object
    ) -> SimulatedBackend:
        """A backend over a TUM ``groundtruth.txt`` resampled to ``rate_hz`` (options: __init__)."""
        return cls(GroundTruth.from_tum(path, rate_hz=rate_hz), **options)  # type: ignore[arg-type]

    # ------------------------------------------------------------------ Backend protocol
    @property
    def info(self) -> BackendInfo:
        return self._info

    @property
    def expected_translation_rmse(self) -> float:
        """RMS norm of the injected translation error of a confidently tracked frame."""
        return float(np.sqrt(3.0) * self.translation_noise_m)

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        """Mapping pass over uint8 [N, H, W, 3] frames rendered by ``SimulatedCamera``."""
        start = time.perf_counter()
        images = self._check_images(images)
        size = (int(images.shape[1]), int(images.shape[2]))
        frames = [self._decode(image) for image in images]
        with self._lock:
            pass_id = self._passes
            self._passes += 1
        hidden = self._hidden_sim3(pass_id)
        jitter = np.random.default_rng((self.seed, 2, pass_id)).standard_normal((len(frames), 6))
        deltas = self._frame_noise[frames] + self.pass_jitter * jitter
        poses = hidden.apply_to_pose(self._noisy_poses(frames, deltas))
        pattern = self._confidence_pattern(size)
        confidence = np.empty((len(frames), *size), dtype=np.float32)
        points = np.empty((len(frames), *size, 3), dtype=np.float32)
        rays = self._rays_for(size)
        for i, frame in enumerate(frames):
            np.multiply(pattern, self._map_confidence(frame), out=confidence[i])
            depth = self._depth(frame, size) * np.float32(hidden.scale)
            np.multiply(rays, depth[..., None], out=points[i])
        cache = self._make_cache(frames, pass_id, hidden, size)
        elapsed = {"map": (time.perf_counter() - start) * 1e3}
        return MapResult(poses, confidence, points, cache, elapsed)

    def track(
        self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
    ) -> TrackResult:
        """The frame's pose in the cache's raw frame (the hidden Sim(3) stored in the cache)."""
        start = time.perf_counter()
        image = self._check_images(image[None])[0]
        frame = self._decode(image)
        hidden = self._hidden_frame(cache)
        lost = _in_segments(frame, self.loss_segments) or (
            self.object_in_view and not self._shows_object(image, frame))
        delta = self._frame_noise[[frame]] * (_LOSS_NOISE_FACTOR if lost else 1.0)
        pose = hidden.apply_to_pose(self._noisy_poses([frame], delta)[0])
        level = self.lost_confidence if lost else self.confidence
        size = (int(image.shape[0]), int(image.shape[1]))
        pattern = self._confidence_pattern(size)
        confidence, confidence_map, points = None, None, None
        if heads is not HeadSet.CAMERA:
            confidence = float(level * self._pattern_means[size])
            confidence_map = pattern * np.float32(level)
        if heads is HeadSet.ALL:
            depth = self._depth(frame, size) * np.float32(hidden.scale)
            points = self._rays_for(size) * depth[..., None]
        elapsed = {"track": (time.perf_counter() - start) * 1e3}
        return TrackResult(pose, confidence, confidence_map, points, elapsed)

    def close(self) -> None:
        """Nothing to release (idempotent)."""

    def model_K(self, size: tuple[int, int]) -> np.ndarray:
        """3x3 K of the model-resolution images (H, W) = ``size`` that this backend answers for:
        ``camera_matrix(camera_size)`` carried through the resize to ``size`` when
        ``camera_size`` is set, else ``camera_matrix(size)``."""
        if self.camera_size is None or self.camera_size == tuple(size):
            return camera_matrix(size)
        return PixelTransform.resize(self.camera_size, size).apply_to_K(
            camera_matrix(self.camera_size)
        )

    # ------------------------------------------------------------------ demo helpers
    def camera(
        self, size: tuple[int, int] = (240, 320), *, textured: bool = True
    ) -> SimulatedCamera:
        """A camera rendering this backend's trajectory and scene at ``size`` = (H, W)."""
        return SimulatedCamera(self.ground_truth, self.scene, size=size, textured=textured)

    def frames(
        self,
        size: tuple[int, int] = (240, 320),
        *,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        textured: bool = True,
        with_mask: bool = False,
    ) -> Iterator[SimulatedFrame]:
        """Rendered frames ``start:stop:step`` (image, timestamp, ground-truth pose, mask)."""
        return self.camera(size, textured=textured).frames(start, stop, step, with_mask=with_mask)

    def read_cache(self, cache: KVCache) -> tuple[Sim3, tuple[int, ...]]:
        """(hidden Sim(3) of the pass that made ``cache``, frame index of each cached keyframe)."""
        if cache.layout != _LAYOUT or cache.num_keyframes == 0:
            raise CacheError(f"not a simulated cache: {cache!r}")
        with cache.lock:
            values = cache.values(0)[0, 0, 0].numpy().astype(np.float64)
            keys = cache.keys(0)[0, 0, :: cache.tokens_per_frame, 0].numpy()
        hidden = Sim3(values[:9].reshape(3, 3), values[9:12], float(values[12]))
        return hidden, tuple(int(k) for k in keys)

    # ------------------------------------------------------------------ internals
    def _make_info(self) -> BackendInfo:
        config = repr((_LAYOUT, _PATCH, _EXTRA_TOKENS)).encode()
        content = hashlib.sha256(self.ground_truth.poses.tobytes())
        content.update(repr((
            self.scene.room_min.tolist(), self.scene.room_max.tolist(),
            self.scene.object_centre.tolist(), self.scene.object_radius,
            self.translation_noise_m, self.rotation_noise_rad, self.pass_jitter, self.confidence,
            self.loss_segments, self.lost_confidence, self.map_confidence_drops, self.seed,
            *(() if self.camera_size is None else (self.camera_size,)),
            *self._solids(),
            *(("object_in_view",) if self.object_in_view else ()),
        )).encode())
        return BackendInfo(
            backend="simulated",
            model="simulated",
            family="simulated",
            config_hash=hashlib.sha256(config).hexdigest()[:16],
            weights_fingerprint=content.hexdigest()[:16],
            patch_size=_PATCH,
            extra_tokens_per_frame=_EXTRA_TOKENS,
            layout=_LAYOUT,
            dtype="float64",
        )

    def _shows_object(self, image: np.ndarray, frame: int) -> bool:
        """Whether ``image`` (model resolution, black where masked) shows the whole object: its
        true silhouette box lies inside the image and at least half of it is unmasked."""
        size = (int(image.shape[0]), int(image.shape[1]))
        box = self.scene.object_box(self.ground_truth.poses[frame], size, self.model_K(size))
        if box is None or box[0] <= 0 or box[1] <= 0 or box[2] >= size[1] or box[3] >= size[0]:
            return False
        window = image[int(box[1]) : int(np.ceil(box[3])), int(box[0]) : int(np.ceil(box[2]))]
        return bool(window.any(axis=-1).mean() >= 0.5)

    def _solids(self) -> tuple[object, ...]:
        """The scene's cuboids and planes as plain values (none for the sphere in a room: its
        fingerprint stays what it was)."""
        scene = self.scene
        shapes = [scene.object_shape, *scene.others]
        solids = tuple(
            (s.centre.tolist(), s.half_extents.tolist(), s.yaw) for s in shapes if s is not None
        ) + tuple((p.point.tolist(), p.normal.tolist()) for p in scene.planes)
        return (solids,) if solids else ()

    def _check_images(self, images: np.ndarray) -> np.ndarray:
        if (
            not isinstance(images, np.ndarray)
            or images.dtype != np.uint8
            or images.ndim != 4
            or images.shape[-1] != 3
            or min(images.shape[1:3]) < _PATCH
            or images.shape[0] == 0
        ):
            shape = getattr(images, "shape", None)
            raise BackendError(f"need uint8 [N, H, W, 3] images (H, W >= {_PATCH}), got {shape}")
        return images

    def _decode(self, image: np.ndarray) -> int:
        frame = decode_frame_index(image)
        if frame >= len(self.ground_truth):
            raise BackendError(
                f"the image shows frame {frame}, the trajectory has {len(self.ground_truth)} frames"
            )
        return frame

    def _hidden_sim3(self, pass_id: int) -> Sim3:
        """A fresh random frame per pass: any rotation, metres-scale offset, scale in [0.2, 5]."""
        rng = np.random.default_rng((self.seed, 1, pass_id))
        rotation = Rotation.random(random_state=rng).as_matrix()
        return Sim3(rotation, rng.normal(scale=2.0, size=3), float(np.exp(rng.uniform(-1.6, 1.6))))

    def _noisy_poses(self, frames: Sequence[int], deltas: np.ndarray) -> np.ndarray:
        """[N, 4, 4] ground truth of ``frames`` with errors ``deltas`` [N, 6] in standard units
        (rotation vector in the camera frame, then the centre's offset in the world frame)."""
        poses = np.array(self.ground_truth.poses[list(frames)], dtype=np.float64)
        turns = Rotation.from_rotvec(deltas[:, :3] * self.rotation_noise_rad).as_matrix()
        poses[:, :3, :3] = poses[:, :3, :3] @ turns
        poses[:, :3, 3] += deltas[:, 3:] * self.translation_noise_m
        return poses

    def _hidden_frame(self, cache: KVCache) -> Sim3:
        """The hidden Sim(3) of ``cache`` (memoised: every keyframe block carries the same one)."""
        hidden = self._hidden.get(cache)
        if hidden is None:
            hidden = self._hidden[cache] = self.read_cache(cache)[0]
        return hidden

    def _map_confidence(self, frame: int) -> float:
        dropped = _in_segments(frame, self.loss_segments) or _in_segments(
            frame, self.map_confidence_drops
        )
        return self.lost_confidence if dropped else self.confidence

    def _rays_for(self, size: tuple[int, int]) -> np.ndarray:
        """[H, W, 3] float32 camera rays with z = 1."""
        rays = self._rays.get(size)
        if rays is None:
            rays = self._rays[size] = pixel_rays(size, self.model_K(size)).astype(np.float32)
        return rays

    def _confidence_pattern(self, size: tuple[int, int]) -> np.ndarray:
        """[H, W] in [0.7, 1]: confidence falls off towards the image border, like a network's."""
        pattern = self._patterns.get(size)
        if pattern is None:
            rays = self._rays_for(size)
            radius = np.hypot(rays[..., 0], rays[..., 1])
            pattern = (1.0 - 0.3 * radius / radius.max()).astype(np.float32)
            self._patterns[size] = pattern
            self._pattern_means[size] = float(pattern.mean())
        return pattern

    def _depth(self, frame: int, size: tuple[int, int]) -> np.ndarray:
        """Ground-truth depth [H, W] float32 (metres) of a frame: ray cast once, kept in an LRU."""
        key = (frame, *size)
        with self._lock:
            depth = self._depths.get(key)
            if depth is not None:
                self._depths.move_to_end(key)
                return depth
        depth64, _ = self.scene.depth(
            self.ground_truth.poses[frame], pixel_rays(size, self.model_K(size))
        )
        depth = depth64.astype(np.float32)
        with self._lock:
            self._depths[key] = depth
            while len(self._depths) > _DEPTH_CACHE_FRAMES:
                self._depths.popitem(last=False)
        return depth

    def _make_cache(
        self, frames: list[int], pass_id: int, hidden: Sim3, size: tuple[int, int]
    ) -> KVCache:
        """K/V with, per keyframe, token 0 = (frame index, pass) in K and the hidden Sim(3) in V.

        Keyframes are appended one small block at a time into a cache preallocated for all of
        them: large tensor copies run on torch's thread pool, which stalls on a busy machine.
        """
        tokens = self._info.tokens_per_frame(*size)
        cache = KVCache(_LAYOUT, tokens, dtype=torch.float64, capacity_frames=len(frames) + 2)
        record = torch.zeros(_LAYOUT.head_dim, dtype=torch.float64)
        record[:9] = torch.tensor(hidden.rotation.reshape(-1))
        record[9:12] = torch.tensor(hidden.translation)
        record[12] = hidden.scale
        shape = (1, _LAYOUT.num_heads, tokens, _LAYOUT.head_dim)
        for slot, frame in enumerate(frames):
            filler = frame + pass_id * 1e-3  # differs per pass, like a network's K/V
            keys = torch.full(shape, filler, dtype=torch.float64)
            values = -keys
            keys[0, :, 0, :2] = torch.tensor([frame, pass_id], dtype=torch.float64)
            values[0, :, 0] = record
            layers = _LAYOUT.num_layers
            cache.append_keyframe([keys] * layers, [values] * layers, keyframe_id=slot)
        return cache
