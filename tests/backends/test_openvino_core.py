"""One OpenVINO ``Core`` per process, so that Ctrl-C after backends come and go is still a
KeyboardInterrupt (``openvino_core``'s docstring: the CPU plugin's alternate signal stack).

The child process makes two ``OpenVinoBackend``s on the session's DA3 export, drops them in the
order they were made, then raises SIGINT in its main thread. With a ``Core`` per backend (the
code before ``shared_core``) the child died of SIGSEGV (-11) at the SIGINT; the test also reads
the main thread's alternate signal stack and checks that it lies in mapped memory.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

from tests.conftest import OnnxExport
from tests.helpers import dev_dependency

CHILD = textwrap.dedent(
    """
    import ctypes, gc, signal, sys
    # Python's own SIGINT handler, whatever the parent left (a shell's background job starts
    # with SIGINT ignored, and Python then installs none): the handler that runs on the
    # alternate stack is what this test is about
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from kvtracker_sdk.backends.openvino import OpenVinoBackend

    class Stack(ctypes.Structure):
        _fields_ = [("sp", ctypes.c_void_p), ("flags", ctypes.c_int), ("size", ctypes.c_size_t)]

    def alternate_stack_is_mapped():
        stack = Stack()
        assert ctypes.CDLL(None).sigaltstack(None, ctypes.byref(stack)) == 0
        if stack.flags & 2 or not stack.sp:  # SS_DISABLE: signals run on the thread's stack
            return True
        with open("/proc/self/maps") as maps:
            ranges = [line.split()[0].split("-") for line in maps]
        return any(int(lo, 16) <= stack.sp < int(hi, 16) for lo, hi in ranges)

    first = OpenVinoBackend(sys.argv[1], threads=1)
    second = OpenVinoBackend(sys.argv[1], threads=1)
    first.close(); del first; gc.collect()
    second.close(); del second; gc.collect()
    print("alternate stack mapped:", alternate_stack_is_mapped(), flush=True)
    try:
        signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        print("KeyboardInterrupt", flush=True)
    """
)


def test_ctrl_c_after_two_backends_is_a_keyboard_interrupt(
    onnx_exports: Callable[[str], OnnxExport],
) -> None:
    dev_dependency("openvino")
    folder: Path = onnx_exports("da3").folder
    child = subprocess.run(
        [sys.executable, "-c", CHILD, str(folder)], capture_output=True, text=True, timeout=300
    )
    assert child.returncode == 0, (child.returncode, child.stdout, child.stderr[-2000:])
    assert child.stdout.splitlines() == ["alternate stack mapped: True", "KeyboardInterrupt"]
