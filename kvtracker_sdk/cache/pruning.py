"""Token pruning of a ``KVCache``, once per rebuild: fewer cached tokens, a smaller map, a faster step.

Per global layer, a budget of cached tokens is kept; the rest are dropped from the cache (and
from map files). Which tokens go is decided without attention weights, from the keys alone, so
the fused attention kernels (which never materialise the weights) still serve every pass:

- **redundancy score** (InfiniteVGGT's key-diversity criterion, re-derived): the cosine similarity
  of a token's key to the layer's mean key, averaged over heads. A key close to the mean adds
  little that the others do not already say; the most similar ones are dropped first.
- or **uniform** (``score="uniform"``): no score at all — an evenly spread subset of the token
  axis (the tokens whose index ``i`` has the smallest ``frac(i·φ)``, a low-discrepancy sequence:
  any budget gives evenly spaced patches in every frame). It keeps an unbiased sample of the
  tokens; on the random-weight golden models it moves poses far less than key diversity does
  (``benchmarks/prune_maps.py``), while key diversity targets trained attention.
- **protected tokens** are always kept: every token of keyframe 0 (the anchor: the world frame and
  the reference confidence come from it) and each frame's extra tokens (Pi3's registers, DA3's
  camera token: the camera head reads them). Both families lay a frame out as
  ``[extra tokens | h*w patches]``, row-major patches.
- **object mode** (optional): patches outside a keyframe's dilated object mask were black in the
  masked input; their tokens are dropped before the budget is applied.

K is stored after RoPE, so a kept token needs no re-rotation. Every layer keeps the same number
of tokens (one budget), so the cache's layers stay equally long and an exported tracking graph,
which takes one ``past_length``, serves a pruned cache unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import CacheError

__all__ = [
    "PRUNE_SCORES",
    "object_token_mask",
    "protected_token_mask",
    "prune_cache",
    "redundancy_scores",
    "uniform_scores",
]

_GOLDEN = (5**0.5 - 1) / 2  # frac(i * golden ratio) spreads any prefix of indices evenly


def redundancy_scores(keys: torch.Tensor) -> torch.Tensor:
    """float32 [L]: cosine similarity of each key of ``keys`` [1, heads, L, head_dim] to the mean
    key of its head, averaged over heads (higher = more redundant)."""
    k = keys[0].float()  # [heads, L, d]
    mean = k.mean(dim=1, keepdim=True)  # [heads, 1, d]
    return torch.nn.functional.cosine_similarity(k, mean, dim=-1).mean(dim=0)


def uniform_scores(tokens: torch.Tensor) -> torch.Tensor:
    """float64 [L]: ``frac(i * φ)`` of each token index ``i`` of ``tokens`` (int64 [L], indices in
    the unpruned token axis); the lowest scores form an evenly spread subset for any budget."""
    return torch.frac(tokens.to(torch.float64) * _GOLDEN)


# how tokens are ranked for dropping (highest first): name -> (layer K [1, H, L, D], token
# indices [L]) -> scores [L]
PRUNE_SCORES: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "key_diversity": lambda keys, tokens: redundancy_scores(keys),
    "uniform": lambda keys, tokens: uniform_scores(tokens),
}


def protected_token_mask(
    num_keyframes: int, tokens_per_frame: int, extra_tokens_per_frame: int
) -> torch.Tensor:
    """bool [N*T]: keyframe 0's tokens and every frame's extra (register/camera) tokens."""
    protected = torch.zeros(num_keyframes, tokens_per_frame, dtype=torch.bool)
    protected[0] = True
    protected[:, :extra_tokens_per_frame] = True
    return protected.reshape(-1)


def object_token_mask(
    masks: Sequence[np.ndarray | None],
    *,
    patch_size: int,
    extra_tokens_per_frame: int,
    dilation_patches: int = 1,
) -> torch.Tensor:
    """bool [N*T]: tokens to keep in object mode, from each keyframe's object mask [H, W] at
    model resolution (None: keep the whole frame). A patch is kept if any of its pixels is in the
    mask, dilated by ``dilation_patches`` patches; extra tokens are always kept."""
    rows: list[torch.Tensor | None] = []
    for mask in masks:
        if mask is None:
            rows.append(None)
            continue
        m = torch.from_numpy(np.asarray(mask, dtype=bool))
        grid_h, grid_w = m.shape[0] // patch_size, m.shape[1] // patch_size
        # [H, W] -> [h, w]: a patch touches the object if any pixel does
        crop = m[: grid_h * patch_size, : grid_w * patch_size].float()
        touched = crop.reshape(grid_h, patch_size, grid_w, patch_size).amax(dim=(1, 3))
        if dilation_patches > 0:
            size = 2 * dilation_patches + 1
            touched = torch.nn.functional.max_pool2d(
                touched[None, None], size, stride=1, padding=dilation_patches
            )[0, 0]
        keep = torch.ones(extra_tokens_per_frame + grid_h * grid_w, dtype=torch.bool)
        keep[extra_tokens_per_frame:] = touched.reshape(-1) > 0
        rows.append(keep)
    tokens = next((len(r) for r in rows if r is not None), None)
    if tokens is None:
        raise CacheError("object_token_mask needs at least one keyframe with a mask")
    full = torch.ones(tokens, dtype=torch.bool)
    return torch.cat([full if r is None else r for r in rows])


def prune_cache(
    cache: KVCache,
    *,
    keep_ratio: float,
    extra_tokens_per_frame: int,
    allowed: torch.Tensor | None = None,
    score: str = "key_diversity",
) -> None:
    """Prune ``cache`` in place (it must not be pruned yet).

    Each layer keeps ``ceil(keep_ratio * candidates)`` tokens, ``candidates`` = the tokens in
    ``allowed`` (bool [N*T], e.g. ``object_token_mask``; None = all): the protected tokens first
    (``protected_token_mask`` — keyframe 0's within ``allowed`` and every frame's extra tokens;
    all of them, even above the budget), then the least redundant of the rest. The same count in
    every layer. ``score``: a key of ``PRUNE_SCORES`` (see the module docstring).
    """
    if score not in PRUNE_SCORES:
        raise CacheError(f"unknown pruning score {score!r}; known: {sorted(PRUNE_SCORES)}")
    if not 0.0 < keep_ratio <= 1.0:
        raise CacheError(f"keep_ratio must be in (0, 1], got {keep_ratio}")
    if cache.pruned:
        raise CacheError("the cache is already pruned: prune the unpruned map of a rebuild")
    full = cache.num_keyframes * cache.tokens_per_frame
    protected = protected_token_mask(
        cache.num_keyframes, cache.tokens_per_frame, extra_tokens_per_frame
    )
    allowed = torch.ones(full, dtype=torch.bool) if allowed is None else allowed.to(torch.bool)
    if allowed.shape != (full,):
        raise CacheError(f"allowed tokens must be bool [{full}], got {tuple(allowed.shape)}")
    # keyframe 0's tokens outside the object go too; the extra tokens never do
    extra = torch.zeros(cache.num_keyframes, cache.tokens_per_frame, dtype=torch.bool)
    extra[:, :extra_tokens_per_frame] = True
    protected = (protected & allowed) | extra.reshape(-1)
    allowed = allowed | protected
    budget = max(int(protected.sum()), math.ceil(keep_ratio * int(allowed.sum())))
    if budget >= full:
        return  # nothing to drop
    kept = []
    for layer in range(cache.layout.num_layers):
        scores = PRUNE_SCORES[score](cache.keys(layer), cache.kept_tokens(layer)).float()
        scores[~allowed] = math.inf  # never chosen unless the budget needs them (it does not)
        scores[protected] = -math.inf  # always chosen
        chosen = torch.topk(scores, budget, largest=False).indices
        kept.append(torch.sort(chosen).values)
    cache.keep_tokens(kept)
