"""The Pi3 (π³) network: configuration, modules, checkpoint loading (see ``model.py`` for the API)."""

from kvtracker_sdk.models.pi3.checkpoint import (
    LoadedPi3,
    check_state_dict,
    load_pi3,
    resolve_weights,
    weights_fingerprint,
)
from kvtracker_sdk.models.pi3.config import (
    Pi3Config,
    Pi3DecoderConfig,
    Pi3EncoderConfig,
    Pi3HeadsConfig,
)
from kvtracker_sdk.models.pi3.model import Pi3, Pi3MapOutput, Pi3Output

__all__ = [
    "LoadedPi3",
    "Pi3",
    "Pi3Config",
    "Pi3DecoderConfig",
    "Pi3EncoderConfig",
    "Pi3HeadsConfig",
    "Pi3MapOutput",
    "Pi3Output",
    "check_state_dict",
    "load_pi3",
    "resolve_weights",
    "weights_fingerprint",
]
