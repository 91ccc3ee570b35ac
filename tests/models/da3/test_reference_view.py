"""Reference-view strategies on hand-made cls tokens."""

from __future__ import annotations

import pytest
import torch

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.da3 import select_reference_view


def _tokens() -> torch.Tensor:
    """[1, 5, 3]: views 0-3 spread around the x axis with norms 1..4, view 4 an outlier on z."""
    return torch.tensor(
        [[[1.0, 0.0, 0.0], [2.0, 0.2, 0.0], [3.0, 0.0, 0.3], [4.0, 0.4, 0.0], [0.0, 0.0, 5.0]]]
    )


def test_position_strategies_and_the_three_view_threshold() -> None:
    tokens = _tokens()
    assert select_reference_view(tokens, "first").tolist() == [0]
    assert select_reference_view(tokens, "middle").tolist() == [2]
    # fewer than 3 views: always view 0, whatever the strategy
    for strategy in ("middle", "saddle_balanced", "saddle_sim_range"):
        assert select_reference_view(tokens[:, 3:], strategy).tolist() == [0]  # type: ignore[arg-type]


def test_saddle_strategies_follow_their_definitions() -> None:
    tokens = torch.cat([_tokens(), _tokens().flip(1)])  # batch of 2, second reversed
    unit = tokens / tokens.norm(dim=-1, keepdim=True)
    similarity = unit @ unit.transpose(1, 2) - torch.eye(5)

    def scaled(score: torch.Tensor) -> torch.Tensor:
        low, high = score.min(1, keepdim=True).values, score.max(1, keepdim=True).values
        return (score - low) / (high - low + 1e-8)

    scores = (similarity.sum(-1) / 4, tokens.norm(dim=-1), unit.var(dim=-1))
    balance = sum((scaled(score) - 0.5).abs() for score in scores)
    chosen = select_reference_view(tokens, "saddle_balanced")
    assert chosen.tolist() == balance.argmin(1).tolist()  # type: ignore[union-attr]
    assert chosen[0] + chosen[1] == 4  # reversing the views mirrors the choice
    spread = similarity.max(-1).values - similarity.min(-1).values
    assert select_reference_view(tokens, "saddle_sim_range").tolist() == spread.argmax(1).tolist()


def test_unknown_strategy_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="saddle_balanced"):
        select_reference_view(_tokens(), "best")  # type: ignore[arg-type]
