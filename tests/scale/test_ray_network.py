"""Ray as this SDK starts it talks only to 127.0.0.1: every socket of every Ray process is
loopback (listening and connected), and no dashboard runs."""

from __future__ import annotations

import ipaddress
import os
from typing import Any

from tests.helpers import dev_dependency


def _loopback(ip: str) -> bool:
    address = ipaddress.ip_address(ip.split("%")[0])
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_loopback


def test_every_ray_socket_is_loopback(ray_session: Any) -> None:
    psutil = dev_dependency("psutil")
    ray = ray_session

    @ray.remote(num_cpus=1)
    def pid() -> int:
        return os.getpid()

    worker_pid = ray.get(pid.remote())  # a worker exists and answered
    session_dir = ray._private.worker._global_node.get_session_dir_path()
    processes = []
    for process in psutil.process_iter(["pid", "cmdline"]):
        cmdline = " ".join(process.info["cmdline"] or [])
        if session_dir in cmdline or process.info["pid"] in (worker_pid, os.getpid()):
            processes.append(process)
    names = " ".join(" ".join(p.info["cmdline"] or []) for p in processes)
    assert "gcs_server" in names and "raylet" in names and len(processes) >= 3
    assert not ray_session._private.worker._global_node.address_info.get("webui_url")  # no UI
    sockets = []
    for process in processes:
        try:
            sockets += process.net_connections(kind="inet")
        except psutil.NoSuchProcess:  # a worker that exited meanwhile has no sockets left
            continue
    assert sockets
    bad = [
        (s.laddr, s.raddr, s.status) for s in sockets
        if not _loopback(s.laddr.ip) or (s.raddr and not _loopback(s.raddr.ip))
    ]
    assert bad == [], bad
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"
