"""DA3 outputs in the SDK's conventions (what a backend hands to the tracker).

| SDK quantity | from DA3 |
|---|---|
| ``T_world_cam`` 4x4 float64, camera-to-world | ``[R(q) | t]`` decoded from ``pose_enc`` in float64 (DA3's ``extrinsics`` are its inverse, world-to-camera) |
| ``intrinsics`` 3x3 float64 | DA3's, from the predicted field of view |
| ``depth`` float32 | DA3's depth (camera z, up to scale) |
| ``confidence`` float32 in [0, 1) | ``1 - 1 / depth_conf`` |
| ``local_points`` float32, camera frame | ``depth * K⁻¹ (u, v, 1)`` |

Confidence: DA3's ``depth_conf = exp(l) + 1`` is >= 1 and unbounded. ``1 - 1/depth_conf`` equals
``sigmoid(l)``, the same map from logit to [0, 1) that Pi3's confidence uses, so the tracker's
thresholds mean the same for both families; it keeps DA3's ordering of pixels.

Pixel coordinates follow DA3 (the principal point is at (W/2, H/2)): pixel (row i, column j) is at
(u, v) = (j, i), as in DA3's own depth-to-points code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from kvtracker_sdk.models.da3.camera import decode_pose_encoding, quat_xyzw_to_matrix
from kvtracker_sdk.models.da3.model import DA3Output
from kvtracker_sdk.models.family import FrameOutputs, numpy_or_none

__all__ = [
    "SDKOutput",
    "confidence_from_depth_conf",
    "frames_from_heads",
    "frames_from_sdk",
    "sdk_outputs",
    "to_sdk",
    "unproject_depth",
]


@dataclass(frozen=True)
class SDKOutput:
    """Per-view outputs [B, N, ...] in SDK conventions; None where DA3 did not compute them."""

    T_world_cam: torch.Tensor  # [B, N, 4, 4] float64, camera-to-world, OpenCV axes
    intrinsics: torch.Tensor  # [B, N, 3, 3] float64, pixels
    depth: torch.Tensor | None = None  # [B, N, H, W] float32
    confidence: torch.Tensor | None = None  # [B, N, H, W] float32 in [0, 1)
    local_points: torch.Tensor | None = None  # [B, N, H, W, 3] float32, camera frame


def confidence_from_depth_conf(depth_conf: torch.Tensor) -> torch.Tensor:
    """DA3's confidence (>= 1) -> [0, 1): ``1 - 1/c``, i.e. the sigmoid of DA3's logit."""
    return 1.0 - 1.0 / depth_conf


def unproject_depth(depth: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Depth [..., H, W] and intrinsics [..., 3, 3] -> camera-frame points [..., H, W, 3]."""
    height, width = depth.shape[-2:]
    rows = torch.arange(height, dtype=depth.dtype, device=depth.device).view(height, 1)
    cols = torch.arange(width, dtype=depth.dtype, device=depth.device).view(1, width)
    k = intrinsics.to(depth.dtype)[..., None, None, :, :]  # [..., 1, 1, 3, 3]
    x = (cols - k[..., 0, 2]) / k[..., 0, 0] * depth
    y = (rows - k[..., 1, 2]) / k[..., 1, 1] * depth
    return torch.stack((x, y, depth), dim=-1)


def to_sdk(output: DA3Output, *, with_points: bool = False) -> SDKOutput:
    """``DA3Output`` -> ``SDKOutput``; ``with_points`` unprojects the depth (needs DualDPT)."""
    return sdk_outputs(
        output.pose_enc,
        output.intrinsics,
        depth=output.depth,
        depth_conf=output.depth_conf,
        with_points=with_points,
    )


def sdk_outputs(
    pose_enc: torch.Tensor,
    intrinsics: torch.Tensor,
    *,
    depth: torch.Tensor | None = None,
    depth_conf: torch.Tensor | None = None,
    with_points: bool = False,
) -> SDKOutput:
    """DA3's raw outputs [..., 9] / [..., 3, 3] / [..., H, W] -> ``SDKOutput``: shared by
    ``to_sdk`` (PyTorch) and the ONNX backend, so both convert with the same arithmetic."""
    pose_enc = pose_enc.double()
    T_world_cam = torch.zeros(
        *pose_enc.shape[:-1], 4, 4, dtype=torch.float64, device=pose_enc.device
    )
    T_world_cam[..., :3, :3] = quat_xyzw_to_matrix(pose_enc[..., 3:7])
    T_world_cam[..., :3, 3] = pose_enc[..., :3]
    T_world_cam[..., 3, 3] = 1.0
    if depth is None or depth_conf is None:
        return SDKOutput(T_world_cam=T_world_cam, intrinsics=intrinsics.double())
    points = unproject_depth(depth, intrinsics) if with_points else None
    return SDKOutput(
        T_world_cam=T_world_cam,
        intrinsics=intrinsics.double(),
        depth=depth,
        confidence=confidence_from_depth_conf(depth_conf),
        local_points=points,
    )


def frames_from_sdk(sdk: SDKOutput) -> FrameOutputs:
    """``SDKOutput`` of one sequence of F views ([1, F, ...] or [F, 1, ...]) -> ``FrameOutputs``
    [F, ...] (numpy on the CPU)."""
    return FrameOutputs(
        poses=sdk.T_world_cam.flatten(0, 1).cpu().numpy(),
        confidence=numpy_or_none(None if sdk.confidence is None else sdk.confidence.flatten(0, 1)),
        local_points=numpy_or_none(
            None if sdk.local_points is None else sdk.local_points.flatten(0, 1)
        ),
        intrinsics=sdk.intrinsics.flatten(0, 1).cpu().numpy(),
    )


def frames_from_heads(
    pose_enc: np.ndarray,
    image_size: tuple[int, int],
    *,
    depth: np.ndarray | None = None,
    depth_conf: np.ndarray | None = None,
    with_points: bool = False,
) -> FrameOutputs:
    """The exported head graphs' outputs [F, ...] -> ``FrameOutputs``, through ``sdk_outputs``
    (the PyTorch passes' arithmetic) on tensors sharing the arrays' memory."""
    pose = torch.from_numpy(pose_enc)
    _, intrinsics = decode_pose_encoding(pose, image_size)
    sdk = sdk_outputs(
        pose,
        intrinsics,
        depth=None if depth is None else torch.from_numpy(depth),
        depth_conf=None if depth_conf is None else torch.from_numpy(depth_conf),
        with_points=with_points,
    )
    return FrameOutputs(
        poses=sdk.T_world_cam.numpy(),
        confidence=numpy_or_none(sdk.confidence),
        local_points=numpy_or_none(sdk.local_points),
        intrinsics=sdk.intrinsics.numpy(),
    )
