"""The base of every family's architecture configuration (``Pi3Config``, ``DA3Config`` and their
sections): frozen, unknown keys refused, pydantic's ``ValidationError`` re-raised as
``ConfigError``, and a stable hash that goes into a backend's fingerprint."""

from __future__ import annotations

import hashlib
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from kvtracker_sdk.errors import ConfigError

__all__ = ["ArchitectureConfig"]


class ArchitectureConfig(BaseModel):
    """A frozen pydantic model; ``config_hash`` identifies the architecture."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise ConfigError(f"invalid {type(self).__name__}: {exc}") from exc

    def __setattr__(self, name: str, value: Any) -> None:
        raise ConfigError(
            f"{type(self).__name__} is frozen; make a copy with model_copy(update=...)"
        )

    @property
    def config_hash(self) -> str:
        """Stable hash of the architecture (16 hex chars), part of a backend's fingerprint."""
        return hashlib.sha256(self.model_dump_json().encode()).hexdigest()[:16]
