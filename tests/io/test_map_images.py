"""Compact maps' keyframe images as PNG files: a bit-exact round trip, and hostile files.

A hostile file re-seals every checksum (the tensor's sha256 and the header's), so only the
image checks stand between it and OpenCV's decoder: each must raise a typed map error, allocate
nothing beyond the image's own size, and print nothing (libpng writes its errors to stderr).
"""

from __future__ import annotations

import hashlib
import json
import struct
import zlib
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.cache import KeyframeMap
from kvtracker_sdk.errors import MapCorruptedError, MapError, MapFormatError
from kvtracker_sdk.io.map_file.image_codec import encode_images, max_png_bytes
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from tests.io.map_factory import (
    TRACKER_CONFIG,
    backend_info,
    compact_maps_match,
    join_file,
    make_map,
    rewrite_header,
    split_file,
)

IMAGE_PNG = "keyframes.image_png"
SIZE = (28, 42)


def smooth_map() -> KeyframeMap:
    """An int8 map whose images compress (gradients and a little seeded noise): PNG-stored."""
    rng = np.random.default_rng(7)
    base = make_map(storage="int8")
    h, w = SIZE
    ramp = (np.arange(h)[:, None, None] * 3 + np.arange(w)[None, :, None] * 2 + [0, 40, 80])
    keyframes = tuple(
        replace(kf, image=(ramp + 5 * i + rng.integers(0, 3, (h, w, 3))).astype(np.uint8))
        for i, kf in enumerate(base.keyframes)
    )
    return replace(base, keyframes=keyframes)


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> tuple[KeyframeMap, bytes]:
    path = tmp_path_factory.mktemp("png") / "m.kvmap"
    keyframe_map = smooth_map()
    save_map(path, keyframe_map, backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG,
             mode="object")  # fmt: skip
    return keyframe_map, path.read_bytes()


def test_png_images_reload_bit_for_bit_and_are_smaller(
    saved: tuple[KeyframeMap, bytes], tmp_path: Path
) -> None:
    keyframe_map, data = saved
    path = tmp_path / "m.kvmap"
    path.write_bytes(data)
    info = read_map_info(path)
    assert info.image_codec == "png" and info.image_bytes is not None
    assert sum(info.image_bytes) < keyframe_map.num_keyframes * SIZE[0] * SIZE[1] * 3
    loaded = load_map(path).keyframe_map
    for mine, theirs in zip(loaded.keyframes, keyframe_map.keyframes, strict=True):
        assert mine.image.dtype == np.uint8 and np.array_equal(mine.image, theirs.image)
    assert compact_maps_match(loaded, keyframe_map)
    # a PNG another tool opens shows the true colours: the file is RGB, not OpenCV's BGR
    first = split_file(data)
    begin = first[0][IMAGE_PNG]["data_offsets"][0]
    png = first[1][begin : begin + info.image_bytes[0]]
    decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(decoded, keyframe_map.keyframes[0].image)


def test_images_that_do_not_compress_stay_raw() -> None:
    noise = np.random.default_rng(8).integers(0, 256, (2, *SIZE, 3), dtype=np.uint8)
    assert encode_images(noise) is None  # make_map's random images: stored raw, as before


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _png(width: int, height: int, rows: bytes, *, ihdr_tail: bytes = b"\x08\x02\x00\x00\x00",
         extra: bytes = b"") -> bytes:  # fmt: skip
    ihdr = _chunk(b"IHDR", struct.pack(">II", width, height) + ihdr_tail)
    return (b"\x89PNG\r\n\x1a\n" + ihdr + extra + _chunk(b"IDAT", zlib.compress(rows, 9))
            + _chunk(b"IEND", b""))  # fmt: skip


def _with_first_image(data: bytes, png: bytes, *, reseal: bool = True) -> bytes:
    """The file with keyframe 0's PNG replaced by ``png`` (later tensors moved, their offsets,
    the image tensor's shape and checksum and the header's lengths updated)."""
    header, body = split_file(data)
    meta = header["__metadata__"]
    lengths = json.loads(meta["keyframe_image_bytes"])
    begin, end = header[IMAGE_PNG]["data_offsets"]
    stored = png + body[begin + lengths[0] : end]
    lengths[0] = len(png)
    shift = len(stored) - (end - begin)
    for name, entry in header.items():
        if name != "__metadata__" and entry["data_offsets"][0] > begin:
            entry["data_offsets"] = [o + shift for o in entry["data_offsets"]]
    header[IMAGE_PNG].update(shape=[len(stored)], data_offsets=[begin, begin + len(stored)])
    sums = json.loads(meta["tensor_sha256"])
    sums[IMAGE_PNG] = hashlib.sha256(stored).hexdigest() if reseal else sums[IMAGE_PNG]
    meta.update(tensor_sha256=json.dumps(sums), keyframe_image_bytes=json.dumps(lengths))
    rebuilt = join_file(header, body[:begin] + stored + body[end:])
    return rewrite_header(rebuilt, lambda h: None, reseal=reseal)


def _hostile_pngs(keyframe_map: KeyframeMap) -> dict[str, bytes]:
    h, w = SIZE
    rows = b"".join(b"\x00" + bytes(3 * w) for _ in range(h))
    real = cv2.imencode(".png", np.ascontiguousarray(keyframe_map.keyframes[0].image[..., ::-1]))[1]
    real = bytes(real)
    jpeg = bytes(cv2.imencode(".jpg", keyframe_map.keyframes[0].image)[1])
    return {
        "dimensions of a bomb": _png(65535, 65535, rows),
        "another size": _png(w, h + 1, rows + b"\x00" + bytes(3 * w)),
        "16-bit": _png(w, h, rows, ihdr_tail=b"\x10\x02\x00\x00\x00"),
        "grey": _png(w, h, rows, ihdr_tail=b"\x08\x00\x00\x00\x00"),
        "interlaced": _png(w, h, rows, ihdr_tail=b"\x08\x02\x00\x00\x01"),
        "inflates far beyond its rows": _png(w, h, bytes(3_000_000)),
        "inflates short": _png(w, h, rows[:-7]),
        "unknown row filter": _png(w, h, b"".join(b"\x07" + bytes(3 * w) for _ in range(h))),
        "an extra chunk": _png(w, h, rows, extra=_chunk(b"tEXt", b"Comment\x00hi")),
        "garbage idat": (b"\x89PNG\r\n\x1a\n" + real[8:33] + _chunk(b"IDAT", bytes(range(256)) * 4)
                         + _chunk(b"IEND", b"")),  # fmt: skip
        "cut in half": real[: len(real) // 2],
        "a chunk CRC off": real[:-5] + bytes([real[-5] ^ 1]) + real[-4:],
        "jpeg": jpeg,
        "random bytes": np.random.default_rng(9).integers(0, 256, 900, dtype=np.uint8).tobytes(),
        "empty": b"",
    }


def _outcome(data: bytes, folder: Path) -> type:
    path = folder / "case.kvmap"
    path.write_bytes(data)
    try:
        load_map(path)
    except MapError as exc:
        return type(exc)
    return type(None)


def test_hostile_pngs_raise_typed_errors_and_print_nothing(
    saved: tuple[KeyframeMap, bytes], tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    keyframe_map, data = saved
    outcomes = {}
    for name, png in _hostile_pngs(keyframe_map).items():
        sealed = _outcome(_with_first_image(data, png), tmp_path)
        unsealed = _outcome(_with_first_image(data, png, reseal=False), tmp_path)
        outcomes[name] = (sealed, unsealed)
    too_long = _with_first_image(data, bytes(max_png_bytes(*SIZE) + 1))
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == "", "the decoder printed"
    for name, (sealed, unsealed) in outcomes.items():
        # "empty" and "random bytes" too short for a PNG; every other one reaches the checks
        assert sealed in (MapCorruptedError, MapFormatError), (name, sealed)
        assert unsealed is MapCorruptedError, (name, unsealed)  # the sha256 covers stored bytes
    assert _outcome(too_long, tmp_path) is MapFormatError  # refused from the header alone
    assert _outcome(data, tmp_path) is type(None)  # the benign map still loads


def test_header_fields_of_png_images_are_checked(
    saved: tuple[KeyframeMap, bytes], tmp_path: Path
) -> None:
    _, data = saved
    edits: dict[str, tuple[Callable[[dict], None], str]] = {
        "codec webp": (lambda h: h["__metadata__"].update(keyframe_image_codec="webp"),
                       "unsupported 'keyframe_image_codec'"),
        "no lengths": (lambda h: h["__metadata__"].pop("keyframe_image_bytes"),
                       "need the header field 'keyframe_image_bytes'"),
        "one length short": (lambda h: h["__metadata__"].update(keyframe_image_bytes="[10, 10]"),
                             "must list 3 lengths"),
        "zero length": (lambda h: h["__metadata__"].update(keyframe_image_bytes="[0, 10, 10]"),
                        "must be an integer >= 1"),
        "version 3": (lambda h: h["__metadata__"].update(format_version="3"),
                      "need format version >= 4"),
        "lengths without codec": (lambda h: h["__metadata__"].pop("keyframe_image_codec"),
                                  "without 'keyframe_image_codec'"),
    }  # fmt: skip
    for name, (edit, match) in edits.items():
        path = tmp_path / "edited.kvmap"
        path.write_bytes(rewrite_header(data, edit))
        with pytest.raises(MapFormatError, match=match):
            read_map_info(path)
        assert name
