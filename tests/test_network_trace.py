"""The connect()/bind() tracer the network tests rely on cannot miss a short-lived connection:
a grandchild that lives a few milliseconds and connects once is seen, and loopback is told
apart from everything else."""

from __future__ import annotations

import sys
from pathlib import Path

from tests.network_trace import SocketCall, parse_strace, require_strace, run_traced

# one interpreter that starts a child that starts a grandchild: the grandchild connects a UDP
# socket to a documentation address (192.0.2.0/24, TEST-NET-1; a UDP connect sends nothing) and
# exits at once (in a namespace with only loopback the connect fails, ENETUNREACH: the call is
# made and traced all the same); the parent binds all interfaces, then loopback, and connects
# over loopback
GRANDCHILD = (
    "import contextlib, socket\n"
    "with contextlib.suppress(OSError):\n"
    "    socket.socket(socket.AF_INET, socket.SOCK_DGRAM).connect(('192.0.2.1', 9))\n"
)
CHILD = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {GRANDCHILD!r}], check=True)"
PARENT = f"""
import socket, subprocess, sys
subprocess.run([sys.executable, '-c', {CHILD!r}], check=True)
wide = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
wide.bind(('0.0.0.0', 0))
server = socket.socket()
server.bind(('127.0.0.1', 0))
server.listen()
socket.create_connection(server.getsockname()).close()
"""


def test_a_grandchilds_short_connect_and_a_wide_bind_are_seen(tmp_path: Path) -> None:
    require_strace()
    run = run_traced([sys.executable, "-c", PARENT], tmp_path / "trace.log", timeout=60)
    assert run.process.returncode == 0, run.process.stderr
    seen = {(c.call, c.host, c.port) for c in run.outside}
    assert seen == {("connect", "192.0.2.1", 9), ("bind", "0.0.0.0", 0)}, run.outside
    assert len({c.pid for c in run.outside}) == 2  # the grandchild's connect, the parent's bind
    assert [c.is_control for c in run.outside if c.call == "connect"] == [True]
    loopback = [c for c in run.calls if c.host == "127.0.0.1"]
    assert {c.call for c in loopback} == {"bind", "connect"}
    assert not any(c.leaves_loopback for c in loopback)


def test_strace_lines_are_classified() -> None:
    log = "\n".join([
        '7 connect(7, {sa_family=AF_INET6, sin6_port=htons(38179), sin6_flowinfo=htonl(0), '
        'inet_pton(AF_INET6, "::ffff:127.0.0.1", &sin6_addr), sin6_scope_id=0}, 28) = -1 '
        'EINPROGRESS (Operation now in progress)',
        '8 connect(3, {sa_family=AF_INET6, sin6_port=htons(53), sin6_flowinfo=htonl(0), '
        'inet_pton(AF_INET6, "2001:db8::1", &sin6_addr), sin6_scope_id=0}, 28 <unfinished ...>',
        '9 connect(23, {sa_family=AF_INET, sin_port=htons(80), '
        'sin_addr=inet_addr("169.254.169.254")}, 16) = -1 EINPROGRESS',
        '9 connect(3, {sa_family=AF_UNIX, sun_path="/var/run/nscd/socket"}, 110) = -1 ENOENT',
        '9 bind(4, {sa_family=AF_NETLINK, nl_pid=0, nl_groups=00000000}, 12) = 0',
        '9 connect(5, {sa_family=AF_UNSPEC, sa_data="\\0\\0"}, 16) = 0',
        '9 bind(6, {sa_family=AF_INET6, sin6_port=htons(0), sin6_flowinfo=htonl(0), '
        'inet_pton(AF_INET6, "::", &sin6_addr), sin6_scope_id=0}, 28) = 0',
        '9 connect(6, {sa_family=AF_PACKET, sll_protocol=htons(ETH_P_ALL)}, 20) = 0',
        '9 connect(7, {sa_family=AF_UNIX, sun_path="/run/systemd/resolve/io.systemd.Resolve"}'
        ', 42) = 0',
        '9 connect(8, {sa_family=AF_INET, sin_port=htons(53), sin_addr=inet_addr("127.0.0.53")}'
        ', 16) = 0',
        "9 <... connect resumed>) = 0",
        "9 +++ exited with 0 +++",
    ])
    calls = parse_strace(log)
    assert [(c.pid, c.call, c.family, c.host, c.port) for c in calls] == [
        (7, "connect", "AF_INET6", "::ffff:127.0.0.1", 38179),
        (8, "connect", "AF_INET6", "2001:db8::1", 53),
        (9, "connect", "AF_INET", "169.254.169.254", 80),
        (9, "connect", "AF_UNIX", "/var/run/nscd/socket", None),
        (9, "bind", "AF_NETLINK", None, None),
        (9, "connect", "AF_UNSPEC", None, None),
        (9, "bind", "AF_INET6", "::", 0),
        (9, "connect", "AF_PACKET", None, None),
        (9, "connect", "AF_UNIX", "/run/systemd/resolve/io.systemd.Resolve", None),
        (9, "connect", "AF_INET", "127.0.0.53", 53),  # a DNS stub on loopback forwards outside
    ]
    assert [c.leaves_loopback for c in calls] == [
        False, True, True, False, False, False, True, True, True, True]
    assert not SocketCall(1, "connect", "AF_INET", "127.0.0.53", 80, "").leaves_loopback
    assert not SocketCall(1, "bind", "AF_INET", "127.0.0.1", 53, "").leaves_loopback
