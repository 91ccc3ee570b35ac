"""OpenVINO compiles and runs the graphs without telemetry and without touching the network.

A fresh interpreter (so that ``import openvino`` happens under watch; ``import openvino``
alone sends a telemetry event unless the SDK stops it) with an empty ``HOME`` records, from
before the import: the host of every socket connect/bind/send and host lookup and every child
process started (Python audit events: ``openvino-telemetry`` sends from a child process), every
call of ``openvino_telemetry``'s ``Telemetry`` (initialisation, sending), and, after compiling
and running, the hosts of the process's open inet sockets (``psutil``: native code's too). Every
host must be loopback, no child process, no telemetry call, nothing written to ``HOME`` (where
telemetry keeps its client id). A negative control, in the same process after the watch is
read, connects a UDP socket to 192.0.2.1 (no packet leaves: UDP connect only sets the peer) and
must be seen. The same child runs under ``tests/network_trace.py`` (strace: every connect() and
bind() of the process and any child, native code's included): the control is the one call that
leaves loopback.
"""

from __future__ import annotations

import ipaddress
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from tests.conftest import OnnxExport
from tests.helpers import dev_dependency, openvino_bf16_usable
from tests.network_trace import require_strace, run_traced, strace_executable, traced_already

WATCHED = """
import json, socket, sys

events = []


def host_of(address):
    return str(address[0]) if isinstance(address, tuple) else None  # None: a unix socket


def hook(event, args):
    if event in ("socket.connect", "socket.bind", "socket.sendto", "socket.sendmsg"):
        events.append([event, host_of(args[1])])
    elif event == "socket.getaddrinfo":
        events.append([event, None if args[0] is None else str(args[0])])
    elif event in ("os.fork", "os.posix_spawn", "subprocess.Popen", "os.system"):
        events.append([event, "a child process"])  # how openvino-telemetry sends


sys.addaudithook(hook)
telemetry = []
try:
    import openvino_telemetry
except ImportError:  # openvino without its telemetry package: nothing could send
    openvino_telemetry = None
if openvino_telemetry is not None:
    for name in ("init", "send_event", "send_error", "send_stack_trace", "start_session"):
        if hasattr(openvino_telemetry.Telemetry, name):
            def record(*args, _name=name, **kwargs):
                telemetry.append(_name)
            setattr(openvino_telemetry.Telemetry, name, record)

import numpy as np
import psutil
from kvtracker_sdk.backends.openvino import OpenVinoBackend

backend = OpenVinoBackend(sys.argv[1], precision=sys.argv[2], threads=1)
images = np.random.default_rng(0).integers(0, 256, (3, 112, 154, 3), dtype=np.uint8)
mapped = backend.map(images[:2])
backend.track(images[2], mapped.cache)
connections = psutil.Process().net_connections("inet")
sockets = [c.laddr.ip for c in connections] + [c.raddr.ip for c in connections if c.raddr]
watched = {"events": events[:], "telemetry": telemetry[:], "sockets": sockets}
try:  # the control; without a route (a loopback-only namespace) it fails after being seen
    socket.socket(socket.AF_INET, socket.SOCK_DGRAM).connect(("192.0.2.1", 9))
except OSError:
    pass
print(json.dumps({"watched": watched, "control": events[len(watched["events"]):]}))
"""


def is_loopback(host: str | None) -> bool:
    """Whether ``host`` (an ip, a host name, or None for a unix socket) is this machine."""
    if host is None or host == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host.split("%")[0])
    except ValueError:  # a host name other than localhost
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_loopback


def test_compiling_and_running_opens_no_outside_socket_and_no_telemetry(
    onnx_exports: Callable[[str], OnnxExport], tmp_path: Path
) -> None:
    dev_dependency("openvino")
    dev_dependency("psutil")
    folder = str(onnx_exports("pi3").folder)
    home = tmp_path / "home"  # where telemetry would keep its client id
    home.mkdir()
    # bf16, as the SDK's fastest CPU path runs; fp32 only where a oneDNN cap makes OpenVINO's
    # bf16 kernels unavailable (tests/helpers.openvino_bf16_or_skip says why)
    precision = "bfloat16" if openvino_bf16_usable() else "float32"
    command = [sys.executable, "-c", WATCHED, folder, precision]
    env = {**os.environ, "HOME": str(home)}
    traced = None
    if strace_executable() is not None and not traced_already():
        traced = run_traced(command, tmp_path / "openvino.strace", env=env, timeout=300)
        out = traced.process
    else:
        out = subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    recorded = json.loads(out.stdout.strip().splitlines()[-1])
    watched = recorded["watched"]
    assert [e for e in watched["events"] if not is_loopback(e[1])] == []
    assert [host for host in watched["sockets"] if not is_loopback(host)] == []
    assert watched["telemetry"] == [] and list(home.iterdir()) == []
    assert recorded["control"] == [["socket.connect", "192.0.2.1"]]  # the watch sees a send
    if traced is None:
        require_strace()  # the audit checks passed; the trace could not run (skip, or fail in CI)
        return
    assert [(c.call, c.host, c.port) for c in traced.outside] == [("connect", "192.0.2.1", 9)], [
        c.line for c in traced.outside]
