"""``DepthAnything3``: the DA3 any-view network, with the mapping/tracking split of KV-Tracker.

Input images are RGB in [0, 1] (as for ``Pi3``); the model applies the ImageNet mean/std itself
(the official ``DepthAnything3Net`` expects normalised input — its input processor does this).
H and W must be multiples of 14. Outputs follow the official code: ``extrinsics`` are
**world-to-camera** [R | t] (OpenCV axes) in the frame of the pass's reference view,
``intrinsics`` come from the predicted field of view, depth is along the camera z axis, up to
scale. ``to_sdk`` (``conventions.py``) converts to the SDK's conventions.

Passes (inference code runs them under ``torch.no_grad()``):

- ``model(imgs [B, N, 3, H, W])`` -> ``DA3Output``: the official forward. The reference view is
  chosen by ``ref_view_strategy`` when N >= 3 (``saddle_balanced`` by default, ``first``,
  ``middle``, ``saddle_sim_range``), else view 0. With ``extrinsics``/``intrinsics`` (pose
  conditioning) the pose encoder supplies the camera tokens instead. ``global_attn_mask`` (bool
  [N*T, N*T]) masks the global blocks: with ``keyframe_query_mask`` and ``ref_view_strategy=
  "first"`` this is the reference for tracking.
- ``model.forward_map(imgs [B, N, 3, H, W])`` -> ``DA3MapOutput``: keyframes with the reference
  **pinned to view 0**, so keyframe 0 defines the world frame of every (re-)mapping; also every
  global block's K (after k_norm and RoPE) and V, [B, heads, N*T, head_dim], camera tokens
  included (T = 1 + (H/14)(W/14) tokens per view, view-major).
- ``model.forward_track(imgs [F, 3, H, W], cache)`` -> ``DA3Output`` with leading dims [F, 1]:
  F independent query views, each carrying the **non-reference** camera token and attending in
  every global block to all cached tokens plus its own. ``cache`` is anything with ``length``,
  ``ensure_capacity(tokens)`` and ``buffers(layer)`` (``kvtracker_sdk.cache.KVCache``).

``heads`` (``HeadSet``): CAMERA runs only the camera decoder (the DualDPT head is skipped: the
fastest step); CONFIDENCE and ALL also run DualDPT, which gives depth and confidence together.
``with_rays`` adds the auxiliary ray maps (not needed for tracking; DA3 itself discards them).

Precision: ``set_precision(torch.bfloat16)`` runs the official bf16 recipe (``torch.autocast``
over the backbone; see ``models/layers/precision.py``) with the backbone's Linear/conv weights
stored in bf16 once: matrix products and the K/V cache in bf16, the residual stream, norms,
LayerScales and tokens in fp32, RoPE angles rounded to bf16 as in the official code. The DualDPT
head and the camera modules stay fp32, as the official bf16 inference runs them with autocast
disabled. A caller's ``torch.autocast`` likewise reaches only the backbone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from kvtracker_sdk.errors import ImageShapeError, InputError
from kvtracker_sdk.models.da3.backbone import BackboneOutput, DA3Backbone
from kvtracker_sdk.models.da3.camera import (
    CameraDecoder,
    CameraEncoder,
    decode_pose_encoding,
    invert_rigid,
)
from kvtracker_sdk.models.da3.config import DA3Config
from kvtracker_sdk.models.da3.dualdpt import DualDPT
from kvtracker_sdk.models.da3.reference_view import ReferenceStrategy
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.patch_embed import IMAGENET_MEAN, IMAGENET_STD
from kvtracker_sdk.models.layers.precision import cast_matmul_weights, trunk_autocast
from kvtracker_sdk.types import HeadSet

__all__ = ["DA3MapOutput", "DA3Output", "DepthAnything3"]

_FP32_MODULES = ("head", "cam_dec", "cam_enc")


@dataclass(frozen=True)
class DA3Output:
    """Outputs of a pass over [B, N] views (float32). Unrequested heads are None."""

    pose_enc: torch.Tensor  # [B, N, 9]: t, quaternion xyzw, fov_h, fov_w (camera-to-world)
    extrinsics: torch.Tensor  # [B, N, 3, 4] world-to-camera [R | t], OpenCV axes
    intrinsics: torch.Tensor  # [B, N, 3, 3] pixels; principal point at the image centre
    depth: torch.Tensor | None = None  # [B, N, H, W] > 0, camera z, up to scale
    depth_conf: torch.Tensor | None = None  # [B, N, H, W] >= 1
    ray: torch.Tensor | None = None  # [B, N, 8h, 8w, 6] auxiliary rays (raw)
    ray_conf: torch.Tensor | None = None  # [B, N, 8h, 8w] >= 1
    reference_view: torch.Tensor | None = None  # [B] int64, the view given camera_token[:, 0]


@dataclass(frozen=True)
class DA3MapOutput:
    """A mapping pass: its outputs and the K/V of every global block (the cache content)."""

    output: DA3Output
    keys: list[torch.Tensor]  # per global block [B, heads, N*T, head_dim], after k_norm + RoPE
    values: list[torch.Tensor]  # per global block [B, heads, N*T, head_dim]
    tokens_per_frame: int  # T = 1 + (H/14)*(W/14)


def _channel_constants(values: Sequence[float], device: torch.device) -> torch.Tensor:
    """float32 [len(values)] on ``device``, each filled there (no host-to-device copy)."""
    return torch.stack([torch.full((), value, device=device) for value in values])


class DepthAnything3(nn.Module):
    """DA3 with module names equal to the official ``DepthAnything3Net`` (its checkpoints load strictly)."""

    def __init__(self, config: DA3Config | None = None) -> None:
        super().__init__()
        self.config = config = config or DA3Config.small()
        dim = config.backbone.embed_dim
        self.backbone = DA3Backbone(config)
        self.head = DualDPT(2 * dim, config.head, patch_size=config.patch_size)
        self.cam_dec = CameraDecoder(2 * dim)
        self.cam_enc = CameraEncoder(dim, config.cam_enc)

    # ------------------------------------------------------------------ properties
    @property
    def compute_dtype(self) -> torch.dtype:
        """dtype of the backbone's matrix products (the KV cache's dtype); the heads stay fp32."""
        return self.backbone.pretrained.patch_embed.proj.weight.dtype

    def tokens_per_frame(self, height: int, width: int) -> int:
        """Backbone tokens per view: 1 camera/cls token + (H/14)*(W/14) patches."""
        patch = self.config.patch_size
        return 1 + (height // patch) * (width // patch)

    def set_precision(self, dtype: torch.dtype) -> DepthAnything3:
        """Matrix products of the backbone in ``dtype``.

        Its Linear/conv weights are cast to ``dtype`` and the passes run it under
        ``torch.autocast(dtype)``; every other parameter, the DualDPT head and the camera modules
        stay fp32.
        """
        self.to(torch.float32)
        if dtype != torch.float32:
            for name, module in self.named_children():
                if name not in _FP32_MODULES:
                    cast_matmul_weights(module, dtype)
        return self

    # ------------------------------------------------------------------ passes
    def forward(
        self,
        imgs: torch.Tensor,
        *,
        heads: HeadSet = HeadSet.ALL,
        ref_view_strategy: ReferenceStrategy = "saddle_balanced",
        extrinsics: torch.Tensor | None = None,
        intrinsics: torch.Tensor | None = None,
        global_attn_mask: torch.Tensor | None = None,
        with_rays: bool = False,
    ) -> DA3Output:
        """Official forward on ``imgs`` [B, N, 3, H, W] in [0, 1]; see the module docstring.

        ``extrinsics`` world-to-camera [B, N, 3 or 4, 4] and ``intrinsics`` [B, N, 3, 3] (both or
        neither) condition the pass on known cameras.
        """
        if (extrinsics is None) != (intrinsics is None):
            raise InputError("pose conditioning needs both extrinsics and intrinsics")
        camera_tokens = None
        if extrinsics is not None and intrinsics is not None:
            with torch.autocast(imgs.device.type, enabled=False):
                camera_tokens = self.cam_enc(
                    extrinsics, intrinsics, (imgs.shape[-2], imgs.shape[-1])
                )
        with trunk_autocast(self.compute_dtype, imgs.device):
            features = self.backbone(
                self.normalise(imgs),
                strategy=ref_view_strategy,
                camera_tokens=camera_tokens,
                global_attn_mask=global_attn_mask,
            )
        return self._heads(features, (imgs.shape[-2], imgs.shape[-1]), heads, with_rays)

    def forward_map(
        self, imgs: torch.Tensor, *, heads: HeadSet = HeadSet.ALL, with_rays: bool = False
    ) -> DA3MapOutput:
        """Keyframes [B, N, 3, H, W] (reference = view 0) -> outputs and every global block's K/V."""
        with trunk_autocast(self.compute_dtype, imgs.device):
            features, keys, values = self.backbone.forward_map(self.normalise(imgs))
        output = self._heads(features, (imgs.shape[-2], imgs.shape[-1]), heads, with_rays)
        tokens = self.tokens_per_frame(imgs.shape[-2], imgs.shape[-1])
        return DA3MapOutput(output, keys, values, tokens_per_frame=tokens)

    def forward_track(
        self,
        imgs: torch.Tensor,
        cache: CacheBuffers,
        *,
        heads: HeadSet = HeadSet.CAMERA,
        with_rays: bool = False,
    ) -> DA3Output:
        """Track F independent views [F, 3, H, W] against ``cache``; outputs have dims [F, 1, ...]."""
        if imgs.dim() != 4:
            raise ImageShapeError(
                f"tracking expects views [F, 3, H, W], got shape {tuple(imgs.shape)}"
            )
        with trunk_autocast(self.compute_dtype, imgs.device):
            features = self.backbone.forward_track(self.normalise(imgs.unsqueeze(0))[0], cache)
        # [1, F, ...] -> [F, 1, ...]: the views are independent sequences
        per_view = BackboneOutput(
            features=[feature.transpose(0, 1) for feature in features.features],
            camera_tokens=features.camera_tokens.transpose(0, 1),
            reference_view=None,
        )
        return self._heads(per_view, (imgs.shape[-2], imgs.shape[-1]), heads, with_rays)

    # ------------------------------------------------------------------ stages
    def normalise(self, imgs: torch.Tensor) -> torch.Tensor:
        """[B, N, 3, H, W] in [0, 1] -> ImageNet-normalised, fp32 (the residual stream's dtype)."""
        if imgs.dim() != 5 or imgs.shape[2] != 3:
            raise ImageShapeError(f"expected images [B, N, 3, H, W], got shape {tuple(imgs.shape)}")
        # constants, not buffers: DA3 checkpoints hold no normalisation tensors. Filled on the
        # device, not copied from the host: a CUDA graph cannot capture a host-to-device copy
        mean = _channel_constants(IMAGENET_MEAN, imgs.device).view(1, 1, 3, 1, 1)
        std = _channel_constants(IMAGENET_STD, imgs.device).view(1, 1, 3, 1, 1)
        return (imgs.float() - mean) / std

    def _heads(
        self, features: BackboneOutput, image_size: tuple[int, int], heads: HeadSet, with_rays: bool
    ) -> DA3Output:
        """Backbone outputs of [B, N] views -> ``DA3Output`` (float32).

        Autocast is off here, as in the official code, so the heads stay fp32 under a caller's
        ``torch.autocast`` too.
        """
        with torch.autocast(features.camera_tokens.device.type, enabled=False):
            return self._fp32_heads(features, image_size, heads, with_rays)

    def _fp32_heads(
        self, features: BackboneOutput, image_size: tuple[int, int], heads: HeadSet, with_rays: bool
    ) -> DA3Output:
        batch, views = features.camera_tokens.shape[:2]
        height, width = image_size
        pose_enc = self.cam_dec(features.camera_tokens.float())  # [B, N, 9]
        cam_to_world, intrinsics = decode_pose_encoding(pose_enc, (height, width))
        camera = {
            "pose_enc": pose_enc,
            "extrinsics": invert_rigid(cam_to_world),
            "intrinsics": intrinsics,
            "reference_view": features.reference_view,
        }
        if heads is HeadSet.CAMERA and not with_rays:
            return DA3Output(**camera)
        maps = self.head(
            [f.float().flatten(0, 1) for f in features.features],
            (height, width),
            with_rays=with_rays,
        )

        def per_view(tensor: torch.Tensor | None) -> torch.Tensor | None:
            return None if tensor is None else tensor.unflatten(0, (batch, views))

        return DA3Output(
            **camera,
            depth=per_view(maps.depth),
            depth_conf=per_view(maps.depth_conf),
            ray=per_view(maps.ray),
            ray_conf=per_view(maps.ray_conf),
        )
