"""What the ONNX runtime needs from each model family: its head graphs and their outputs in the
SDK's conventions (the ONNX counterpart of ``torch_families.py``).

The graphs stop where a computation is better done in float64 numpy or shared with the PyTorch
backend; the rest happens here:

| | Pi3 | Depth Anything 3 |
|---|---|---|
| heads for CAMERA | ``head_camera`` | ``head_camera`` |
| heads for CONFIDENCE | + ``head_conf`` | + ``head_depth`` (depth and confidence in one pass) |
| heads for ALL | + ``head_points`` | ``head_camera``, ``head_depth`` |
| pose | raw 3x3 rows normalised, SVD onto SO(3) in float64 (``camera_poses``) | ``pose_enc`` decoded by ``models.da3.sdk_outputs`` (as ``TorchBackend``) |
| confidence | ``sigmoid(conf_logits)`` | ``1 - 1/depth_conf`` |
| local points | ``local_points`` | depth unprojected with the predicted intrinsics |
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from scipy.special import expit

from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.geometry.se3 import project_to_rotation
from kvtracker_sdk.models.da3 import sdk_outputs
from kvtracker_sdk.models.da3.camera import decode_pose_encoding
from kvtracker_sdk.types import HeadSet

__all__ = [
    "DA3OnnxHeads",
    "HeadOutputs",
    "OnnxHeads",
    "Pi3OnnxHeads",
    "camera_poses",
    "onnx_heads",
]


@dataclass(frozen=True)
class HeadOutputs:
    """Per-frame outputs of the head graphs (F frames), SDK conventions; unrequested ones None."""

    poses: np.ndarray  # [F, 4, 4] float64 T_world_cam, OpenCV axes
    confidence: np.ndarray | None = None  # [F, H, W] float32 in [0, 1]
    local_points: np.ndarray | None = None  # [F, H, W, 3] float32, camera frame


class OnnxHeads(Protocol):
    """One family's head graphs: which to run for a ``HeadSet``, and their outputs converted."""

    def graphs(self, heads: HeadSet) -> tuple[str, ...]: ...

    def convert(
        self, outputs: Mapping[str, np.ndarray], heads: HeadSet, image_size: tuple[int, int]
    ) -> HeadOutputs: ...


def camera_poses(rotation_raw: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Pi3's camera-to-world poses [F, 4, 4] float64 from its camera head's raw outputs.

    ``rotation_raw`` [F, 9] is a row-major 3x3 per frame: its rows are normalised (as
    ``F.normalize``, eps 1e-12), then it is replaced by the nearest rotation with det = +1
    (SVD); equal to the PyTorch head's ``rotation_from_matrix9`` to 1e-12 in float64 (the
    PyTorch backend runs it in float32, whose rounding is ~1e-6). ``translation`` [F, 3].
    """
    matrices = np.asarray(rotation_raw, dtype=np.float64).reshape(-1, 3, 3)
    norms = np.linalg.norm(matrices, axis=-1, keepdims=True)
    matrices = matrices / np.maximum(norms, 1e-12)
    poses = np.tile(np.eye(4), (matrices.shape[0], 1, 1))
    for frame, matrix in enumerate(matrices):
        poses[frame, :3, :3] = project_to_rotation(matrix)
    poses[:, :3, 3] = np.asarray(translation, dtype=np.float64).reshape(-1, 3)
    return poses


class Pi3OnnxHeads:
    """Pi3: a graph per head; the pose's SVD in numpy."""

    _GRAPHS = {
        HeadSet.CAMERA: ("head_camera",),
        HeadSet.CONFIDENCE: ("head_camera", "head_conf"),
        HeadSet.ALL: ("head_camera", "head_conf", "head_points"),
    }

    def graphs(self, heads: HeadSet) -> tuple[str, ...]:
        return self._GRAPHS[heads]

    def convert(
        self, outputs: Mapping[str, np.ndarray], heads: HeadSet, image_size: tuple[int, int]
    ) -> HeadOutputs:
        logits = outputs.get("conf_logits")
        return HeadOutputs(
            poses=camera_poses(outputs["rotation_raw"], outputs["translation"]),
            confidence=None if logits is None else expit(logits).astype(np.float32),
            local_points=outputs.get("local_points"),
        )


class DA3OnnxHeads:
    """Depth Anything 3: ``pose_enc`` and DualDPT's depth, converted by ``models.da3.sdk_outputs``
    (the function ``TorchBackend`` uses) on tensors sharing the arrays' memory."""

    def graphs(self, heads: HeadSet) -> tuple[str, ...]:
        return ("head_camera",) if heads is HeadSet.CAMERA else ("head_camera", "head_depth")

    def convert(
        self, outputs: Mapping[str, np.ndarray], heads: HeadSet, image_size: tuple[int, int]
    ) -> HeadOutputs:
        pose_enc = torch.from_numpy(outputs["pose_enc"])
        _, intrinsics = decode_pose_encoding(pose_enc, image_size)
        depth, depth_conf = outputs.get("depth"), outputs.get("depth_conf")
        sdk = sdk_outputs(
            pose_enc,
            intrinsics,
            depth=None if depth is None else torch.from_numpy(depth),
            depth_conf=None if depth_conf is None else torch.from_numpy(depth_conf),
            with_points=heads is HeadSet.ALL,
        )
        return HeadOutputs(
            poses=sdk.T_world_cam.numpy(),
            confidence=None if sdk.confidence is None else sdk.confidence.numpy(),
            local_points=None if sdk.local_points is None else sdk.local_points.numpy(),
        )


def onnx_heads(family: str) -> OnnxHeads:
    """The head logic of an export's family (``manifest.family``)."""
    if family == "pi3":
        return Pi3OnnxHeads()
    if family == "da3":
        return DA3OnnxHeads()
    raise ModelError(f"no ONNX head logic for family {family!r}")
