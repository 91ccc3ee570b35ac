"""Pi3 outputs in the SDK's conventions (what a backend hands to the tracker).

| SDK quantity | from Pi3 |
|---|---|
| ``T_world_cam`` 4x4 float64, camera-to-world | ``camera_poses`` (PyTorch); from the exported camera head, the raw 3x3 rows normalised and projected onto SO(3) by SVD in float64 (``camera_poses``) |
| ``confidence`` float32 in [0, 1] | ``sigmoid(conf logit)`` |
| ``local_points`` float32, camera frame | ``local_points`` (z = exp(d)) |

Pi3 picks its own world frame in every pass (frame 0 is not the identity); the tracker's gauge
aligns successive maps.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.special import expit

from kvtracker_sdk.geometry.se3 import project_to_rotation
from kvtracker_sdk.models.family import FrameOutputs, numpy_or_none
from kvtracker_sdk.models.pi3.model import Pi3Output

__all__ = ["camera_poses", "frames_from_heads", "frames_from_output"]


def frames_from_output(output: Pi3Output) -> FrameOutputs:
    """A pass's ``Pi3Output`` with one sequence of F frames ([1, F, ...] or [F, 1, ...]) ->
    ``FrameOutputs`` [F, ...]."""
    flat = output.camera_poses.flatten(0, 1)  # [F, 4, 4]
    conf = None if output.conf is None else torch.sigmoid(output.conf.flatten(0, 1)[..., 0])
    points = None if output.local_points is None else output.local_points.flatten(0, 1)
    return FrameOutputs(
        poses=flat.double().cpu().numpy(),
        confidence=numpy_or_none(conf),
        local_points=numpy_or_none(points),
    )


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


def frames_from_heads(
    rotation_raw: np.ndarray,
    translation: np.ndarray,
    conf_logits: np.ndarray | None = None,
    local_points: np.ndarray | None = None,
) -> FrameOutputs:
    """The exported head graphs' outputs [F, ...] -> ``FrameOutputs``."""
    return FrameOutputs(
        poses=camera_poses(rotation_raw, translation),
        confidence=None if conf_logits is None else expit(conf_logits).astype(np.float32),
        local_points=local_points,
    )
