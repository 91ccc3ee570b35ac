"""The seccomp filter the browser test starts chromedriver under: IPv6 UDP sockets fail to open
(so Chromium's reachability probe cannot connect), everything else still opens."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.viz.no_ipv6_udp import refuse_ipv6_udp, supported

PROBE = """
import errno, socket
def opens(family, kind):
    try:
        socket.socket(family, kind).close()
        return "ok"
    except OSError as error:
        return errno.errorcode[error.errno]
print(opens(socket.AF_INET6, socket.SOCK_DGRAM), opens(socket.AF_INET6, socket.SOCK_DGRAM | socket.SOCK_NONBLOCK),
      opens(socket.AF_INET6, socket.SOCK_STREAM), opens(socket.AF_INET, socket.SOCK_DGRAM),
      opens(socket.AF_INET, socket.SOCK_STREAM))
"""


@pytest.mark.skipif(not supported(), reason="the filter is written for x86-64 and AArch64 Linux")
@pytest.mark.parametrize("filtered", [False, True])
def test_only_ipv6_udp_sockets_are_refused(filtered: bool) -> None:
    run = subprocess.run([sys.executable, "-I", "-c", PROBE], capture_output=True, text=True,
                         check=True, preexec_fn=refuse_ipv6_udp if filtered else None)
    first = "EAFNOSUPPORT" if filtered else "ok"
    assert run.stdout.split() == [first, first, "ok", "ok", "ok"]
