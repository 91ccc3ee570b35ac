"""Pose-encoding math and the conversion of DA3 outputs to the SDK's conventions."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from kvtracker_sdk.models.da3 import DA3Output, confidence_from_depth_conf, to_sdk, unproject_depth
from kvtracker_sdk.models.da3.camera import (
    decode_pose_encoding,
    encode_pose_encoding,
    invert_rigid,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
)


def _random_rotations(count: int, seed: int) -> torch.Tensor:
    return torch.from_numpy(Rotation.random(count, random_state=seed).as_matrix())


def test_quaternion_conversions_match_scipy() -> None:
    rotations = _random_rotations(64, seed=0)
    quat = matrix_to_quat_xyzw(rotations)
    expected = Rotation.from_matrix(rotations.numpy()).as_quat()  # xyzw
    expected = np.where(expected[:, 3:] < 0, -expected, expected)  # w >= 0
    np.testing.assert_allclose(quat.numpy(), expected, atol=1e-12)
    # an unnormalised quaternion still gives the same rotation
    torch.testing.assert_close(quat_xyzw_to_matrix(3.7 * quat), rotations, atol=1e-12, rtol=0)
    # 180-degree turns (w = 0) pick another row of the conversion and must still be exact
    flips = torch.diag_embed(
        torch.tensor([[1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]], dtype=torch.float64)
    )
    torch.testing.assert_close(
        quat_xyzw_to_matrix(matrix_to_quat_xyzw(flips)), flips, atol=1e-12, rtol=0
    )


def test_pose_encoding_round_trip_and_intrinsics() -> None:
    cam_to_world = torch.eye(4, dtype=torch.float64).repeat(2, 3, 1, 1)
    cam_to_world[..., :3, :3] = _random_rotations(6, seed=1).reshape(2, 3, 3, 3)
    cam_to_world[..., :3, 3] = torch.linspace(-1, 1, 18, dtype=torch.float64).reshape(2, 3, 3)
    intrinsics = torch.tensor(
        [[200.0, 0, 77], [0, 180.0, 56], [0, 0, 1]], dtype=torch.float64
    ).repeat(2, 3, 1, 1)
    encoding = encode_pose_encoding(cam_to_world, intrinsics, (112, 154)).double()
    assert encoding.shape == (2, 3, 9)
    torch.testing.assert_close(
        encoding[..., 7], torch.full((2, 3), 2 * math.atan(56 / 180), dtype=torch.float64)
    )
    decoded, decoded_intrinsics = decode_pose_encoding(encoding, (112, 154))
    torch.testing.assert_close(
        decoded, cam_to_world[..., :3, :], atol=1e-6, rtol=0
    )  # fp32 encoding
    torch.testing.assert_close(decoded_intrinsics, intrinsics, atol=1e-4, rtol=1e-6)
    identity = invert_rigid(cam_to_world) @ cam_to_world
    torch.testing.assert_close(
        identity, torch.eye(4, dtype=torch.float64).expand(2, 3, 4, 4), atol=1e-12, rtol=0
    )


def test_to_sdk_inverts_the_extrinsics_and_maps_confidence() -> None:
    generator = torch.Generator().manual_seed(0)
    pose_enc = torch.randn(1, 2, 9, generator=generator)
    pose_enc[..., 7:] = pose_enc[..., 7:].abs() + 0.5
    cam_to_world, intrinsics = decode_pose_encoding(pose_enc, (28, 42))
    depth = torch.rand(1, 2, 28, 42, generator=generator) + 0.5
    logits = torch.randn(1, 2, 28, 42, generator=generator)
    output = DA3Output(
        pose_enc=pose_enc,
        extrinsics=invert_rigid(cam_to_world),
        intrinsics=intrinsics,
        depth=depth,
        depth_conf=torch.exp(logits) + 1,
    )
    sdk = to_sdk(output, with_points=True)
    assert sdk.T_world_cam.dtype == torch.float64 and sdk.T_world_cam.shape == (1, 2, 4, 4)
    world_to_cam = torch.cat([output.extrinsics.double(), sdk.T_world_cam[..., 3:, :]], dim=-2)
    torch.testing.assert_close(
        sdk.T_world_cam @ world_to_cam,
        torch.eye(4, dtype=torch.float64).expand(1, 2, 4, 4),
        atol=1e-6,
        rtol=0,
    )
    assert sdk.confidence is not None and sdk.local_points is not None
    torch.testing.assert_close(sdk.confidence, torch.sigmoid(logits), atol=1e-6, rtol=0)
    assert float(confidence_from_depth_conf(torch.tensor(1.0))) == 0.0
    # points project back to their pixels: u = fx x / z + cx, v = fy y / z + cy
    points = sdk.local_points[0, 1]
    k = intrinsics[0, 1]
    u = k[0, 0] * points[..., 0] / points[..., 2] + k[0, 2]
    v = k[1, 1] * points[..., 1] / points[..., 2] + k[1, 2]
    torch.testing.assert_close(u, torch.arange(42.0).expand(28, 42), atol=1e-4, rtol=0)
    torch.testing.assert_close(v, torch.arange(28.0).unsqueeze(1).expand(28, 42), atol=1e-4, rtol=0)
    torch.testing.assert_close(points[..., 2], depth[0, 1])
    camera_only = to_sdk(
        DA3Output(pose_enc=pose_enc, extrinsics=output.extrinsics, intrinsics=intrinsics)
    )
    assert camera_only.depth is None and camera_only.confidence is None
    assert unproject_depth(depth, intrinsics).shape == (1, 2, 28, 42, 3)
