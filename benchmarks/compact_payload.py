"""The keyframe payload of map files for ``benchmarks/compact_maps.py``: family-shaped keyframes,
a file's bytes per keyframe by part, and the compact payload's deviation on the golden models
(see that module's docstring)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache import Keyframe
from kvtracker_sdk.eval.cache_deviation import tum_frames
from kvtracker_sdk.io.map_file.keyframe_codec import decode_compact, encode_compact
from kvtracker_sdk.io.map_file.map_file import MapInfo
from kvtracker_sdk.io.sources.sources import TumSource
from kvtracker_sdk.models.da3.conventions import unproject_depth

__all__ = ["PARTS", "composition", "keyframe_payload", "payload_deviation"]


def keyframe_payload(model: str, size: tuple[int, int], count: int) -> list[Keyframe]:
    """Keyframes with random images and points shaped as the family makes them (DA3: depth x
    pinhole rays, which the compact payload stores as depth; Pi3: per-pixel xyz)."""
    height, width = size
    rng = np.random.default_rng(0)
    keyframes = []
    for i in range(count):
        depth = rng.uniform(0.5, 5.0, (height, width)).astype(np.float32)
        if model.startswith("da3"):
            K = torch.tensor([[0.8 * width, 0, width / 2], [0, 0.8 * width, height / 2], [0, 0, 1]])
            points = unproject_depth(torch.from_numpy(depth), K.double()).numpy()
        else:
            points = np.dstack([rng.normal(size=(height, width, 2)), depth]).astype(np.float32)
        keyframes.append(Keyframe(
            keyframe_id=i, frame_index=i, timestamp=None,
            image=rng.integers(0, 256, (height, width, 3), dtype=np.uint8), mask=None,
            T_world_cam=np.eye(4), confidence_map=rng.random((height, width), dtype=np.float32),
            local_points=points, mean_confidence=0.5,
        ))  # fmt: skip
    return keyframes


PARTS = {  # file part -> tensor name prefixes (the rest is "other")
    "kv": ("layers.",), "image": ("keyframes.image",), "mask": ("keyframes.mask",),
    "confidence": ("keyframes.confidence",),
    "points": ("keyframes.local_points", "keyframes.depth", "keyframes.ray", "keyframes.points"),
}  # fmt: skip


def composition(info: MapInfo) -> dict[str, float]:
    """Bytes per keyframe of each part of a map file (the header counts as "other")."""
    parts = dict.fromkeys([*PARTS, "other"], 0.0)
    for name, spec in info.tensor_schema().items():
        part = next((p for p, prefixes in PARTS.items() if name.startswith(prefixes)), "other")
        parts[part] += spec.nbytes
    parts["other"] += info.file_size - sum(parts.values())
    return {part: nbytes / info.num_keyframes for part, nbytes in parts.items()}


def _relative(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(reference, axis=-1)
    keep = np.isfinite(norm) & (norm > 0)
    return (np.linalg.norm(points - reference, axis=-1)[keep] / norm[keep]).astype(np.float64)


def payload_deviation(shared: Path) -> list[dict[str, Any]]:
    """Per golden model: the compact payload's point / confidence error and the bf16 backend's,
    both against the fp32 mapping pass of the same 4 TUM frames (see the module docstring)."""
    frames_source = list(TumSource(shared / "data" / "tum_fr2_desk"))
    rows = []
    for family in ("pi3", "da3"):
        frames = tum_frames(frames_source, family, resolution=224)[[0, 5, 10, 15]]
        weights = shared / "golden" / family / "weights.safetensors"
        fp32 = TorchBackend.from_pretrained(weights).map(frames)
        bf16 = TorchBackend.from_pretrained(weights, dtype="bfloat16").map(frames)
        masks = np.zeros(fp32.confidence.shape, bool)
        encoding, tensors = encode_compact(masks, fp32.confidence, fp32.local_points)
        _, confidence, points = decode_compact(tensors, encoding, frames.shape[1:3], family)
        compact_rel, bf16_rel = _relative(points, fp32.local_points), _relative(bf16.local_points, fp32.local_points)
        rows.append({
            "model": f"golden-{family}", "encoding": encoding,
            "compact_points_rel_median": float(np.median(compact_rel)),
            "compact_points_rel_max": float(compact_rel.max()),
            "bf16_points_rel_median": float(np.median(bf16_rel)),
            "bf16_points_rel_max": float(bf16_rel.max()),
            "compact_confidence_abs_max": float(np.abs(confidence - fp32.confidence).max()),
            "bf16_confidence_abs_median": float(np.median(np.abs(bf16.confidence - fp32.confidence))),
            "bf16_confidence_abs_max": float(np.abs(bf16.confidence - fp32.confidence).max()),
        })  # fmt: skip
    return rows
