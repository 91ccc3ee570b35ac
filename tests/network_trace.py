"""Every ``connect()`` and ``bind()`` of a whole process tree, and the ones that leave loopback.

A socket listing sampled now and then misses a connection that lives for a millisecond (a cloud
metadata probe, a DNS query); this does not: the command runs under ``strace -f`` (every child,
grandchild and thread, from its first instruction to its exit) with ``--seccomp-bpf``, so the
kernel stops the process only at the traced system calls and the rest runs at full speed.

* ``connect`` to an AF_INET/AF_INET6 address other than 127.0.0.0/8, ::1 or ::ffff:127.x counts
  as leaving the machine. A UDP ``connect`` sends nothing, but it is how resolvers and "which is
  my address" probes start, so it counts too.
* ``bind`` to any address but loopback (0.0.0.0, ::, a network address) counts: such a server
  can be reached from outside.
* A DNS query counts even to a loopback resolver (``connect`` to port 53 on 127.0.0.53, as
  systemd-resolved's stub listens): the resolver forwards the name outside. So does a connect
  to systemd-resolved's own socket (``/run/systemd/resolve/...``, what glibc's ``nss-resolve``
  uses for host names).
* Other AF_UNIX sockets, AF_NETLINK (the kernel) and AF_UNSPEC (dissolving a UDP association)
  are local; any other family counts, so that nothing unknown passes silently. Not told apart:
  a host lookup through nscd's socket (``/var/run/nscd/socket``), which also answers user
  lookups (``getpwuid``) that many libraries make.

``python -m tests.network_trace -- COMMAND ...`` runs a command so and prints the count (see
``benchmarks/trace_connects.sh``). Tests' negative controls connect to 192.0.2.0/24 (TEST-NET-1,
RFC 5737: documentation only, routed nowhere, and a UDP connect sends nothing); the count leaves
them out and says how many it saw, so a traced test run that passes counts 0.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

TRACED_CALLS = ("connect", "bind")
LOCAL_FAMILIES = frozenset({"AF_UNIX", "AF_LOCAL", "AF_NETLINK", "AF_UNSPEC"})
DNS_PORT = 53
RESOLVER_SOCKETS = ("/run/systemd/resolve/",)  # a host name asked here is asked outside
CONTROL_NETWORK = ipaddress.ip_network("192.0.2.0/24")  # TEST-NET-1: the tests' controls

# "1234  connect(7, {sa_family=AF_INET, sin_port=htons(80), sin_addr=inet_addr("1.2.3.4")}, 16)"
# (also the first half of a call another thread interrupted: "... <unfinished ...>")
_CALL = re.compile(r"^(?P<pid>\d+)\s+(?P<call>connect|bind)\(\d+, \{sa_family=(?P<family>\w+)")
_PORT = re.compile(r"sin6?_port=htons\((?P<port>\d+)\)")
_HOST = re.compile(r'(?:inet_addr\("(?P<v4>[^"]+)"\)|inet_pton\(AF_INET6?, "(?P<v6>[^"]+)")')
_PATH = re.compile(r'sun_path=@?"(?P<path>[^"]*)"')


@dataclass(frozen=True)
class SocketCall:
    """One traced ``connect``/``bind``: the process, the call, the address family and host."""

    pid: int
    call: str  # "connect" or "bind"
    family: str  # "AF_INET", "AF_INET6", "AF_UNIX", ...
    host: str | None  # the IP for AF_INET/AF_INET6, the path for AF_UNIX
    port: int | None
    line: str  # the strace line, for the failure message

    @property
    def leaves_loopback(self) -> bool:
        if self.family in ("AF_UNIX", "AF_LOCAL"):
            return self.call == "connect" and (self.host or "").startswith(RESOLVER_SOCKETS)
        if self.family in LOCAL_FAMILIES:
            return False
        if self.family not in ("AF_INET", "AF_INET6") or self.host is None:
            return True  # an unknown family, or an address strace did not decode
        if self.call == "connect" and self.port == DNS_PORT:
            return True
        return not is_loopback(self.host)

    @property
    def is_control(self) -> bool:
        """A test's deliberate connect to TEST-NET-1 (see the module docstring)."""
        try:
            return self.call == "connect" and ipaddress.ip_address(self.host or "") in CONTROL_NETWORK
        except ValueError:
            return False


def is_loopback(host: str) -> bool:
    """127.0.0.0/8, ::1 and the IPv4-mapped ::ffff:127.x.y.z (how Ray's gRPC connects)."""
    try:
        address = ipaddress.ip_address(host.split("%")[0])
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_loopback


def parse_strace(text: str) -> list[SocketCall]:
    """The ``connect``/``bind`` calls of an ``strace -f -o`` log (other lines are skipped)."""
    calls = []
    for line in text.splitlines():
        match = _CALL.match(line)
        if match is None:
            continue
        port, host, path = _PORT.search(line), _HOST.search(line), _PATH.search(line)
        address = host["v4"] or host["v6"] if host else path["path"] if path else None
        calls.append(SocketCall(
            pid=int(match["pid"]),
            call=match["call"],
            family=match["family"],
            host=address,
            port=None if port is None else int(port["port"]),
            line=line,
        ))
    return calls


def outside(calls: Sequence[SocketCall]) -> list[SocketCall]:
    return [c for c in calls if c.leaves_loopback]


def strace_executable() -> str | None:
    return shutil.which("strace")


def traced_already() -> bool:
    """Whether a tracer (an outer ``strace -f``) watches this process: it then follows every
    child too, and a child cannot be traced by a second one."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("TracerPid:"):
                    return int(line.split()[1]) != 0
    except (OSError, ValueError):
        pass
    return False


def require_strace() -> None:
    """Skip a test without strace, failing instead under CI=true (.ci/run installs it); skip it
    under an outer tracer, which is already seeing the calls this test would trace."""
    import pytest

    if traced_already():
        pytest.skip("this test session already runs under a tracer (strace -f), which sees "
                    "these calls; a second tracer cannot attach")
    if strace_executable() is None:
        message = "strace is not installed (apt-get install strace): the connect() trace needs it"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " (CI=true: this is a failure, not a skip)")
        pytest.skip(message)


def traced_command(argv: Sequence[str], log: Path) -> list[str]:
    """``argv`` run under strace, writing every process's connect/bind calls to ``log``."""
    strace = strace_executable()
    if strace is None:
        raise FileNotFoundError("strace is not installed (apt-get install strace)")
    return [strace, "-f", "-qq", "--seccomp-bpf", "-s", "256", "-e", f"trace={','.join(TRACED_CALLS)}",
            "-e", "signal=none", "-o", str(log), "--", *argv]


@dataclass(frozen=True)
class TracedRun:
    process: subprocess.CompletedProcess[str]
    calls: list[SocketCall]

    @property
    def outside(self) -> list[SocketCall]:
        return outside(self.calls)


def run_traced(
    argv: Sequence[str],
    log: Path,
    *,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
    timeout: float = 300,
) -> TracedRun:
    """Run ``argv`` under the trace until it and every process it started have exited."""
    process = subprocess.run(traced_command(argv, log), capture_output=True, text=True,
                             env=None if env is None else dict(env), cwd=cwd, timeout=timeout)
    return TracedRun(process, parse_strace(log.read_text() if log.exists() else ""))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.network_trace",
        description="Run COMMAND under strace -f and count its connect()/bind() calls that "
                    "leave loopback (exit status: the command's, or 3 if any left).")
    parser.add_argument("--log", type=Path, help="keep the strace log here")
    parser.add_argument("--show", type=int, default=20, help="print at most N offending calls")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND [ARGS...]")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given")
    with tempfile.TemporaryDirectory() as scratch:
        log = args.log or Path(scratch) / "strace.log"
        # the command's own output goes straight through: only the count is ours
        returncode = subprocess.call(traced_command(command, log))
        calls = parse_strace(log.read_text() if log.exists() else "")
    controls = [c for c in outside(calls) if c.is_control]
    bad = [c for c in outside(calls) if not c.is_control]
    inet = [c for c in calls if c.family in ("AF_INET", "AF_INET6")]
    print(f"network-trace: {len(calls)} connect/bind calls traced ({len(inet)} inet, "
          f"{len({c.pid for c in calls})} processes); non-loopback: {len(bad)} "
          f"(and {len(controls)} tests' controls to TEST-NET-1 192.0.2.0/24)", file=sys.stderr)
    for call in bad[: args.show]:
        print(f"network-trace: OUTSIDE {call.line}", file=sys.stderr)
    print(len(bad))
    if returncode == 0 and bad:
        return 3
    return returncode


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
