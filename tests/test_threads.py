"""Thread defaults (``kvtracker_sdk/threads.py``): the automatic choice, the OpenMP wait policy
set before torch loads, and what ``TorchBackend`` reports and applies."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from kvtracker_sdk import threads
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.threads import ThreadSettings, choose_threads
from tests.conftest import OnnxExport


@pytest.mark.parametrize(
    ("cores", "load", "expected"),
    [(2, 0.0, 2), (2, 0.3, 2), (2, 0.8, 1), (2, 4.0, 1), (8, 2.2, 6), (1, 0.0, 1), (4, -1.0, 4)],
)
def test_spinning_threads_leave_the_busy_cores_alone(cores: int, load: float, expected: int) -> None:
    assert choose_threads(cores, load, passive=False) == expected


@pytest.mark.parametrize(("cores", "load"), [(2, 0.0), (2, 4.0), (8, 7.5)])
def test_passive_threads_use_every_core(cores: int, load: float) -> None:
    assert choose_threads(cores, load, passive=True) == cores


def test_resolve_user_auto_and_bad_values(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.1, 0.0, 0.0))
    monkeypatch.setattr(threads, "wait_policy", lambda: "active")
    auto = ThreadSettings.resolve(None, current=8)
    assert (auto.threads, auto.source, auto.usable_cores, auto.load_average) == (3, "auto", 4, 1.1)
    assert ThreadSettings.resolve(None, current=2).threads == 2  # torch's setting is a ceiling
    monkeypatch.setattr(threads, "wait_policy", lambda: "passive")
    assert ThreadSettings.resolve(None, current=8).threads == 4
    user = ThreadSettings.resolve(5, current=1)
    assert (user.threads, user.source) == (5, "user")
    assert "threads=5 (user; 4 cores, load 1.1" in user.describe()
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ConfigError):
            ThreadSettings.resolve(bad, current=2)  # type: ignore[arg-type]


def _policy_after_import(env: dict[str, str], torch_first: bool) -> str:
    code = ("import torch\n" if torch_first else "") + (
        "import os, kvtracker_sdk, sys\n"
        "from kvtracker_sdk.threads import wait_policy\n"
        "print(os.environ.get('OMP_WAIT_POLICY'), wait_policy().split()[0])\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    return result.stdout.strip()


def test_import_sets_a_passive_wait_policy_unless_chosen_or_too_late() -> None:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    assert _policy_after_import(env, torch_first=False) == "PASSIVE passive"
    assert _policy_after_import({**env, "OMP_WAIT_POLICY": "ACTIVE"}, False) == "ACTIVE active"
    # torch (and its OpenMP) loaded first: the variable would come too late, so it is not set
    assert _policy_after_import(env, torch_first=True) == "None active"


def test_torch_backend_applies_and_reports_threads() -> None:
    import torch

    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from tests.models.pi3.factories import random_pi3

    before = torch.get_num_threads()
    try:
        backend = TorchBackend(random_pi3(seed=1), threads=2)
        assert backend.threads.threads == 2 and backend.threads.source == "user"
        assert torch.get_num_threads() == 2
        torch.set_num_threads(1)
        auto = TorchBackend(random_pi3(seed=1))
        assert auto.threads.source == "auto" and auto.threads.threads == 1  # never above torch's
        assert auto.threads.wait_policy == threads.wait_policy()
    finally:
        torch.set_num_threads(before)


_TORCH_FIRST = """
import os, sys, time
import torch
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import ConfigError
from tests.models.pi3.factories import random_pi3
torch.set_num_threads(2)
auto = TorchBackend(random_pi3(seed=1))
print("auto", auto.threads.threads, torch.get_num_threads())
try:
    TorchBackend(random_pi3(seed=1), threads=2)
    print("refused no")
except ConfigError as exc:
    print("refused", "OMP_WAIT_POLICY=PASSIVE" in str(exc) and "import kvtracker_sdk" in str(exc))
if len(sys.argv) > 1:
    from kvtracker_sdk.backends.openvino import OpenVinoBackend
    torch.set_num_threads(2)
    OpenVinoBackend(sys.argv[1])
    print("openvino", torch.get_num_threads())
"""


def _torch_first(env: dict[str, str], *args: str) -> list[str]:
    result = subprocess.run(
        [sys.executable, "-c", _TORCH_FIRST, *args], env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout.split("\n")[:-1]


def test_torch_imported_first_gets_no_spinning_threads(
    onnx_exports: Callable[[str], OnnxExport],
) -> None:
    """An app that imports torch before kvtracker_sdk (OMP_WAIT_POLICY unset: libgomp, which
    read the variable when torch loaded, spins): the torch backend takes one thread by default
    and refuses two with the fix; the OpenVINO backend sets torch to one thread. A chosen
    policy (PASSIVE here; ACTIVE takes the same path) is honoured."""
    pytest.importorskip("openvino")
    folder = str(onnx_exports("da3").folder)
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).parents[1]), env.get("PYTHONPATH", "")])
    assert _torch_first(env, folder) == ["auto 1 1", "refused True", "openvino 1"]
    cores = min(2, threads.usable_cores())  # passive: every usable core, at most torch's 2
    passive = _torch_first({**env, "OMP_WAIT_POLICY": "PASSIVE"})
    assert passive == [f"auto {cores} {cores}", "refused no"]
