"""Tracking quality: per-frame confidence -> confident or not, and the streak counters that decide
loss, recovery and relocalisation timeouts.

The monitor only counts; the ``Tracker`` turns its verdicts into state transitions. Confidence is
judged relative to a reference (keyframe 0's mean confidence in the current map), like the paper's
keyframe rejection rule, so the threshold does not depend on one model's absolute confidence scale.
A frame without a confidence (``HeadSet.CAMERA``) counts as confident: without a confidence head
there is no loss detection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.config import RelocalizationConfig

__all__ = ["ConfidenceMonitor", "QualityVerdict", "frame_confidence", "masked_mean"]


def masked_mean(confidence: np.ndarray, mask: np.ndarray | None) -> float:
    """Mean of a confidence map [h, w] over ``mask`` (all pixels without one)."""
    return float(confidence[mask].mean() if mask is not None else confidence.mean())


def frame_confidence(
    summary: float | None, confidence_map: np.ndarray | None, mask: np.ndarray | None
) -> float | None:
    """A tracked frame's confidence: the masked mean of its map when it has a mask (object
    mode), else the backend's summary (None without a confidence head)."""
    if mask is not None and confidence_map is not None:
        return masked_mean(confidence_map, mask)
    return summary


@dataclass(frozen=True)
class QualityVerdict:
    """What one frame says about tracking quality."""

    confident: bool
    lost: bool  # at least `lost_after` low-confidence frames in a row
    recovered: bool  # at least `recover_after` confident frames in a row
    timed_out: bool  # relocalising for at least `timeout_frames` frames


class ConfidenceMonitor:
    """Streak counters over tracked frames.

    ``reference`` is keyframe 0's mean confidence; a frame is confident when its confidence is at
    least ``threshold * reference``. ``relocalizing`` tells the monitor to count timeout frames.
    """

    def __init__(
        self,
        *,
        threshold: float,
        lost_after: int,
        recover_after: int,
        timeout_frames: int | None,
    ) -> None:
        self.threshold = float(threshold)
        self.lost_after = int(lost_after)
        self.recover_after = int(recover_after)
        self.timeout_frames = timeout_frames
        self.reference = 1.0
        self.reset()

    @classmethod
    def from_config(cls, config: RelocalizationConfig) -> ConfidenceMonitor:
        return cls(
            threshold=config.confidence_threshold,
            lost_after=config.lost_after,
            recover_after=config.recover_after,
            timeout_frames=config.timeout_frames,
        )

    def reset(self) -> None:
        """Clear every streak (new map, reset, recovered, state change)."""
        self.low_streak = 0
        self.high_streak = 0
        self.relocalizing_frames = 0

    def set_reference(self, reference: float) -> None:
        """Keyframe 0's mean confidence in the current map (positive; tiny values are clamped)."""
        self.reference = max(float(reference), 1e-6)

    def is_confident(self, confidence: float | None) -> bool:
        return confidence is None or confidence >= self.threshold * self.reference

    def update(self, confidence: float | None, *, relocalizing: bool) -> QualityVerdict:
        """Count one tracked frame; ``relocalizing`` is True while the tracker is RELOCALIZING."""
        confident = self.is_confident(confidence)
        if confident:
            self.high_streak += 1
            self.low_streak = 0
        else:
            self.low_streak += 1
            self.high_streak = 0
        self.relocalizing_frames = self.relocalizing_frames + 1 if relocalizing else 0
        timed_out = (
            relocalizing
            and self.timeout_frames is not None
            and self.relocalizing_frames >= self.timeout_frames
        )
        return QualityVerdict(
            confident=confident,
            lost=self.low_streak >= self.lost_after,
            recovered=self.high_streak >= self.recover_after,
            timed_out=timed_out,
        )
