"""Scale out beyond one process: many sequences (``eval-many``) and many camera streams (a tracker
service), on a local process pool or on Ray. Layer 6, beside ``eval/``: it runs trackers and
scores them. Ray is an optional extra (``[ray]``), imported only by ``ray_runtime``.
"""

from kvtracker_sdk.scale.manifest import EvalManifest, SequenceSpec, load_manifest
from kvtracker_sdk.scale.runner import EvalManyResult, run_many
from kvtracker_sdk.scale.sequence_run import SequenceResult
from kvtracker_sdk.scale.service import TrackerHost

__all__ = [
    "EvalManifest",
    "EvalManyResult",
    "SequenceResult",
    "SequenceSpec",
    "TrackerHost",
    "load_manifest",
    "run_many",
]
