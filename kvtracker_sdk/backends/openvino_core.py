"""The ``openvino`` module, imported without telemetry, and the process's one OpenVINO ``Core``.

Telemetry off: ``import openvino`` itself initialises OpenVINO's telemetry and sends an
"import" event to Google Analytics (``openvino/tools/ovc/__init__.py``, with the opt-in dialog
disabled: it sends unless the user opted out with ``opt_in_out --opt_out``), and writes a client
id under ``~/intel``. ``import_openvino`` imports openvino with ``openvino_telemetry`` hidden
from the import system, so that OpenVINO takes its own no-op stub (the path it takes when the
telemetry package is not installed); the package is visible again afterwards. The runtime itself
(``Core``, ``read_model``, ``compile_model``, inference) collects nothing. If the application
imported openvino before, the event was sent then: this SDK cannot take it back.
``tests/backends/test_openvino_network.py`` checks that importing, compiling and running make
no telemetry call and open no socket that is not loopback.

One ``Core`` per process, never released (``shared_core``): OpenVINO's CPU plugin gives the thread
that creates it a fresh alternate signal stack (``sigaltstack``, mmap'ed: AMX state needs a large
one) and, when the plugin is destroyed, restores the stack it found and unmaps its own
(``src/plugins/intel_cpu/src/sigstack_manager.cpp``, OpenVINO 2026.4). Each ``Core`` holds its
own plugin, so two Cores whose plugins die in the order they were made (plugin A saved the
interpreter's stack, B saved A's; A is unmapped, then B puts A's back) leave the thread's
alternate stack on unmapped memory, and the next signal with a handler run on it (Python's SIGINT
handler: Ctrl-C) kills the process with SIGSEGV, losing what a Ctrl-C should have saved. Two
backends made and dropped in a session did exactly that (``tests/backends/test_openvino_core.py``
reproduces it with plain Cores). With one Core the plugin is made once and its stack stays mapped
for the process's life. Its cost: the plugin's compiled-kernel cache and the CPU threads' pool are
shared by every backend in the process, which is what OpenVINO recommends anyway.
An application that makes Cores of its own can still hit the plugin bug with them; ``shared_core``
is public in this module so that it can use this one instead.
"""

from __future__ import annotations

import importlib
import sys
import threading
from typing import Any

from kvtracker_sdk.errors import MissingDependencyError

__all__ = ["import_openvino", "shared_core"]

_TELEMETRY = "openvino_telemetry"
_ABSENT = object()
_import_lock = threading.Lock()


def import_openvino() -> Any:
    """The ``openvino`` module imported without its telemetry (see the module docstring), or
    ``MissingDependencyError`` naming the ``[openvino]`` extra."""
    with _import_lock:
        first = "openvino" not in sys.modules
        saved = sys.modules.get(_TELEMETRY, _ABSENT)
        if first:
            sys.modules[_TELEMETRY] = None  # type: ignore[assignment]  # import -> ImportError
        try:
            return importlib.import_module("openvino")
        except ImportError as exc:
            raise MissingDependencyError.for_extra(
                "openvino", f"the OpenVINO backend needs openvino ({exc})") from exc
        finally:
            if first and saved is _ABSENT:
                sys.modules.pop(_TELEMETRY, None)
            elif first:
                sys.modules[_TELEMETRY] = saved  # type: ignore[assignment]


_core: Any = None
_core_lock = threading.Lock()


def shared_core() -> Any:
    """The process's one ``openvino.Core`` (made on first call, kept for the process's life: see
    the module docstring); ``MissingDependencyError`` without the ``[openvino]`` extra."""
    global _core
    with _core_lock:
        if _core is None:
            _core = import_openvino().Core()
        return _core
