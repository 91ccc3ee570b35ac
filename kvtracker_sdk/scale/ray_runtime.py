"""Ray, started so that nothing leaves this machine, or joined if the app already connected.

A cluster this module starts is local and loopback-only (docs/network.md says what was checked):

* ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` makes Ray pick 127.0.0.1 as the node address (its
  documented single-machine mode; otherwise it advertises the machine's network address, its GCS,
  raylet and workers connect through it, and its runtime-env agent asks the kernel for a route
  to 8.8.8.8 to learn that address); ``_node_ip_address`` says the same explicitly.
* Usage statistics are off (``RAY_USAGE_STATS_ENABLED=0``, Ray's documented opt-out).
* No dashboard process at all. ``include_dashboard=False`` does not stop Ray from starting its
  dashboard ("API server") process: it still runs, loading only ``UsageStatsHead``, whose
  ``run()`` calls ``get_cluster_config_to_report()``, and that, without a
  ``~/ray_bootstrap_config.yaml``, requests the cloud metadata services (169.254.169.254, and
  ``metadata.google.internal`` through DNS) before it looks at whether usage statistics are on.
  No setting of Ray's skips it, so the head node is started without that process (see
  ``_without_api_server``). With usage statistics off it has nothing else to do: the dashboard
  UI, the job and state APIs it would serve are off with ``include_dashboard=False`` anyway.

``tests/scale/test_ray_network.py`` traces every ``connect()``/``bind()`` of every Ray process
from start to shutdown and fails on any non-loopback address.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
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
        with _without_api_server(ray):
            ray.init(
                _node_ip_address="127.0.0.1",
                include_dashboard=False,
                num_cpus=num_cpus,
                log_to_driver=False,
                configure_logging=False,
            )
    return ray


# two threads starting Ray at once must not restore each other's swap of the class attribute
_START_LOCK = threading.Lock()


@contextmanager
def _without_api_server(ray: Any) -> Iterator[None]:
    """While Ray starts a head node here, its dashboard ("API server") process is not started.

    ``Node.start_head_processes`` calls ``Node.start_api_server`` unconditionally; replacing that
    method for the duration of ``ray.init`` with one that starts nothing leaves the node exactly
    as when the dashboard fails to start (which Ray tolerates: ``webui_url`` is None). Why the
    process must not run: the module docstring. A Ray without that method is one this was not
    checked with; it is refused rather than started with a process that reaches out.
    """
    from ray._private import node as ray_node

    original = getattr(ray_node.Node, "start_api_server", None)
    if original is None:
        raise MissingDependencyError(
            f"Ray {getattr(ray, '__version__', '?')} starts its dashboard differently from the "
            "versions this SDK keeps off the network; start Ray yourself (ray.init) before using "
            "the Ray engine, or install a Ray this SDK supports (see docs/network.md)"
        )

    def start_no_api_server(self: Any, **_: Any) -> None:
        _log.debug("Ray's dashboard (API server) process is not started: it probes the network")

    with _START_LOCK:
        ray_node.Node.start_api_server = start_no_api_server  # type: ignore[method-assign]
        try:
            yield
        finally:
            ray_node.Node.start_api_server = original  # type: ignore[method-assign]


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
