"""The compact keyframe payload of quantised map files (format version 3): encode and decode.

A quantised cache makes the K/V about half of a bf16 map's; the keyframe arrays stored in full
(uint8 image and mask, float32 confidences and local points: 20 bytes per pixel) then take a
third of the file and more. A compact map stores them as (H x W pixels, N keyframes):

    tensor                         dtype  shape            content
    keyframes.image                uint8  [N, H, W, 3]     exact (rebuilds re-run the network on it);
                                                           PNG files from version 4 (image_codec.py)
    keyframes.mask_bits            uint8  [N, ceil(HW/8)]  the 0/1 mask, 8 pixels a byte (np.packbits)
    keyframes.confidence_unorm16   uint16 [N, H, W]        round(confidence * 65535): |error| <= 7.7e-6
    keyframes.points_scale         F32    [N]              a power of two per keyframe (below)
    "compact-xyz" (e.g. Pi3):
    keyframes.local_points_f16     F16    [N, H, W, 3]     local points / points_scale
    "compact-depth" (e.g. DA3):
    keyframes.depth_f16            F16    [N, H, W]        z / points_scale
    keyframes.ray_x, .ray_y        F32    [N, W], [N, H]   x = ray_x[col] * z, y = ray_y[row] * z

Points: float16 after division by a power of two (exact in float32) chosen so the keyframe's
largest finite |coordinate| is below 2**15: no overflow whatever the world scale, and every
coordinate keeps float16's relative precision (round to nearest, relative error <= 2**-11 = 4.9e-4)
unless it is below 2**-29 of that largest one. A network's own bf16 compute moves points by
more (``benchmarks/compact_maps.py`` measures both). Depth-and-ray storage is used when every
keyframe's points are depth times a pinhole ray — x / z constant along each column and y / z along
each row, as DA3's ``unproject_depth`` makes them — which the encoder checks on the data
(float32 reconstruction within 1e-5 relative), so no family knowledge is needed; then x and y
carry the depth's float16 error only. Anything else (Pi3's per-pixel points, a non-positive or
non-finite depth) is stored as xyz.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch

from kvtracker_sdk.errors import MapCorruptedError

__all__ = [
    "COMPACT_DEPTH",
    "COMPACT_XYZ",
    "FULL",
    "KEYFRAME_ENCODINGS",
    "compact_tensor_specs",
    "decode_compact",
    "encode_compact",
]

FULL = "full"  # uint8 mask, float32 confidences and points (every version; dense maps)
COMPACT_XYZ = "compact-xyz"
COMPACT_DEPTH = "compact-depth"
# keyframe encoding -> the oldest format version that holds it
KEYFRAME_ENCODINGS: dict[str, int] = {FULL: 1, COMPACT_XYZ: 3, COMPACT_DEPTH: 3}

MASK_BITS = "keyframes.mask_bits"
CONFIDENCE_UNORM16 = "keyframes.confidence_unorm16"
POINTS_SCALE = "keyframes.points_scale"
POINTS_F16 = "keyframes.local_points_f16"
DEPTH_F16 = "keyframes.depth_f16"
RAY_X = "keyframes.ray_x"
RAY_Y = "keyframes.ray_y"

_UNORM16 = 65535.0
_F16_HEADROOM_LOG2 = 15  # largest |value| / scale < 2**15, below float16's 65504
# a keyframe's largest |coordinate| is ~2**15 scales: these allow 2**-41 (5e-13) to 2**40 (1e12)
# world units, far beyond any scene; an edited scale outside gives points that are finite but
# meaningless
POINTS_SCALE_RANGE = (2.0**-55, 2.0**25)
_RAY_RTOL = 1e-5  # float32 x / z is constant per column to a few ulp; anything else is not a ray


def compact_tensor_specs(
    encoding: str, num_keyframes: int, resolution: tuple[int, int]
) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Name -> (safetensors dtype, shape) of the compact keyframe tensors (not the image)."""
    n, (h, w) = num_keyframes, resolution
    specs = {
        MASK_BITS: ("U8", (n, (h * w + 7) // 8)),
        CONFIDENCE_UNORM16: ("U16", (n, h, w)),
        POINTS_SCALE: ("F32", (n,)),
    }
    if encoding == COMPACT_XYZ:
        specs[POINTS_F16] = ("F16", (n, h, w, 3))
    else:
        specs.update({DEPTH_F16: ("F16", (n, h, w)), RAY_X: ("F32", (n, w)), RAY_Y: ("F32", (n, h))})
    return specs


def _power_of_two_scales(values: np.ndarray) -> np.ndarray:
    """[N] float32 powers of two with max finite |values[k]| / scale < 2**15 (1 if none)."""
    scales = np.ones(len(values), dtype=np.float32)
    for k, block in enumerate(values):
        finite = np.abs(block[np.isfinite(block)])
        largest = float(finite.max()) if finite.size else 0.0
        if largest > 0.0:
            scales[k] = math.ldexp(1.0, math.frexp(largest)[1] - _F16_HEADROOM_LOG2)
    return scales


def _ray_slopes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """([N, W], [N, H]) float32 slopes with x = ray_x[col] * z and y = ray_y[row] * z for every
    pixel of [N, H, W, 3] ``points`` (to float32 rounding), or None if they are not such rays."""
    z = points[..., 2].astype(np.float64)
    if not (np.all(np.isfinite(points)) and np.all(z > 0)):
        return None
    ray_x = ((points[..., 0] * z).sum(axis=1) / (z * z).sum(axis=1)).astype(np.float32)  # [N, W]
    ray_y = ((points[..., 1] * z).sum(axis=2) / (z * z).sum(axis=2)).astype(np.float32)  # [N, H]
    z32 = points[..., 2]
    x = ray_x[:, None, :] * z32
    y = ray_y[:, :, None] * z32
    tolerance = _RAY_RTOL * (np.abs(points[..., :2]).max(axis=-1) + z32)
    if np.all(np.abs(x - points[..., 0]) <= tolerance) and np.all(
        np.abs(y - points[..., 1]) <= tolerance
    ):
        return ray_x, ray_y
    return None


def _to_f16(values: np.ndarray, scales: np.ndarray) -> torch.Tensor:
    shape = (-1,) + (1,) * (values.ndim - 1)
    return torch.from_numpy((values / scales.reshape(shape)).astype(np.float16))


def encode_compact(
    masks: np.ndarray, confidence: np.ndarray, points: np.ndarray
) -> tuple[str, dict[str, torch.Tensor]]:
    """(encoding, tensors) of bool [N, H, W] masks (False where absent), float32 [N, H, W]
    confidences in [0, 1] and float32 [N, H, W, 3] local points."""
    n = len(points)
    tensors = {
        MASK_BITS: torch.from_numpy(np.packbits(masks.reshape(n, -1), axis=1)),
        CONFIDENCE_UNORM16: torch.from_numpy(
            np.rint(confidence.astype(np.float64) * _UNORM16).astype(np.uint16)
        ),
    }
    rays = _ray_slopes(points)
    if rays is None:
        scales = _power_of_two_scales(points)
        tensors.update({POINTS_SCALE: torch.from_numpy(scales), POINTS_F16: _to_f16(points, scales)})
        return COMPACT_XYZ, tensors
    depth = np.ascontiguousarray(points[..., 2])
    scales = _power_of_two_scales(depth)
    tensors.update({
        POINTS_SCALE: torch.from_numpy(scales), DEPTH_F16: _to_f16(depth, scales),
        RAY_X: torch.from_numpy(rays[0]), RAY_Y: torch.from_numpy(rays[1]),
    })  # fmt: skip
    return COMPACT_DEPTH, tensors


def decode_compact(
    tensors: Mapping[str, torch.Tensor], encoding: str, resolution: tuple[int, int], source: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bool masks [N, H, W], float32 confidences [N, H, W], float32 points [N, H, W, 3]) of a
    compact map's tensors. MapCorruptedError for a scale the encoder cannot write (it writes
    finite positive powers of two) and for points or rays that decode to values the stored
    float16 did not hold (an edited scale overflowing float32)."""
    h, w = resolution
    scales = tensors[POINTS_SCALE].numpy()
    low, high = POINTS_SCALE_RANGE
    if not np.all(np.isfinite(scales) & (scales >= low) & (scales <= high)
                  & (np.frexp(scales)[0] == 0.5)):
        raise MapCorruptedError(
            f"{source}: keyframe point scales (keyframes.points_scale) must be powers of two in "
            f"[2**-55, 2**25], got {scales.tolist()[:8]}"
        )
    for name in (RAY_X, RAY_Y):
        if name in tensors and not np.all(np.isfinite(tensors[name].numpy())):
            raise MapCorruptedError(f"{source}: {name} must be finite")
    bits = tensors[MASK_BITS].numpy()
    masks = np.unpackbits(bits, axis=1, count=h * w).reshape(len(bits), h, w).astype(bool)
    confidence = (tensors[CONFIDENCE_UNORM16].numpy().astype(np.float32) / np.float32(_UNORM16))
    if encoding == COMPACT_XYZ:
        stored = tensors[POINTS_F16].numpy()
        _check_scales_fit(stored, scales, POINTS_F16, source)
        with np.errstate(over="ignore"):
            points = stored.astype(np.float32) * scales[:, None, None, None]
        _same_finiteness(stored, points, POINTS_F16, source)
        return masks, confidence, points
    stored = tensors[DEPTH_F16].numpy()
    _check_scales_fit(stored, scales, DEPTH_F16, source)
    with np.errstate(over="ignore", invalid="ignore"):
        z = stored.astype(np.float32) * scales[:, None, None]
        ray_x, ray_y = tensors[RAY_X].numpy(), tensors[RAY_Y].numpy()
        points = np.stack((ray_x[:, None, :] * z, ray_y[:, :, None] * z, z), axis=-1)
    _same_finiteness(stored[..., None].repeat(3, axis=-1), points, DEPTH_F16, source)
    return masks, confidence, points


def _check_scales_fit(stored: np.ndarray, scales: np.ndarray, name: str, source: str) -> None:
    """The encoder's invariant (``_power_of_two_scales``): each keyframe's largest finite
    |stored value| lies in [2**14, 2**15] (float16 rounding may reach 2**15), or is 0 with scale
    1. An edited power-of-two scale (2**120, 2**-149) breaks it."""
    for k, block in enumerate(stored):
        finite = np.abs(block[np.isfinite(block)].astype(np.float32))
        largest = float(finite.max()) if finite.size else 0.0
        low, high = 2.0 ** (_F16_HEADROOM_LOG2 - 1), 2.0**_F16_HEADROOM_LOG2
        if (largest == 0.0 and scales[k] != 1.0) or (largest != 0.0 and not low <= largest <= high):
            raise MapCorruptedError(
                f"{source}: keyframes.points_scale[{k}] = {float(scales[k])!r} does not fit the "
                f"stored {name} (the encoder writes the power of two that does)"
            )


def _same_finiteness(stored: np.ndarray, decoded: np.ndarray, name: str, source: str) -> None:
    """Decoding makes no value non-finite that was finite in the file."""
    if not np.array_equal(np.isfinite(stored), np.isfinite(decoded)):
        raise MapCorruptedError(f"{source}: {name} decodes to values out of float32's range "
                                "(an impossible points_scale)")
