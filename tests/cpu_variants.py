"""CPU kernel variants the numeric tests must pass under, and a runner for any command.

The same float computation takes different kernels on different x86 CPUs, and so rounds
differently: oneDNN (``ONEDNN_MAX_CPU_ISA``), MKL (``MKL_ENABLE_INSTRUCTIONS``) and ATen's own
vectorised kernels (``ATEN_CPU_CAPABILITY``: softmax, layer norm, GELU, reductions) each pick the
widest instruction set the CPU has (AVX2, AVX-512, AVX-512 with BF16/VNNI, AMX), and the number
of threads changes how a reduction is split. A variant caps all three libraries alike (capping
only oneDNN leaves most of torch's float32 path as it was), or sets the thread count. The
machine's default is the widest its CPU offers.

Threads: the test session runs torch single-threaded (``tests/conftest.py``) unless
``KVTRACKER_TEST_TORCH_THREADS`` says otherwise, so the thread variants set that and
``OMP_NUM_THREADS`` (which ONNX Runtime, OpenVINO and MKL read) together.

``python -m tests.cpu_variants [--variant NAME ...] -- COMMAND ...`` runs a command once per
variant and prints a table (the README's test command under each: see CONTRIBUTING.md).
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence

TEST_THREADS = "KVTRACKER_TEST_TORCH_THREADS"

VARIANTS: Mapping[str, Mapping[str, str]] = {
    "avx2": {"ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
             "ATEN_CPU_CAPABILITY": "avx2"},
    "avx512_core": {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE", "MKL_ENABLE_INSTRUCTIONS": "AVX512",
                    "ATEN_CPU_CAPABILITY": "avx512"},
    "default": {},
    "threads1": {"OMP_NUM_THREADS": "1", TEST_THREADS: "1"},
    "threads2": {"OMP_NUM_THREADS": "2", TEST_THREADS: "2"},
}
# what a variant sets is its own: the caller's values of these are dropped first
_CONTROLLED = sorted({key for env in VARIANTS.values() for key in env})


def variant_environment(name: str, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """``base`` (default: this process's environment) with exactly ``name``'s settings."""
    env = {k: v for k, v in (os.environ if base is None else base).items() if k not in _CONTROLLED}
    env.update(VARIANTS[name])
    return env


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.cpu_variants",
        description="Run COMMAND once under each CPU kernel variant; exit 1 if any run failed.")
    parser.add_argument("--variant", action="append", choices=sorted(VARIANTS),
                        help="only these (repeatable; default: all)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND [ARGS...]")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given")
    rows = []
    for name in args.variant or list(VARIANTS):
        settings = " ".join(f"{k}={v}" for k, v in VARIANTS[name].items()) or "(the machine's)"
        print(f"== cpu variant {name}: {settings}", flush=True)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.monotonic()
        returncode = subprocess.call(command, env=variant_environment(name))
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        rows.append((name, returncode, time.monotonic() - start, cpu))
    print(f"\ncpu: {cpu_model()}; load average {os.getloadavg()[0]:.1f}")
    print("| variant | exit | wall s | cpu s |\n|---|---|---|---|")
    for name, returncode, wall, cpu in rows:
        print(f"| {name} | {returncode} | {wall:.0f} | {cpu:.0f} |")
    return 0 if all(row[1] == 0 for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
