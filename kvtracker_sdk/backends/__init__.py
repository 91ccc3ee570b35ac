"""Layer 3: the Backend contract and its implementations (imported lazily where heavy)."""

from kvtracker_sdk.backends.base import Backend, BackendInfo, MapResult, TrackResult

__all__ = ["Backend", "BackendInfo", "MapResult", "TrackResult"]
