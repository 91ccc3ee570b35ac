"""Helpers shared by tests (importable as ``tests.helpers``)."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = PROJECT_ROOT.parent / "shared"


def shared_path(*parts: str) -> Path:
    """Path inside ``../shared``; skips the test (fails under CI=true) if it is missing."""
    path = SHARED_DIR.joinpath(*parts)
    if not path.exists():
        message = f"{path} is missing: tests that read ../shared need it beside the checkout"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " (CI=true: this is a failure, not a skip)")
        pytest.skip(message)
    return path


def dev_dependency(module: str) -> ModuleType:
    """Import a development-only dependency (evo, plyfile); skip without it, fail under CI=true.

    CI installs the ``[dev]`` extra, so a missing module there is a broken install, and the
    cross-checks that need it must not go green by skipping.
    """
    if os.environ.get("CI", "").lower() == "true":
        try:
            return importlib.import_module(module)
        except ImportError as exc:
            pytest.fail(f"{module} is missing under CI=true (is it in the [dev] extra?): {exc}")
    return pytest.importorskip(module)


# oneDNN ISA caps below AVX-512 (``ONEDNN_MAX_CPU_ISA``; ``tests/cpu_variants.py`` sets them)
_CAPS_WITHOUT_BF16_KERNELS = frozenset({"SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2"})


def openvino_bf16_or_skip() -> None:
    """Skip an OpenVINO bf16 test under a oneDNN ISA cap below AVX-512 on a CPU that has bf16.

    OpenVINO's CPU plugin decides from the CPU's own flags (cpuid) that it can run bf16, and the
    cap does not change them; its bundled oneDNN then honours the cap and refuses the bf16
    kernels ("Supported primitive descriptors list is empty"), so compiling fails. No real CPU is
    in that state: one without AVX-512 reports no bf16, and OpenVINO runs the hint in fp32. The
    AVX-512 cap and the machine's default run these tests.
    """
    if not openvino_bf16_usable():
        pytest.skip(f"ONEDNN_MAX_CPU_ISA={os.environ['ONEDNN_MAX_CPU_ISA']} on a bf16 CPU: "
                    "OpenVINO asks for bf16 kernels the cap forbids, a state no real CPU is in "
                    "(tests/helpers.py says why)")


def openvino_bf16_usable() -> bool:
    """False exactly in the capped state ``openvino_bf16_or_skip`` describes."""
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA", "").upper()
    return not (cap in _CAPS_WITHOUT_BF16_KERNELS and _cpu_has_bf16())


def _cpu_has_bf16() -> bool:
    try:
        with open("/proc/cpuinfo") as info:
            return any(flag in info.read().split() for flag in ("avx512_bf16", "amx_bf16"))
    except OSError:
        return False
