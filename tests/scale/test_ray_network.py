"""Ray as this SDK starts it talks only to 127.0.0.1, from start to shutdown.

A fresh driver process starts Ray through ``ensure_ray`` (after importing ray itself, as an app
may), runs a task and an actor, lists the session's processes and shuts Ray down, all under
``tests/network_trace.py``: every ``connect()``/``bind()`` of the driver, the GCS, the raylet,
the agents and the workers is recorded, however short-lived. Nothing may leave loopback, and no
dashboard (API server) process may run: even with ``include_dashboard=False`` Ray starts one,
and it probes the cloud metadata service and DNS.

One more Ray start than the shared ``ray_session`` (the trace must see the start itself), so
the test is ``slow``.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from kvtracker_sdk.errors import MissingDependencyError
from tests.helpers import PROJECT_ROOT, dev_dependency
from tests.network_trace import require_strace, run_traced

DRIVER = """
import json, os, sys
import psutil
import ray  # before the SDK, as an app may: ensure_ray must cope

from kvtracker_sdk.scale.ray_runtime import ensure_ray

ray = ensure_ray(num_cpus=2)


@ray.remote(num_cpus=1)
def task_pid():
    return os.getpid()


@ray.remote(num_cpus=1)
class Echo:
    def pid(self):
        return os.getpid()


pids = ray.get([task_pid.remote(), Echo.remote().pid.remote()])
session_dir = ray._private.worker._global_node.get_session_dir_path()
processes = []
for process in psutil.process_iter(["pid", "cmdline"]):
    cmdline = " ".join(process.info["cmdline"] or [])
    if session_dir in cmdline or process.info["pid"] in pids:
        processes.append(cmdline)
ray.shutdown()
print(json.dumps({"processes": processes, "pids": pids}))
"""


@pytest.mark.slow
def test_a_ray_session_connects_and_binds_only_to_loopback(tmp_path: Path) -> None:
    dev_dependency("ray")
    dev_dependency("psutil")
    require_strace()
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    for inherited in ("RAY_USAGE_STATS_ENABLED", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"):
        env.pop(inherited, None)  # the SDK must set what it needs, not the test's environment
    run = run_traced([sys.executable, "-c", DRIVER], tmp_path / "ray.strace", env=env,
                     timeout=240)
    assert run.process.returncode == 0, run.process.stderr[-4000:]
    report = json.loads(run.process.stdout.strip().splitlines()[-1])
    names = " ".join(report["processes"])
    assert "gcs_server" in names and "raylet" in names  # the session's daemons were listed
    # the trace saw the session's TCP traffic: several processes connected over loopback
    inet = [c for c in run.calls if c.call == "connect" and c.family in ("AF_INET", "AF_INET6")]
    assert len({c.pid for c in inet}) >= 3, [c.line for c in inet]
    assert [c.line for c in run.outside] == []
    assert [p for p in report["processes"] if "dashboard/dashboard.py" in p] == []


def test_the_dashboard_is_kept_out_only_while_ray_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    ray = dev_dependency("ray")
    from ray._private import node as ray_node

    from kvtracker_sdk.scale.ray_runtime import _without_api_server

    original = ray_node.Node.start_api_server
    with _without_api_server(ray):
        replaced = ray_node.Node.start_api_server
        assert replaced is not original
        assert replaced(object(), include_dashboard=False, raise_on_failure=False) is None
    assert ray_node.Node.start_api_server is original  # restored: other clusters are untouched
    # a Ray that starts its dashboard some other way is refused, not started with the probe
    monkeypatch.delattr(ray_node.Node, "start_api_server")
    with pytest.raises(MissingDependencyError, match="start Ray yourself"), \
            _without_api_server(ray):
        pass
