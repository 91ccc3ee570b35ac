"""Seeded hostile user files: camera files and eval-many manifests, as a careless or hostile
user would write them (absurd values of every type, deep nesting, YAML alias bombs, huge files,
FIFOs and devices behind innocent names).

A case is a :class:`Case`: how to make the file and which field names its rejection must
mention (``fields``: any of them; empty when the file is plausible and may be accepted). Shared
by the in-process fuzz tests and ``benchmarks/fuzz_inputs.py`` (each case in a fresh process).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from copy import deepcopy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

NAN, INF = float("nan"), float("inf")


@dataclass(frozen=True)
class Case:
    name: str
    suffix: str  # ".json", ".yaml"
    content: bytes | None  # None: ``special`` makes the path
    # every case must be refused; the message must name one of these ("": any typed error)
    fields: tuple[str, ...]
    special: str = ""  # "fifo", "dev-zero", "folder", "dangling-link"

    def make(self, folder: Path) -> Path:
        """Create the case's file in ``folder``; its path."""
        path = folder / f"case{self.suffix}"
        if path.is_dir() and not path.is_symlink():
            path.rmdir()
        elif os.path.lexists(path):
            path.unlink()
        if self.special == "fifo":
            os.mkfifo(path)
        elif self.special == "dev-zero":
            path.symlink_to("/dev/zero")
        elif self.special == "folder":
            path.mkdir()
        elif self.special == "dangling-link":
            path.symlink_to(folder / "nowhere")
        else:
            assert self.content is not None
            path.write_bytes(self.content)
        return path


def _dump(document: Any, suffix: str) -> bytes:
    if suffix == ".yaml":
        import yaml

        return yaml.safe_dump(document).encode()
    return json.dumps(document).encode()  # NaN/Infinity written as JSON's common extension


def _special_cases(kind: str) -> list[Case]:
    deep = ("[" * 100_000 + "]" * 100_000).encode()
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
        f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
        f"*{chr(97 + i)}]\n" for i in range(9)
    )
    return [
        Case(f"{kind}-fifo", ".json", None, ("FIFO",), "fifo"),
        Case(f"{kind}-dev-zero", ".json", None, ("character device",), "dev-zero"),
        Case(f"{kind}-folder", ".json", None, ("folder",), "folder"),
        Case(f"{kind}-dangling-link", ".json", None, ("no such file",), "dangling-link"),
        Case(f"{kind}-deep-json", ".json", deep, ("nested",)),
        Case(f"{kind}-deep-yaml", ".yaml", b"a: " + b"[" * 100_000, ("",)),
        Case(f"{kind}-alias-bomb", ".yaml", bomb.encode(), ("alias", "values")),
        Case(f"{kind}-huge", ".json", b" " * (2 << 20) + b"{}", ("bytes",)),
        Case(f"{kind}-not-utf8", ".json", b"\xff\xfe\x00{", ("UTF-8",)),
        Case(f"{kind}-empty", ".json", b"", ("",)),
        Case(f"{kind}-list", ".json", b"[1, 2]", ("",)),
        Case(f"{kind}-nan", ".json", b"NaN", ("",)),
        Case(f"{kind}-long-int", ".json", b"{\"width\": " + b"9" * 5000 + b"}", ("",)),
        Case(f"{kind}-python-object", ".yaml", b"!!python/object/apply:os.system ['true']", ("YAML",)),
    ]


# ---------------------------------------------------------------------------------- cameras
_CAMERA = {"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7, "width": 640, "height": 480,
           "distortion": [0.23, -0.78, -0.003, -0.0001, 0.92]}
_ROS = {"width": 640, "height": 480, "distortion_model": "plumb_bob",
        "D": [0.23, -0.78, -0.003, -0.0001, 0.92],
        "K": [520.9, 0.0, 325.1, 0.0, 521.0, 249.7, 0.0, 0.0, 1.0]}
_CALIBRATION = {"image_width": 640, "image_height": 480, "distortion_model": "plumb_bob",
                "camera_matrix": {"rows": 3, "cols": 3, "data": _ROS["K"]},
                "distortion_coefficients": {"rows": 1, "cols": 5, "data": _ROS["D"]}}
_NOT_NUMBERS: list[Any] = [NAN, INF, -INF, "640", [640], {"a": 1}, None, True]
_ABSURD: dict[str, list[Any]] = {
    "size": [0, -1, 0.5, 1e300, 10**30, 65537, 2**63, 5e-324],
    "focal": [0, -500.0, 5e-324, 1e-3, 1e308, 10**30, 1e9],
    "centre": [1e300, -1e308, 10**30, 1e6, -1e5],
    "distortion": [1e308, -1e308, 1e4, 10**30],
}
# field -> (kind, names a refusal may use)
_SDK_FIELDS = {"width": ("size", ("width",)), "height": ("size", ("height",)),
               "fx": ("focal", ("fx",)), "fy": ("focal", ("fy",)),
               "cx": ("centre", ("cx",)), "cy": ("centre", ("cy",))}
_K_FIELDS = {0: ("focal", ("fx", "K[0]")), 4: ("focal", ("fy", "K[4]")),
             2: ("centre", ("cx", "K[2]")), 5: ("centre", ("cy", "K[5]"))}


def _camera_mutation(rng: np.random.Generator) -> tuple[str, Any, tuple[str, ...]]:
    """(label, document, fields) of one mutated camera file."""
    layout = int(rng.integers(3))
    if layout == 0:
        document = deepcopy(_CAMERA)
        target = ["width", "height", "fx", "fy", "cx", "cy", "distortion"][rng.integers(7)]
    elif layout == 1:
        document = deepcopy(_ROS)
        target = ["width", "height", "K", "D"][rng.integers(4)]
    else:
        document = deepcopy(_CALIBRATION)
        target = ["image_width", "image_height", "camera_matrix", "distortion_coefficients"][
            rng.integers(4)]
    absurd = rng.random() < 0.6
    if target in ("distortion", "D", "distortion_coefficients"):
        holder = document[target]["data"] if isinstance(document[target], dict) else document[target]
        index = int(rng.integers(len(holder)))
        pool = _ABSURD["distortion"] if absurd else _NOT_NUMBERS
        holder[index] = pool[rng.integers(len(pool))]
        names = ("distortion", "D[")
    elif target in ("K", "camera_matrix"):
        holder = document[target]["data"] if isinstance(document[target], dict) else document[target]
        index = int(list(_K_FIELDS)[rng.integers(4)])
        kind, names = _K_FIELDS[index]
        pool = _ABSURD[kind] if absurd else _NOT_NUMBERS
        holder[index] = pool[rng.integers(len(pool))]
    else:
        kind, names = _SDK_FIELDS.get(target.replace("image_", ""), ("size", (target,)))
        pool = _ABSURD[kind] if absurd else _NOT_NUMBERS
        document[target] = pool[rng.integers(len(pool))]
        names = (*names, target.replace("image_", ""))
    return f"layout{layout}-{target}", document, names


def camera_cases(count: int, seed: int) -> Iterator[Case]:
    """``count`` seeded camera-file cases (the special ones first)."""
    specials = _special_cases("camera")
    yield from specials[:count]
    rng = np.random.default_rng(seed)
    for index in range(max(0, count - len(specials))):
        label, document, names = _camera_mutation(rng)
        suffix = ".yaml" if rng.random() < 0.3 else ".json"
        yield Case(f"camera-{index}-{label}", suffix, _dump(document, suffix), names)


# ---------------------------------------------------------------------------------- manifests
_SIMULATED = {"sequences": [{"name": "orbit", "simulated": {"orbit_frames": 30, "seed": 1}}]}
_MANIFEST_ABSURD: dict[tuple[str, ...], list[Any]] = {
    ("sequences",): [NAN, {}, "x", 5, [], None, [NAN], [[]], 10**30],
    ("sequences", 0, "name"): ["..", ".", "/etc", "a/b", "a\\b", "", "x" * 65, 5, None, "\u00e9t\u00e9",
                               "../../x", "~"],
    ("sequences", 0, "simulated", "orbit_frames"): [10**9, 0, 1, -5, NAN, INF, 2.5, "30", True,
                                                    10**30, 60000],
    ("sequences", 0, "simulated", "frames"): [0, -1, 10**9, NAN, "5", 2.5],
    ("sequences", 0, "simulated", "orbit_turns"): [0, -1, NAN, INF, 1e300, "1"],
    ("sequences", 0, "simulated", "size"): [[0, 0], [10**9, 10**9], [-1, 5], [NAN, 1], [224],
                                            "196x252", [10**30, 10**30], [1.5, 2.5]],
    ("sequences", 0, "simulated", "noise_cm"): [-1, NAN, INF, 1e300, "1"],
    ("sequences", 0, "simulated", "noise_deg"): [-1, 1e9, NAN, INF],
    ("sequences", 0, "simulated", "loss"): [[5, 1], [-1, 3], [0, 10**30], [NAN, 1], [1, 2, 3], 7],
    ("sequences", 0, "simulated", "seed"): [-1, 2**64, NAN, 1.5, "1"],
    ("threads_per_task",): [0, -1, 10**9, NAN, 1.5, "2"],
    ("configs",): [{"../x": {}}, {"": {}}, {"a/b": {}}, {"..": {}}, {"ok": {"resolution": -5}},
                   {"ok": {"resolution": NAN}}, {"ok": "x"}, NAN, {}, {"ok": {"nope": 1}}],
    ("model",): [5, {"weights": 5}, {"weights": None}, {"weights": "w", "dtype": "int3"}],
    ("unknown_field",): [1],
}


def _set(document: Any, path: tuple[Any, ...], value: Any) -> None:
    for key in path[:-1]:
        document = document[key]
    document[path[-1]] = value


def manifest_cases(count: int, seed: int) -> Iterator[Case]:
    """``count`` seeded eval-many manifest cases (the special ones first). A refusal must name
    the mutated field (or its parent)."""
    specials = _special_cases("manifest")
    yield from specials[:count]
    rng = np.random.default_rng(seed)
    paths = sorted(_MANIFEST_ABSURD, key=str)
    for index in range(max(0, count - len(specials))):
        path = paths[rng.integers(len(paths))]
        values = _MANIFEST_ABSURD[path]
        value = values[rng.integers(len(values))]
        document = deepcopy(_SIMULATED)
        _set(document, path, deepcopy(value))
        suffix = ".yaml" if rng.random() < 0.3 else ".json"
        fields = tuple(str(p) for p in path if not isinstance(p, int))
        if path == ("configs",):
            fields = ("config",)
        yield Case(f"manifest-{index}-{'.'.join(map(str, path))}", suffix, _dump(document, suffix),
                   fields)


# ------------------------------------------------------------------------------- ground truths
def ground_truth_cases() -> list[tuple[str, Callable[[Path], Path]]]:
    """(name, make(folder) -> path) of hostile TUM ground truths."""
    def text(content: str) -> Callable[[Path], Path]:
        def make(folder: Path) -> Path:
            path = folder / "gt.txt"
            path.write_text(content)
            return path
        return make

    def special(kind: str) -> Callable[[Path], Path]:
        return lambda folder: Case("gt", ".txt", None, (), kind).make(folder)

    return [
        ("two-lines-1e8-s-apart", text("0 0 0 0 0 0 0 1\n100000000 1 0 0 0 0 0 1\n")),
        ("backwards-in-time", text("10 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 1\n")),
        ("nan-stamp", text("nan 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")),
        ("zero-quaternion", text("0 0 0 0 0 0 0 0\n1 0 0 0 0 0 0 0\n")),
        ("fifo", special("fifo")),
        ("dev-zero", special("dev-zero")),
        ("folder", special("folder")),
    ]


__all__ = ["Case", "camera_cases", "ground_truth_cases", "manifest_cases"]
