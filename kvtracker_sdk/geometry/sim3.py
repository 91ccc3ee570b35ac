"""Similarity transforms and the Umeyama alignment.

Every mapping pass of a multi-view transformer returns poses in its own frame and scale; the SDK
keeps one world frame by chaining Sim(3) corrections (``tracking/core/gauge.py``) and evaluates
trajectories after a Sim(3) or SE(3) alignment (``eval/``).

``umeyama_alignment`` is written out here (about 20 lines) rather than taken from evo because evo
is GPL-3 and may not be a runtime dependency; tests check it against evo.
Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two point
patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.errors import InputError

__all__ = ["Sim3", "umeyama_alignment"]


@dataclass(frozen=True)
class Sim3:
    """``x -> scale * R @ x + t``, acting on points; on poses ``T -> S ∘ T`` (see apply_to_pose)."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    def __post_init__(self) -> None:
        try:
            R = np.array(self.rotation, dtype=np.float64).reshape(3, 3)
            t = np.array(self.translation, dtype=np.float64).reshape(3)
            scale_ok = bool(np.isfinite(self.scale)) and self.scale > 0
        except (TypeError, ValueError) as exc:  # wrong sizes, not numbers
            raise InputError(
                f"Sim3 needs a 3x3 rotation, 3 translation numbers and a scale: {exc}"
            ) from exc
        if not scale_ok:
            raise InputError(f"Sim3 scale must be finite and > 0, got {self.scale}")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def identity(cls) -> Sim3:
        return cls(np.eye(3), np.zeros(3), 1.0)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Sim3:
        """From a 4x4 ``[[s R, t], [0, 1]]``."""
        M = np.asarray(matrix, dtype=np.float64)
        sR = M[:3, :3]
        scale = float(np.cbrt(np.linalg.det(sR)))
        return cls(sR / scale, M[:3, 3], scale)

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def inverse(self) -> Sim3:
        R_inv = self.rotation.T
        s_inv = 1.0 / self.scale
        return Sim3(R_inv, -s_inv * (R_inv @ self.translation), s_inv)

    def compose(self, other: Sim3) -> Sim3:
        """``self ∘ other`` (apply ``other`` first)."""
        return Sim3(
            self.rotation @ other.rotation,
            self.scale * (self.rotation @ other.translation) + self.translation,
            self.scale * other.scale,
        )

    def __matmul__(self, other: Sim3) -> Sim3:
        return self.compose(other)

    def apply_to_points(self, points: np.ndarray) -> np.ndarray:
        """Points [..., 3] mapped to the target frame."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    def apply_to_pose(self, T_world_cam: np.ndarray) -> np.ndarray:
        """A camera pose (or stack [..., 4, 4]) moved to the target frame, kept rigid.

        The camera centre moves like a point; the orientation rotates; the scale changes only
        the translation, so the result is still a rigid ``T_world_cam``.
        """
        T = np.asarray(T_world_cam, dtype=np.float64)
        out = np.array(T, copy=True)
        out[..., :3, :3] = self.rotation @ T[..., :3, :3]
        out[..., :3, 3] = self.apply_to_points(T[..., :3, 3])
        return out


def umeyama_alignment(
    source: np.ndarray, target: np.ndarray, *, with_scale: bool = True
) -> Sim3:
    """The Sim(3) (or SE(3) if ``with_scale`` is False) minimising ``|target - S(source)|²``.

    ``source`` and ``target`` are [N, 3] corresponding points, N >= 3 and not collinear for a
    unique rotation (N >= 1 still returns a usable transform: identity rotation for N < 2).
    """
    src = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape or len(src) == 0:
        raise InputError(
            f"need matching non-empty [N,3] point sets, got {src.shape} and {dst.shape}"
        )
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    var_src = float(np.mean(np.sum(src_c**2, axis=1)))
    cov = dst_c.T @ src_c / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / var_src) if with_scale and var_src > 0 else 1.0
    if scale <= 0 or not np.isfinite(scale):
        scale = 1.0
    t = mu_dst - scale * R @ mu_src
    return Sim3(R, t, scale)
