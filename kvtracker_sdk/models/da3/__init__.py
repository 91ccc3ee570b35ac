"""The Depth Anything 3 network: configuration, modules, checkpoint loading, SDK conventions.

See ``model.py`` for the passes (full forward, reference-pinned mapping, cached tracking),
``backbone.py`` for the alternating local/global DINOv2 backbone and the camera tokens, and
``conventions.py`` for the conversion to the SDK's ``T_world_cam`` / confidence in [0, 1].
"""

from kvtracker_sdk.models.da3.checkpoint import HUB_REPOS, LoadedDA3, canonical_state_dict, load_da3
from kvtracker_sdk.models.da3.config import (
    DA3BackboneConfig,
    DA3CameraEncoderConfig,
    DA3Config,
    DA3HeadConfig,
)
from kvtracker_sdk.models.da3.conventions import (
    SDKOutput,
    confidence_from_depth_conf,
    sdk_outputs,
    to_sdk,
    unproject_depth,
)
from kvtracker_sdk.models.da3.model import DA3MapOutput, DA3Output, DepthAnything3
from kvtracker_sdk.models.da3.reference_view import ReferenceStrategy, select_reference_view

__all__ = [
    "HUB_REPOS",
    "DA3BackboneConfig",
    "DA3CameraEncoderConfig",
    "DA3Config",
    "DA3HeadConfig",
    "DA3MapOutput",
    "DA3Output",
    "DepthAnything3",
    "LoadedDA3",
    "ReferenceStrategy",
    "SDKOutput",
    "canonical_state_dict",
    "confidence_from_depth_conf",
    "load_da3",
    "sdk_outputs",
    "select_reference_view",
    "to_sdk",
    "unproject_depth",
]
