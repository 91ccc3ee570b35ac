"""The numeric verdicts hold whatever kernels the CPU picks: a chosen few numeric tests, each
variant in a fresh interpreter (the libraries read these settings once, when they load).

The suite itself is the machine's default instruction set on one torch thread; this runs the
variant of ``tests/cpu_variants.py`` farthest from it: AVX2 for oneDNN, MKL and ATen's kernels
(half the vector width: other blockings and reduction orders). Each variant costs a fresh
interpreter (~8 CPU-seconds), so the in-suite job is kept to this one; two threads, AVX-512
without BF16/VNNI/AMX, and the whole README command under every variant run with
``python -m tests.cpu_variants`` (CONTRIBUTING.md). The chosen tests: the end-to-end Pi3
run on real frames (its first pose once failed on an AMX CPU), and the Pi3 full forward against
the official outputs (the float32 poses with the thinnest margin: benchmarks/results/
cpu_variant_spread.md).
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.cpu_variants import variant_environment
from tests.helpers import PROJECT_ROOT, shared_path

CHOSEN = (
    "tests/tracking/test_tracker_pi3.py::test_real_frames_run_end_to_end",
    "tests/models/pi3/test_golden_parity.py::test_full_forward",
)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["avx2"])
def test_numeric_tests_pass_under_the_variant(variant: str) -> None:
    shared_path("golden", "pi3")  # skip (fail under CI=true) before starting a child without it
    env = variant_environment(variant)
    env["PYTHONPATH"] = str(PROJECT_ROOT)
    child = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-x", *CHOSEN],
        cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=600,
    )
    summary = child.stdout.strip().splitlines()[-1] if child.stdout.strip() else ""
    assert child.returncode == 0, child.stdout[-6000:] + child.stderr[-2000:]
    assert " passed" in summary and "skipped" not in summary, summary
