"""Start a process in which IPv6 UDP sockets cannot be made, so Chromium's reachability probe
never connects anywhere.

Before every host resolution, even of ``127.0.0.1``, Chromium (and chromedriver, which shares
its network stack) checks whether IPv6 reaches the internet at most once a second: it opens a UDP
socket and ``connect()``s it to Google's public DNS, ``2001:4860:4860::8888`` port 443
(``HostResolverManager::StartIPv6ReachabilityCheck`` in ``net/dns/host_resolver_manager.cc``).
No switch or feature turns the probe off. A UDP connect sends no packet, but the suite's tracer
counts every non-loopback ``connect()``, as it should: it is how a resolver starts.

The browser test therefore starts chromedriver (and the Chromium it starts, which inherits the
filter) under a seccomp filter that refuses ``socket(AF_INET6, SOCK_DGRAM, ...)`` with
``EAFNOSUPPORT``. The probe's socket fails to open, Chromium takes IPv6 as unreachable, and no
``connect()`` is made; the page is served on 127.0.0.1 over IPv4 TCP, which the filter leaves
alone. The filter is a dozen BPF instructions written here rather than a new test dependency
(``libseccomp``'s Python binding) for one rule.
"""

from __future__ import annotations

import ctypes
import errno
import platform
import socket

# seccomp_data (linux/seccomp.h): u32 nr, u32 arch, u64 instruction_pointer, u64 args[6];
# the low 32 bits of args[i] sit at 16 + 8 * i on little-endian machines.
_NR_OFFSET, _ARCH_OFFSET, _ARG0_LOW, _ARG1_LOW = 0, 4, 16, 24
_LD_W_ABS, _JEQ_K, _AND_K, _RET_K = 0x20, 0x15, 0x54, 0x06  # BPF opcodes (linux/filter.h)
_RET_ALLOW = 0x7FFF0000
_RET_ERRNO = 0x00050000
_SOCK_TYPE_MASK = 0xF  # socket(2)'s type without SOCK_NONBLOCK / SOCK_CLOEXEC
_PR_SET_NO_NEW_PRIVS, _PR_SET_SECCOMP, _SECCOMP_MODE_FILTER = 38, 22, 2

# machine -> (AUDIT_ARCH_*, __NR_socket)
_ARCHES = {"x86_64": (0xC000003E, 41), "aarch64": (0xC00000B7, 198)}


class _SockFilter(ctypes.Structure):
    _fields_ = [("code", ctypes.c_uint16), ("jt", ctypes.c_uint8), ("jf", ctypes.c_uint8),
                ("k", ctypes.c_uint32)]


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_uint16), ("filter", ctypes.POINTER(_SockFilter))]


def supported() -> bool:
    """Whether this machine's architecture has the filter (x86-64 and AArch64 Linux)."""
    return platform.system() == "Linux" and platform.machine() in _ARCHES


def _program() -> list[tuple[int, int, int, int]]:
    arch, nr_socket = _ARCHES[platform.machine()]
    allow = 10  # index of the final RET ALLOW; a jump of k lands on (its index + 1 + k)
    return [
        (_LD_W_ABS, 0, 0, _ARCH_OFFSET),
        (_JEQ_K, 0, allow - 2, arch),
        (_LD_W_ABS, 0, 0, _NR_OFFSET),
        (_JEQ_K, 0, allow - 4, nr_socket),
        (_LD_W_ABS, 0, 0, _ARG0_LOW),
        (_JEQ_K, 0, allow - 6, socket.AF_INET6),
        (_LD_W_ABS, 0, 0, _ARG1_LOW),
        (_AND_K, 0, 0, _SOCK_TYPE_MASK),
        (_JEQ_K, 0, allow - 9, socket.SOCK_DGRAM),
        (_RET_K, 0, 0, _RET_ERRNO | errno.EAFNOSUPPORT),
        (_RET_K, 0, 0, _RET_ALLOW),
    ]


def refuse_ipv6_udp() -> None:
    """Install the filter in this process; it holds for every child and survives ``exec``.

    Meant as a ``preexec_fn`` (it runs in the forked child before ``exec``). Raises ``OSError``
    when the kernel refuses the filter.
    """
    program = _program()
    filters = (_SockFilter * len(program))(*[_SockFilter(*instruction) for instruction in program])
    fprog = _SockFprog(len(program), filters)
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
    if libc.prctl(_PR_SET_SECCOMP, _SECCOMP_MODE_FILTER, ctypes.byref(fprog), 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_SECCOMP)")

