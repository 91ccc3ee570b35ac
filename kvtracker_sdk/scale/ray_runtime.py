"""Ray, started so that nothing leaves this machine, or joined if the app already connected.

A cluster this module starts is local and loopback-only: ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``
makes Ray pick 127.0.0.1 as the node address (its documented single-machine mode; otherwise it
advertises the machine's network address and its GCS, raylet and workers connect through it),
``_node_ip_address`` says the same explicitly, the dashboard is off and usage statistics are off
(``RAY_USAGE_STATS_ENABLED=0``, Ray's documented opt-out). ``tests/scale/test_ray_network.py``
lists the sockets of every Ray process and fails on any non-loopback address.
"""

from __future__ import annotations

import os
from typing import Any

from kvtracker_sdk.errors import MissingDependencyError
from kvtracker_sdk.log import get_logger

__all__ = ["LOOPBACK_ENVIRONMENT", "actor_class", "ensure_ray", "import_ray"]

_log = get_logger(__name__)

LOOPBACK_ENVIRONMENT = {
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
}


def import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise MissingDependencyError.for_extra("ray", "the Ray engine needs Ray") from exc
    return ray


def ensure_ray(*, num_cpus: int | None = None) -> Any:
    """The ``ray`` module, initialised: the app's cluster if it already called ``ray.init``,
    else a new local one bound to 127.0.0.1 (see the module docstring)."""
    # before importing ray: it reads these at import and at init, and its workers inherit them
    for key, value in LOOPBACK_ENVIRONMENT.items():
        os.environ.setdefault(key, value)
    ray = import_ray()
    if not ray.is_initialized():
        _loopback_node_address()
        # all of the machine's cores unless told otherwise: a cluster sized for the first
        # caller's worker count would starve a later, larger pool
        num_cpus = max(num_cpus or 0, os.cpu_count() or 1)
        _log.info("starting a local Ray cluster bound to 127.0.0.1", num_cpus=num_cpus)
        ray.init(
            _node_ip_address="127.0.0.1",
            include_dashboard=False,
            num_cpus=num_cpus,
            log_to_driver=False,
            configure_logging=False,
        )
    return ray


def _loopback_node_address() -> None:
    """Make sure the cluster we start advertises 127.0.0.1.

    Ray reads ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` once, when ``ray`` is first imported; an app
    (or a test) that imported ray before calling us froze the default (use the machine's network
    address). Its node-address lookup reads the module constant at call time, so setting the
    constant to what the variable would have given is the one place this can be fixed without
    starting Ray in another process. Checked by ``tests/scale/test_ray_network.py``.
    """
    import ray._private.ray_constants as ray_constants

    if os.environ.get("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER") == "0":
        ray_constants.ENABLE_RAY_CLUSTER = False


def actor_class(cls: type, **options: Any) -> Any:
    """``cls`` as a Ray actor class (one CPU each unless ``options`` say otherwise)."""
    ray = import_ray()
    return ray.remote(num_cpus=options.pop("num_cpus", 1), **options)(cls)
