"""A stand-in for ``cv2.VideoCapture``: serves given BGR frames, no device and no network."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class FakeCapture:
    """``grab``/``retrieve``/``read`` over ``frames``; ``interrupt_at``: the grab (0-based) that
    raises KeyboardInterrupt, as a Ctrl-C arriving while the camera waits for a frame would."""

    def __init__(self, frames: Sequence[np.ndarray], *, opened: bool = True,
                 interrupt_at: int | None = None) -> None:
        self.frames = list(frames)
        self.opened = opened
        self.interrupt_at = interrupt_at
        self.position = -1
        self.released = False
        self.settings: dict[int, float] = {}

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self.opened and not self.released

    def set(self, prop: int, value: float) -> bool:
        self.settings[prop] = value
        return True

    def grab(self) -> bool:
        if self.interrupt_at is not None and self.position + 1 == self.interrupt_at:
            raise KeyboardInterrupt
        self.position += 1
        return self.position < len(self.frames)

    def retrieve(self) -> tuple[bool, np.ndarray | None]:
        if 0 <= self.position < len(self.frames):
            return True, self.frames[self.position].copy()
        return False, None

    def read(self) -> tuple[bool, np.ndarray | None]:
        return (self.retrieve() if self.grab() else (False, None))

    def release(self) -> None:
        self.released = True
