"""The world behind ``SimulatedBackend``: a ground-truth trajectory, a simple scene to measure
depth in, and a camera whose images carry their frame index.

* ``GroundTruth``: timestamps and ``T_world_cam`` poses, e.g. TUM fr2_desk's 100 s motion-capture
  trajectory resampled to 30 Hz.
* ``SimulatedScene``: an axis-aligned room around the trajectory plus one sphere (the "object",
  placed where the cameras look). Depth per pixel comes from ray casting, so depth maps, masks and
  object points are geometrically consistent with the poses. ``SimulatedScene.desk`` and
  ``SimulatedScene.wall`` put a cuboid object on a table plane beside a second cuboid of similar
  size (and, for ``wall``, against a wall plane): the case every AR object app starts with.
* Frame code: image pixels carry the frame index in their red and green channels
  (R = 16 + index // 224, G = 16 + index % 224; black, the object-mode background, never encodes
  a frame). A flat code survives resizing, cropping and masking; blue holds an optional texture.

Pinhole intrinsics scale with the image: fx = fy = 0.81 W (TUM's 520 px at 640 px), principal
point at the centre (``camera_matrix``). ``SimulatedBackend(camera_size=(H, W))`` makes the
model-resolution geometry exactly that of resized H x W frames (the resize is not isotropic after
rounding to patches); object-mode crops change the true intrinsics and the simulation ignores
that.
"""

from __future__ import annotations

import functools
import io
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kvtracker_sdk.errors import BackendError, TrajectoryError
from kvtracker_sdk.geometry.se3 import rotation_from_quat_xyzw
from kvtracker_sdk.user_files import read_user_text

__all__ = [
    "Cuboid",
    "GroundTruth",
    "Plane",
    "SimulatedCamera",
    "SimulatedFrame",
    "SimulatedScene",
    "decode_frame_index",
    "encode_frame_index",
    "look_at",
    "camera_matrix",
    "orbit",
    "pixel_rays",
]

_CODE_BASE = 224  # digits per channel
_CODE_OFFSET = 16  # smallest code value: black (masked background) never decodes
MAX_FRAMES = _CODE_BASE * _CODE_BASE
MAX_RESAMPLED_FRAMES = MAX_FRAMES  # a simulated camera cannot number more frames than this
MAX_TRAJECTORY_BYTES = 64 << 20  # ~600k TUM lines; parsing a file costs ~5x its size
FOCAL_PER_WIDTH = 0.81


@dataclass(frozen=True)
class GroundTruth:
    """A camera trajectory: ``timestamps`` [F] seconds, ``poses`` [F, 4, 4] T_world_cam."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        if self.poses.ndim != 3 or self.poses.shape[1:] != (4, 4):
            raise TrajectoryError(f"poses must be [F, 4, 4], got {self.poses.shape}")
        if len(self.timestamps) != len(self.poses) or not 0 < len(self.poses) <= MAX_FRAMES:
            raise TrajectoryError(
                f"need 1..{MAX_FRAMES} poses with one timestamp each, got "
                f"{len(self.poses)} poses and {len(self.timestamps)} timestamps"
            )
        for array in (self.timestamps, self.poses):
            array.setflags(write=False)

    def __len__(self) -> int:
        return len(self.poses)

    @classmethod
    def from_tum(cls, path: str | Path, *, rate_hz: float | None = 30.0) -> GroundTruth:
        """Read a TUM trajectory (``t tx ty tz qx qy qz qw``) and resample it to ``rate_hz``.

        Resampling picks, for each tick of a ``rate_hz`` clock, the nearest recorded pose (the
        motion capture runs at ~300 Hz, a camera at 30 Hz). ``rate_hz=None`` keeps every pose.
        """
        # a FIFO, a device or a huge file is refused before a byte is parsed (user_files)
        text = read_user_text(path, TrajectoryError, what="TUM trajectory",
                              max_bytes=MAX_TRAJECTORY_BYTES)
        try:
            data = np.loadtxt(io.StringIO(text), comments="#", ndmin=2)
        except ValueError as exc:
            raise TrajectoryError(f"cannot read TUM trajectory {path}: {str(exc)[:200]}") from exc
        if data.shape[1] != 8 or not np.all(np.isfinite(data)):
            raise TrajectoryError(f"{path}: expected 8 finite columns, got shape {data.shape}")
        if len(data) == 0:
            raise TrajectoryError(f"{path}: no poses")
        if rate_hz is not None:
            # the resampled count is known before anything is allocated: two poses a year apart
            # would otherwise ask for ~1e9 ticks (tens of GB)
            span = float(data[-1, 0] - data[0, 0])
            ticks_needed = span * rate_hz
            if not (0.0 <= ticks_needed <= MAX_RESAMPLED_FRAMES):
                raise TrajectoryError(
                    f"{path}: time span {span:.6g} s at {rate_hz} Hz gives "
                    f"{ticks_needed:.3g} frames; timestamps must increase and give at most "
                    f"{MAX_RESAMPLED_FRAMES} frames"
                )
            ticks = np.arange(data[0, 0], data[-1, 0], 1.0 / rate_hz)
            if len(ticks) == 0:
                ticks = data[:1, 0]
            nearest = np.clip(np.searchsorted(data[:, 0], ticks), 1, max(1, len(data) - 1))
            if len(data) == 1:
                nearest = np.zeros(len(ticks), dtype=np.intp)
                left_closer = np.zeros(len(ticks), dtype=bool)
            else:
                left_closer = ticks - data[nearest - 1, 0] < data[nearest, 0] - ticks
            data = data[nearest - left_closer.astype(int)]
        if np.any(np.linalg.norm(data[:, 4:8], axis=1) < 1e-12):
            raise TrajectoryError(f"{path}: a zero quaternion")
        poses = np.tile(np.eye(4), (len(data), 1, 1))
        poses[:, :3, :3] = rotation_from_quat_xyzw(data[:, 4:8])
        poses[:, :3, 3] = data[:, 1:4]
        return cls(data[:, 0].copy(), poses)


def look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """T_world_cam of a camera at ``centre`` looking at ``target`` (OpenCV axes, y towards -up)."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    pose[:3, 3] = centre
    return pose


def orbit(
    num_frames: int,
    *,
    radius: float = 1.5,
    height: float = 0.4,
    turns: float = 1.0,
    rate_hz: float = 30.0,
) -> GroundTruth:
    """A camera circling the origin (world z up) at ``radius`` and ``height``, always looking at
    it: the natural object-mode trajectory (``SimulatedScene.around`` puts the sphere there)."""
    if isinstance(num_frames, bool) or not isinstance(num_frames, int | np.integer) or not (
        1 <= num_frames <= MAX_FRAMES
    ):  # checked before the poses are built: 10**9 frames would take tens of GB
        raise TrajectoryError(f"orbit num_frames must be a whole number in 1..{MAX_FRAMES}, "
                              f"got {num_frames!r:.40}")
    if not (math.isfinite(turns) and math.isfinite(radius) and math.isfinite(height)):
        raise TrajectoryError(f"orbit turns, radius and height must be finite, got "
                              f"{turns}, {radius}, {height}")
    angles = np.linspace(0.0, 2.0 * np.pi * turns, num_frames, endpoint=False)
    target, up = np.zeros(3), np.array([0.0, 0.0, 1.0])
    poses = np.stack(
        [
            look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]), target, up)
            for a in angles
        ]
    )
    return GroundTruth(np.arange(num_frames) / rate_hz, poses)


def camera_matrix(size: tuple[int, int]) -> np.ndarray:
    """3x3 K of the simulated camera at ``size`` = (H, W): fx = fy = 0.81 W, principal point at
    the image centre ((W - 1) / 2, (H - 1) / 2 with pixel centres at integers)."""
    height, width = size
    focal = FOCAL_PER_WIDTH * width
    return np.array(
        [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )


def pixel_rays(size: tuple[int, int], K: np.ndarray | None = None) -> np.ndarray:
    """[H, W, 3] camera-frame rays with z = 1 (so a ray times the depth is the local point) of
    an image of ``size`` = (H, W) with intrinsics ``K`` (default: ``camera_matrix(size)``)."""
    height, width = size
    K = camera_matrix(size) if K is None else np.asarray(K, dtype=np.float64)
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    rays = np.empty((height, width, 3))
    rays[..., 0] = u[None, :]
    rays[..., 1] = v[:, None]
    rays[..., 2] = 1.0
    return rays


@dataclass(frozen=True)
class Cuboid:
    """A solid box standing upright in the world (z up): ``centre`` [3] and ``half_extents`` [3]
    in metres, turned by ``yaw`` radians about world z."""

    centre: np.ndarray
    half_extents: np.ndarray
    yaw: float = 0.0

    def __post_init__(self) -> None:
        for name in ("centre", "half_extents"):
            value = np.array(getattr(self, name), dtype=np.float64, copy=True)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def rotation(self) -> np.ndarray:
        """3x3 R_world_box."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> np.ndarray:
        """Edge lengths [3] along the box's own axes."""
        return 2.0 * self.half_extents

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere (half the diagonal)."""
        return float(np.linalg.norm(self.half_extents))

    def corners(self) -> np.ndarray:
        """[8, 3] world corners."""
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return (signs * self.half_extents) @ self.rotation.T + self.centre

    def hit(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """[...] ray parameter of the first hit of rays ``origin + t * directions`` (world),
        inf where a ray misses or starts inside (slab method in the box's own frame)."""
        R = self.rotation
        o = R.T @ (origin - self.centre)
        d = directions @ R  # world -> box frame, per ray
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-self.half_extents - o) / d
            t2 = (self.half_extents - o) / d
        t1 = np.where(np.isnan(t1), -np.inf, t1)
        t2 = np.where(np.isnan(t2), np.inf, t2)
        near = np.minimum(t1, t2).max(axis=-1)
        far = np.maximum(t1, t2).min(axis=-1)
        return np.where((near <= far) & (near > 0), near, np.inf)

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """[N] unsigned distance (metres) of world ``points`` [N, 3] to the box's surface."""
        local = (np.asarray(points, dtype=np.float64) - self.centre) @ self.rotation
        q = np.abs(local) - self.half_extents
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return np.abs(outside + inside)


@dataclass(frozen=True)
class Plane:
    """An infinite solid half-space: points ``x`` with ``normal . (x - point) < 0`` are inside
    (``normal`` [3], unit, points out of the solid: a table top's up, a wall's face)."""

    point: np.ndarray
    normal: np.ndarray

    def __post_init__(self) -> None:
        normal = np.array(self.normal, dtype=np.float64)
        normal /= np.linalg.norm(normal)
        for name, value in (("point", np.array(self.point, dtype=np.float64)), ("normal", normal)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def hit(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """[...] ray parameter where rays from ``origin`` (outside the solid) enter it; inf where
        they run away from it."""
        towards = directions @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.point - origin) @ self.normal / towards
        return np.where((towards < 0) & (t > 0), t, np.inf)


@dataclass(frozen=True)
class SimulatedScene:
    """A box room [room_min, room_max] and a sphere (centre, radius), all in metres (world).

    With ``object_shape`` the object is that cuboid instead (``object_centre`` and
    ``object_radius`` then give its centre and bounding sphere); ``others`` are more cuboids (not
    the object) and ``planes`` solid half-spaces (a table, a wall) inside the room.
    """

    room_min: np.ndarray
    room_max: np.ndarray
    object_centre: np.ndarray
    object_radius: float
    object_shape: Cuboid | None = None
    others: tuple[Cuboid, ...] = ()
    planes: tuple[Plane, ...] = ()

    @classmethod
    def around(
        cls, poses: np.ndarray, *, margin: float = 2.0, radius: float = 0.3
    ) -> SimulatedScene:
        """A room enclosing the trajectory by ``margin`` and a sphere where the optical axes meet.

        The sphere centre is the least-squares point closest to every camera's optical axis.
        """
        centres = poses[:, :3, 3]
        axes = poses[:, :3, 2]
        projector = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # I - a a^T per camera
        target = np.linalg.solve(projector.sum(0), np.einsum("nij,nj->i", projector, centres))
        return cls(centres.min(0) - margin, centres.max(0) + margin, target, radius)

    @classmethod
    def desk(cls, poses: np.ndarray, *, wall: bool = False, margin: float = 2.0) -> SimulatedScene:
        """An object on a desk where the cameras look (world z up): a 12 x 9 x 16 cm cuboid
        standing on a table plane, and a second cuboid of similar size (10 x 10 x 13 cm) beside
        it, 10 cm or more away. ``wall``: a wall plane 2 cm behind the object (on its +y side;
        cameras stay on the -y side) and the second object beside it along the wall."""
        around = cls.around(poses, margin=margin)
        centre = around.object_centre
        half = np.array([0.06, 0.045, 0.08])
        table_z = centre[2] - half[2]
        other_half = np.array([0.05, 0.05, 0.065])
        # bounding circles 7.5 cm and 7.1 cm in radius + a 10 cm gap: never closer than 10 cm
        spacing = float(np.hypot(*half[:2]) + np.hypot(*other_half[:2]) + 0.10)
        direction = np.array([1.0, 0.0]) if wall else np.array([0.5, np.sqrt(3.0) / 2.0])
        other_centre = np.array([*(centre[:2] + spacing * direction), table_z + other_half[2]])
        planes = [Plane(np.array([0.0, 0.0, table_z]), np.array([0.0, 0.0, 1.0]))]
        if wall:
            planes.append(Plane(np.array([0.0, centre[1] + half[1] + 0.02, 0.0]),
                                np.array([0.0, -1.0, 0.0])))
        shape = Cuboid(centre, half, 0.0 if wall else 0.3)
        return cls(around.room_min, around.room_max, centre, shape.radius, shape,
                   (Cuboid(other_centre, other_half, 0.0 if wall else -0.4),), tuple(planes))

    def object_surface_distance(self, points: np.ndarray) -> np.ndarray:
        """[N] distance (metres) of world ``points`` [N, 3] to the object's true surface."""
        points = np.asarray(points, dtype=np.float64)
        if self.object_shape is not None:
            return self.object_shape.surface_distance(points)
        return np.abs(np.linalg.norm(points - self.object_centre, axis=1) - self.object_radius)

    def depth(self, T_world_cam: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth [H, W] metres along camera z, object mask [H, W]) by ray casting ``rays``."""
        R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
        directions = rays @ R.T  # world-frame ray directions, |d| >= 1
        with np.errstate(divide="ignore", invalid="ignore"):
            exits = np.where(directions > 0, self.room_max - c, self.room_min - c) / directions
        nearest = np.min(np.where(np.isfinite(exits) & (exits > 0), exits, np.inf), axis=-1)
        solids: tuple[Cuboid | Plane, ...] = (*self.others, *self.planes)
        for solid in solids:
            nearest = np.minimum(nearest, solid.hit(c, directions))
        if self.object_shape is not None:
            hit = self.object_shape.hit(c, directions)
            on_object = hit < nearest
        else:
            offset = c - self.object_centre
            b = directions @ offset
            a = np.einsum("...i,...i->...", directions, directions)
            disc = b * b - a * (offset @ offset - self.object_radius**2)
            hit = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
            on_object = (disc >= 0) & (hit > 0) & (hit < nearest)
        return np.where(on_object, hit, nearest), on_object

    def object_box(
        self, T_world_cam: np.ndarray, size: tuple[int, int], K: np.ndarray | None = None
    ) -> tuple[float, float, float, float] | None:
        """The box (x0, y0, x1, y1) of the sphere's true silhouette in an image of ``size`` =
        (H, W) with intrinsics ``K`` (default ``camera_matrix(size)``), clipped to the image, in
        the SDK's box convention (pixel (c, r) covers [c, c + 1) x [r, r + 1)); None unless the
        whole sphere lies in front of the camera and its silhouette meets the image.

        Exact and cheap (no ray cast): the silhouette's tangent lines u = const and v = const
        are the lines l with lᵀ C* l = 0, C* = K (c cᵀ - r² I) Kᵀ the dual conic of a sphere of
        centre c (camera frame) and radius r.
        """
        height, width = size
        K = camera_matrix(size) if K is None else np.asarray(K, dtype=np.float64)
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        if self.object_shape is not None:
            return self._cuboid_box(self.object_shape, R, t, size, K)
        c = R.T @ (self.object_centre - t)
        r = self.object_radius
        if c[2] <= r:
            return None
        dual = K @ (np.outer(c, c) - r * r * np.eye(3)) @ K.T
        bounds = []
        for axis in (0, 1):  # tangents u = const, then v = const
            a, b, q = dual[2, 2], dual[axis, 2], dual[axis, axis]
            root = np.sqrt(max(b * b - a * q, 0.0))
            bounds.append(((b - root) / a + 0.5, (b + root) / a + 0.5))  # centres -> box coords
        (x0, x1), (y0, y1) = bounds
        box = (max(0.0, float(x0)), max(0.0, float(y0)), min(float(width), float(x1)),
               min(float(height), float(y1)))
        return box if box[0] < box[2] and box[1] < box[3] else None

    @staticmethod
    def _cuboid_box(
        shape: Cuboid, R: np.ndarray, t: np.ndarray, size: tuple[int, int], K: np.ndarray
    ) -> tuple[float, float, float, float] | None:
        """A convex solid's silhouette box is its projected corners' box (exact, no ray cast)."""
        local = (shape.corners() - t) @ R
        if local[:, 2].min() <= 1e-6:
            return None
        uv = local @ K.T
        uv = uv[:, :2] / uv[:, 2:] + 0.5  # pixel centres -> box coordinates
        height, width = size
        box = (max(0.0, float(uv[:, 0].min())), max(0.0, float(uv[:, 1].min())),
               min(float(width), float(uv[:, 0].max())), min(float(height), float(uv[:, 1].max())))
        return box if box[0] < box[2] and box[1] < box[3] else None


def encode_frame_index(index: int) -> tuple[int, int]:
    """(red, green) code of a frame index."""
    if not 0 <= index < MAX_FRAMES:
        raise BackendError(f"frame index {index} cannot be encoded (0..{MAX_FRAMES - 1})")
    return _CODE_OFFSET + index // _CODE_BASE, _CODE_OFFSET + index % _CODE_BASE


@functools.lru_cache(maxsize=16)
def _sample_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of a 9x9 grid of pixels spanning the image."""
    rows = np.linspace(0, height - 1, 9).astype(int)
    cols = np.linspace(0, width - 1, 9).astype(int)
    return np.repeat(rows, 9), np.tile(cols, 9)


def decode_frame_index(image: np.ndarray) -> int:
    """The frame index an image [H, W, 3] uint8 carries; BackendError if it carries none.

    Reads a sparse grid of pixels first (cheap), all pixels if the grid misses the coded region
    (a small masked object), and takes the most common code among non-background pixels.
    """
    rows, cols = _sample_grid(image.shape[0], image.shape[1])
    for pixels in (image[rows, cols], image.reshape(-1, 3)):
        red = pixels[:, 0].astype(np.int64)
        green = pixels[:, 1].astype(np.int64)
        coded = (
            (red >= _CODE_OFFSET) & (green >= _CODE_OFFSET) & (green < _CODE_OFFSET + _CODE_BASE)
        )
        if coded.any():
            codes = (red[coded] - _CODE_OFFSET) * _CODE_BASE + green[coded] - _CODE_OFFSET
            values, counts = np.unique(codes, return_counts=True)
            if counts.max() * 2 >= coded.sum():  # a majority: a natural photo has no such plateau
                return int(values[np.argmax(counts)])
    raise BackendError(
        "the image carries no simulated frame code: SimulatedBackend needs "
        "frames rendered by SimulatedCamera"
    )


@dataclass(frozen=True)
class SimulatedFrame:
    """One rendered frame with its ground truth."""

    index: int
    timestamp: float
    image: np.ndarray  # uint8 [H, W, 3]
    T_world_cam: np.ndarray  # ground-truth pose, float64 [4, 4]
    mask: np.ndarray | None  # bool [H, W]: the object's pixels (if requested)


class SimulatedCamera:
    """Renders frames of a ground-truth trajectory at ``size`` = (H, W).

    ``textured`` paints a checkerboard on the room and the object into the blue channel (ray cast
    per frame: pleasant in a viewer, slower); without it blue is flat and rendering is ~free.
    """

    def __init__(
        self,
        ground_truth: GroundTruth,
        scene: SimulatedScene,
        *,
        size: tuple[int, int] = (240, 320),
        textured: bool = True,
    ) -> None:
        self.ground_truth = ground_truth
        self.scene = scene
        self.size = (int(size[0]), int(size[1]))
        self.textured = textured
        self._rays = pixel_rays(self.size)

    def render(self, index: int, *, with_mask: bool = False) -> SimulatedFrame:
        """Frame ``index``; ``with_mask`` adds the object's mask (needs a ray cast)."""
        pose = self.ground_truth.poses[index]
        red, green = encode_frame_index(index)
        image = np.empty((*self.size, 3), dtype=np.uint8)
        image[..., 0], image[..., 1], image[..., 2] = red, green, 128
        mask = None
        if self.textured or with_mask:
            depth, on_object = self.scene.depth(pose, self._rays)
            if self.textured:
                points = (self._rays * depth[..., None]) @ pose[:3, :3].T + pose[:3, 3]
                checker = np.floor(points / 0.25).astype(np.int64).sum(axis=-1) % 2
                shade = np.clip(255.0 / (1.0 + 0.3 * depth), 40, 255)
                image[..., 2] = (
                    shade * (0.55 + 0.45 * checker) * np.where(on_object, 0.7, 1.0)
                ).astype(np.uint8)
            mask = on_object if with_mask else None
        return SimulatedFrame(index, float(self.ground_truth.timestamps[index]), image, pose, mask)

    def frames(
        self, start: int = 0, stop: int | None = None, step: int = 1, *, with_mask: bool = False
    ) -> Iterator[SimulatedFrame]:
        """Frames ``start:stop:step`` of the trajectory, rendered lazily."""
        for index in range(start, len(self.ground_truth) if stop is None else stop, step):
            yield self.render(index, with_mask=with_mask)
