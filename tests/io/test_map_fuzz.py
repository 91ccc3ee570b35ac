"""Fuzzing the map loader with damaged and foreign files (seeded, a few seconds).

Over 250 files: truncations, flipped bytes in the header and in the data, edited header fields
(with and without a re-sealed header checksum), wrong versions, bad header lengths, JSON garbage,
foreign safetensors files, a pickle, zips, empty and random files. Each must either raise one of
the typed map errors or — for the rare harmless edit, such as a space turned into a tab in the
JSON — load a map bit-identical to the original: never another exception, never silently
different data. A benign map still loads after every case.
"""

from __future__ import annotations

import io
import json
import pickle
import signal
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from kvtracker_sdk.cache import KeyframeMap
from kvtracker_sdk.errors import MapCorruptedError, MapError
from kvtracker_sdk.io.map_file.map_file import load_map, save_map
from tests.io.map_factory import (
    TRACKER_CONFIG,
    backend_info,
    join_file,
    make_map,
    maps_equal,
    rewrite_header,
    split_file,
)

Case = tuple[str, bytes]


@pytest.fixture(scope="module")
def original(tmp_path_factory: pytest.TempPathFactory) -> tuple[KeyframeMap, Path, bytes]:
    path = tmp_path_factory.mktemp("benign") / "benign.kvmap"
    keyframe_map = make_map(dtype=torch.bfloat16)
    save_map(
        path, keyframe_map, backend_info=backend_info(dtype="bfloat16"),
        tracker_config_json=TRACKER_CONFIG, mode="object",
    )  # fmt: skip
    return keyframe_map, path, path.read_bytes()


@pytest.fixture(autouse=True)
def no_hang() -> Iterator[None]:
    """Fail (instead of hanging CI) if a category takes over a minute."""
    if not hasattr(signal, "SIGALRM"):  # not on Windows: rely on the CI time limit
        yield
        return

    def fail(*_: object) -> None:
        raise TimeoutError("map loading hung on a damaged file")

    previous = signal.signal(signal.SIGALRM, fail)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def run_cases(
    cases: list[Case], original: tuple[KeyframeMap, Path, bytes], folder: Path
) -> dict[str, type]:
    """Load every case; return case name -> error class (or type(None) if it loaded)."""
    keyframe_map, benign_path, _ = original
    outcomes: dict[str, type] = {}
    for name, data in cases:
        path = folder / "case.kvmap"
        path.write_bytes(data)
        try:
            loaded = load_map(path)
        except MapError as exc:
            outcomes[name] = type(exc)
        else:
            assert maps_equal(loaded.keyframe_map, keyframe_map), f"{name}: loaded different data"
            outcomes[name] = type(None)
        assert maps_equal(load_map(benign_path).keyframe_map, keyframe_map), f"after {name}"
    return outcomes


def header_end(data: bytes) -> int:
    return 8 + int.from_bytes(data[:8], "little")


def test_truncated_files(original: tuple[KeyframeMap, Path, bytes], tmp_path: Path) -> None:
    data = original[2]
    rng = np.random.default_rng(1)
    cuts = {0, 1, 7, 8, 9, header_end(data) - 1, header_end(data), len(data) - 1}
    cuts |= {int(c) for c in rng.integers(0, len(data), 52)}
    outcomes = run_cases([(f"cut@{c}", data[:c]) for c in sorted(cuts)], original, tmp_path)
    assert len(outcomes) >= 50 and type(None) not in outcomes.values()


def test_flipped_header_bytes(original: tuple[KeyframeMap, Path, bytes], tmp_path: Path) -> None:
    data = original[2]
    rng = np.random.default_rng(2)
    cases = []
    for i in range(70):
        position = int(rng.integers(0, header_end(data)))
        damaged = bytearray(data)
        damaged[position] ^= int(rng.integers(1, 256))
        cases.append((f"header#{i}@{position}", bytes(damaged)))
    outcomes = run_cases(cases, original, tmp_path)
    assert sum(o is not type(None) for o in outcomes.values()) >= 60  # nearly all are caught


def test_flipped_data_bytes_are_always_caught(
    original: tuple[KeyframeMap, Path, bytes], tmp_path: Path
) -> None:
    data = original[2]
    rng = np.random.default_rng(3)
    cases = []
    for i in range(50):
        position = int(rng.integers(header_end(data), len(data)))
        damaged = bytearray(data)
        damaged[position] ^= 1 << int(rng.integers(0, 8))  # a single bit
        cases.append((f"data#{i}@{position}", bytes(damaged)))
    outcomes = run_cases(cases, original, tmp_path)
    assert set(outcomes.values()) == {MapCorruptedError}


def _metadata_edits() -> list[tuple[str, str, Any]]:
    """(name, metadata key, new value or None to delete)."""
    layout = {"block_indices": [1, 3, 5, 7], "num_heads": 2, "head_dim": 8, "tokens_per_frame": 11}
    edits: list[tuple[str, str, Any]] = [
        (f"version={v}", "format_version", v) for v in ("0", "5", "-1", "1.0", "", "9" * 40, "١")
    ]
    # a compact keyframe encoding on a version-1 map, a "full" written out, an unknown one
    edits += [(f"keyframe_encoding={v}", "keyframe_encoding", v)
              for v in ("compact-xyz", "full", "png")]  # fmt: skip
    edits += [(f"format={v}", "format", v) for v in ("other-map", "", None)]
    edits += [
        (f"del {k}", k, None)
        for k in ("backend", "layout", "gauge", "tensor_sha256", "resolution", "metadata_sha256")
    ]
    for key, value in (("num_heads", 3), ("head_dim", 0), ("tokens_per_frame", 12), ("block_indices", []),
                       ("block_indices", ["a"]), ("num_heads", True), ("head_dim", 8.0)):  # fmt: skip
        edits.append((f"layout.{key}={value}", "layout", json.dumps({**layout, key: value})))
    edits += [
        (f"resolution={v}", "resolution", v)
        for v in ("[28, 43]", "[0, 42]", "[28]", '"28x42"', "[14, 42]")
    ]
    edits += [(f"dtype={v}", "dtype", v) for v in ("float64", "int8", "F32")]
    edits += [
        (f"ids={v}", "keyframe_ids", v)
        for v in ("[]", "[1, 1, 4]", "[1, 4, 8]", '["a", 4, 7]', "[1, 4]", "{}")
    ]
    edits += [(f"generation={v}", "generation", v) for v in ("-1", "abc", "")]
    edits += [(f"gauge={v}", "gauge", v) for v in (
        '{"rotation": [[1,0,0],[0,1,0],[0,0,1]], "translation": [0,0,0], "scale": 0}',
        '{"rotation": [[1,0,0],[0,1,0]], "translation": [0,0,0], "scale": 1}',
        '{"rotation": [[1,0,0],[0,1,0],[0,0,1]], "translation": [0,0,NaN], "scale": 1}',
        "[]",
    )]  # fmt: skip
    edits += [(f"config={v}", "tracker_config", v) for v in ("not json", "[1]", "")]
    edits += [(f"created={v}", "created_utc", v) for v in ("yesterday", "2026-01-01T00:00:00")]
    edits += [(f"backend={v}", "backend", v) for v in ("{}", "[]", '{"family": 3}')]
    edits += [(f"user_metadata={v}", "user_metadata", v) for v in ('{"a": 1}', "[]")]
    edits += [("tensor_sha256=[]", "tensor_sha256", "[]")]
    return edits


def _table_edits(header: dict[str, Any]) -> list[tuple[str, Callable[[dict[str, Any]], None]]]:
    first_value = header["layers.0.value"]["data_offsets"]

    def swap_kv(h: dict[str, Any]) -> None:  # same sizes: only the checksums can tell
        h["layers.0.value"]["data_offsets"] = h["layers.0.key"]["data_offsets"]
        h["layers.0.key"]["data_offsets"] = first_value

    def one_checksum(h: dict[str, Any]) -> None:
        sums = json.loads(h["__metadata__"]["tensor_sha256"])
        sums["keyframes.image"] = "0" * 64
        h["__metadata__"]["tensor_sha256"] = json.dumps(sums)

    return [
        ("shape", lambda h: h["layers.1.key"].update(shape=[2, 33, 4, 2])),
        ("dtype", lambda h: h["layers.1.key"].update(dtype="F16")),
        (
            "offsets+2",
            lambda h: h["keyframes.image"].update(
                data_offsets=[o + 2 for o in h["keyframes.image"]["data_offsets"]]
            ),
        ),
        ("offsets negative", lambda h: h["keyframes.mask"].update(data_offsets=[-4, 10])),
        ("offsets float", lambda h: h["keyframes.mask"].update(data_offsets=[0.0, 1.0])),
        ("swap key/value", swap_kv),
        ("one checksum", one_checksum),
        (
            "extra tensor",
            lambda h: h.update(extra={"dtype": "U8", "shape": [0], "data_offsets": [0, 0]}),
        ),
        ("missing tensor", lambda h: h.pop("keyframes.timestamp")),
        ("extra entry field", lambda h: h["layers.0.key"].update(note="x")),
        ("no metadata", lambda h: h.pop("__metadata__")),
        ("metadata not strings", lambda h: h["__metadata__"].update(generation=2)),
    ]


def test_edited_header_fields(original: tuple[KeyframeMap, Path, bytes], tmp_path: Path) -> None:
    data = original[2]
    cases = []
    for name, key, value in _metadata_edits():

        def edit(h: dict[str, Any], key: str = key, value: Any = value) -> None:
            if value is None:
                h["__metadata__"].pop(key)
            else:
                h["__metadata__"][key] = value

        cases.append((name, rewrite_header(data, edit)))
        cases.append((name + " (unsealed)", rewrite_header(data, edit, reseal=False)))
    for name, edit in _table_edits(split_file(data)[0]):
        cases.append((name, rewrite_header(data, edit)))
    outcomes = run_cases(cases, original, tmp_path)
    assert len(outcomes) >= 100
    loaded = [name for name, outcome in outcomes.items() if outcome is type(None)]
    assert loaded == [], f"edited headers must not load: {loaded}"


def _raw_headers(data: bytes) -> list[Case]:
    header, body = split_file(data)
    text = json.dumps(header)
    n = header_end(data) - 8
    rng = np.random.default_rng(4)

    def framed(raw: bytes) -> bytes:
        return len(raw).to_bytes(8, "little") + raw + body

    return [
        ("duplicate key", framed(('{"__metadata__": {}, ' + text[1:]).encode())),
        ("random header", framed(rng.integers(0, 256, n, dtype=np.uint8).tobytes())),
        ("invalid utf-8", framed(b"\xff" * n)),
        ("json list", framed(b"[]")),
        ("json null", framed(b"null")),
        ("deep nesting", framed(b"[" * 100_000 + b"]" * 100_000)),
        ("huge integer", framed(b'{"x": ' + b"7" * 50_000 + b"}")),
        ("utf-16", framed(text.encode("utf-16"))),
        ("header length 0", (0).to_bytes(8, "little") + data[8:]),
        ("header length 1", (1).to_bytes(8, "little") + data[8:]),
        ("header length > file", (len(data)).to_bytes(8, "little") + data[8:]),
        ("header length 2**63", (2**63).to_bytes(8, "little") + data[8:]),
        ("header length max", (2**64 - 1).to_bytes(8, "little") + data[8:]),
        ("header length -1 byte", (n - 1).to_bytes(8, "little") + data[8:]),
        ("header length +1 byte", (n + 1).to_bytes(8, "little") + data[8:]),
        ("trailing bytes", data + b"\0" * 16),
        ("no body", join_file(header, b"")),
    ]


class _Trap:
    """Unpickling this would create ``marker``: the loader must never unpickle."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (self.marker,))


def _foreign_files(tmp_path: Path, marker: Path) -> list[Case]:
    st = tmp_path / "foreign.safetensors"
    save_file({"weight": torch.ones(4, 4)}, st)
    plain = st.read_bytes()
    save_file({"weight": torch.ones(4, 4)}, st, metadata={"format": "pt"})
    with_metadata = st.read_bytes()
    torch_zip = io.BytesIO()
    torch.save({"layers.0.key": torch.ones(2)}, torch_zip)
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("data.pkl", pickle.dumps(_Trap(marker)))
    rng = np.random.default_rng(5)
    return [
        ("safetensors without metadata", plain),
        ("safetensors of another format", with_metadata),
        ("pickle", pickle.dumps(_Trap(marker))),
        ("pickle protocol 0", pickle.dumps(_Trap(marker), protocol=0)),
        ("torch.save zip", torch_zip.getvalue()),
        ("zip holding a pickle", archive.getvalue()),
        ("empty", b""),
        ("seven bytes", b"\x10\0\0\0\0\0\0"),
        ("text", b"hello, this is not a map\n"),
        ("zeros", bytes(4096)),
        ("random", rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()),
    ]


def test_garbage_headers_and_foreign_files(
    original: tuple[KeyframeMap, Path, bytes], tmp_path: Path
) -> None:
    marker = tmp_path / "unpickled.marker"
    cases = _raw_headers(original[2]) + _foreign_files(tmp_path, marker)
    outcomes = run_cases(cases, original, tmp_path)
    assert type(None) not in outcomes.values(), outcomes
    assert not marker.exists()  # nothing was unpickled
