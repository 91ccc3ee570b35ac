"""Choosing DA3's reference view: the view that receives the reference camera token.

The reference camera defines the world frame of a pass. DA3 chooses it only when a call has at
least ``MIN_VIEWS_FOR_SELECTION`` (3) views; with fewer views, view 0 is the reference whatever
the strategy. The choice reads the cls tokens entering block ``alt_start - 1`` ([B, N, C]).

Strategies (the official ones, re-derived from ``reference_view_selector.py``):

- ``first``: view 0 — what a KV-Tracker mapping pass uses, so keyframe 0 anchors the world;
- ``middle``: view N // 2;
- ``saddle_balanced`` (DA3's default): with u the cls tokens scaled to unit length, three
  per-view scores — mean cosine similarity to the other views, |cls|, and the variance of u over
  channels — are each min-max normalised over the views; the view whose three scores are jointly
  closest to 0.5 (least sum of |score - 0.5|) wins;
- ``saddle_sim_range``: the view with the largest max - min similarity to the others.

The official code then moves the reference view to position 0 for the global blocks; this port
does not reorder (attention is permutation-equivariant), it only routes the camera tokens.
"""

from __future__ import annotations

from typing import Literal

import torch

from kvtracker_sdk.errors import ConfigError

__all__ = ["MIN_VIEWS_FOR_SELECTION", "ReferenceStrategy", "select_reference_view"]

ReferenceStrategy = Literal["first", "middle", "saddle_balanced", "saddle_sim_range"]
MIN_VIEWS_FOR_SELECTION = 3
_STRATEGIES = ("first", "middle", "saddle_balanced", "saddle_sim_range")


def _min_max(score: torch.Tensor) -> torch.Tensor:
    """Normalise [B, N] scores to [0, 1] over the views (the official epsilon 1e-8)."""
    low = score.min(dim=1, keepdim=True).values
    high = score.max(dim=1, keepdim=True).values
    return (score - low) / (high - low + 1e-8)


def _similarity_without_self(unit: torch.Tensor) -> torch.Tensor:
    """Cosine similarities [B, N, N] with the diagonal (self-similarity 1) subtracted."""
    views = unit.shape[1]
    similarity = unit @ unit.transpose(1, 2)
    return similarity - torch.eye(views, device=unit.device, dtype=unit.dtype)


def select_reference_view(
    cls_tokens: torch.Tensor, strategy: ReferenceStrategy = "saddle_balanced"
) -> torch.Tensor:
    """Index [B] (int64) of the reference view for cls tokens [B, N, C]."""
    if strategy not in _STRATEGIES:
        raise ConfigError(
            f"unknown reference-view strategy {strategy!r}; expected one of {_STRATEGIES}"
        )
    batch, views = cls_tokens.shape[:2]
    if views < MIN_VIEWS_FOR_SELECTION or strategy == "first":
        return torch.zeros(batch, dtype=torch.long, device=cls_tokens.device)
    if strategy == "middle":
        return torch.full((batch,), views // 2, dtype=torch.long, device=cls_tokens.device)

    norm = cls_tokens.norm(dim=-1)  # [B, N]
    unit = cls_tokens / norm.unsqueeze(-1)
    similarity = _similarity_without_self(unit)
    if strategy == "saddle_sim_range":
        spread = similarity.max(dim=-1).values - similarity.min(dim=-1).values
        return spread.argmax(dim=1)
    mean_similarity = similarity.sum(dim=-1) / (views - 1)
    balance = (
        (_min_max(mean_similarity) - 0.5).abs()
        + (_min_max(norm) - 0.5).abs()
        + (_min_max(unit.var(dim=-1)) - 0.5).abs()
    )
    return balance.argmin(dim=1)
