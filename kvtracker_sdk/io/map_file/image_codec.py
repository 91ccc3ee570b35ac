"""Keyframe images of compact maps stored losslessly compressed (PNG), and their bounded decoding.

A compact map (format version 4) stores its keyframe images, [N, H, W, 3] uint8 RGB, as N PNG
files laid end to end in one uint8 tensor, ``keyframes.image_png`` [total bytes]; the header
lists each one's length (``keyframe_image_bytes``), so the tensor table is checked before any
byte is read, and the tensor's sha256 covers the stored (compressed) bytes. The images reload
bit for bit. Images that do not compress (the PNGs together no smaller than the raw pixels, or
one of them above :func:`max_png_bytes`) are stored raw, as in older versions.

Why PNG (OpenCV's encoder: zlib level 1, run-length strategy, adaptive row filters): lossless,
fast to encode and decode, and decoded by libpng, the most exercised image decoder there is.
WebP's lossless mode packs natural images somewhat tighter but encodes many times slower, and
its decoder has had heap overflows on crafted files (``benchmarks/map_images.py`` measures
both).

Decoding reads untrusted bytes, so before OpenCV sees a file it is checked against what this
writer produces: the PNG signature, then exactly the chunks IHDR (the header's H x W, 8-bit RGB,
not interlaced), IDAT..., IEND, each with a valid CRC; the IDAT stream must inflate (``zlib``,
capped at the expected size) to exactly H rows of one filter byte (0-4) and 3W bytes. A file
that passes decodes without error in libpng, whose own error path prints to the process's
stderr (the SDK prints nothing); a file that does not is a :class:`MapCorruptedError`, and so is
any decoder failure that remains, or a decoded image of another shape.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from kvtracker_sdk.errors import MapCorruptedError

__all__ = ["PNG", "RAW", "decode_images", "encode_images", "max_png_bytes"]

RAW = "raw"  # uint8 [N, H, W, 3] pixels (every version; dense maps)
PNG = "png"  # N PNG files end to end (version 4, compact maps)

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IHDR_RGB8 = (8, 2, 0, 0, 0)  # bit depth, colour type RGB, deflate, adaptive filters, no interlace
_MAX_FILTER = 4  # PNG row filters: none, sub, up, average, Paeth
_SMALLEST_PNG = len(_SIGNATURE) + 25 + 12 + 12  # IHDR, one empty IDAT, IEND chunks
# cv2 and zlib release the GIL: images encode and decode in parallel
_WORKERS = 4


def max_png_bytes(height: int, width: int) -> int:
    """The largest PNG a map may declare for an H x W image: the raw rows (a filter byte each)
    plus deflate's worst case for stored data and the chunks around it. The writer stores raw
    pixels rather than a larger PNG, so a larger length is a tampered header."""
    rows = height * (1 + 3 * width)
    zlib_frame = 6  # its header and Adler-32
    return _SMALLEST_PNG + zlib_frame + rows + 5 * (rows // 16383 + 1) + 12 * (rows // 8192 + 1)


def _cv2() -> Any:
    import cv2  # the images' codec; imported when a compact map is written or read

    return cv2


def _encode_one(image: np.ndarray) -> bytes:
    cv2 = _cv2()
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
              cv2.IMWRITE_PNG_STRATEGY_RLE]  # fmt: skip
    # OpenCV writes its BGR channel order as the file's RGB: give it BGR so the file is true RGB
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]), params)
    if not ok:  # pragma: no cover - OpenCV encodes every uint8 HxWx3 array
        raise ValueError("OpenCV could not encode a keyframe image as PNG")
    return bytes(encoded)


def encode_images(images: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]] | None:
    """PNG files of uint8 [N, H, W, 3] RGB ``images``, end to end (uint8 [total]), and each
    file's length; None when storing them raw is no larger (or one exceeds ``max_png_bytes``)."""
    n, height, width = images.shape[:3]
    with ThreadPoolExecutor(max_workers=min(_WORKERS, max(1, n))) as pool:
        files = list(pool.map(_encode_one, images))
    lengths = tuple(len(f) for f in files)
    if sum(lengths) >= images.nbytes or max(lengths) > max_png_bytes(height, width):
        return None
    return np.frombuffer(bytearray(b"".join(files)), dtype=np.uint8), lengths


def _chunks(data: bytes, fail: Any) -> list[tuple[bytes, bytes]]:
    """(type, payload) of every chunk after the signature; each length and CRC checked."""
    chunks, position = [], len(_SIGNATURE)
    while position < len(data):
        if position + 12 > len(data):
            raise fail("a chunk is cut off")
        (length,) = struct.unpack_from(">I", data, position)
        end = position + 8 + length
        if end + 4 > len(data):
            raise fail("a chunk is longer than the file")
        kind, payload = data[position + 4 : position + 8], data[position + 8 : end]
        if zlib.crc32(kind + payload) != struct.unpack_from(">I", data, end)[0]:
            raise fail(f"chunk {kind!r} fails its CRC")
        chunks.append((kind, payload))
        position = end + 4
    return chunks


def _check_png(data: bytes, height: int, width: int, fail: Any) -> None:
    """Raise ``fail(reason)`` unless ``data`` is a PNG this writer could have made of an
    H x W RGB image (see the module docstring); never inflates beyond the expected size."""
    if len(data) < _SMALLEST_PNG or not data.startswith(_SIGNATURE):
        raise fail("not a PNG file")
    chunks = _chunks(data, fail)
    kinds = [kind for kind, _ in chunks]
    if (len(chunks) < 3 or kinds[0] != b"IHDR" or kinds[-1] != b"IEND" or chunks[-1][1]
            or any(kind != b"IDAT" for kind in kinds[1:-1])):  # fmt: skip
        raise fail("its chunks are not IHDR, IDAT..., IEND")
    header = chunks[0][1]
    if len(header) != 13 or struct.unpack(">IIBBBBB", header) != (width, height, *_IHDR_RGB8):
        raise fail(f"its IHDR is not an 8-bit RGB {width}x{height} image without interlacing")
    expected = height * (1 + 3 * width)
    inflater = zlib.decompressobj()
    try:
        rows = inflater.decompress(b"".join(payload for _, payload in chunks[1:-1]), expected + 1)
    except zlib.error as exc:
        raise fail(f"its pixel data do not inflate ({exc})") from exc
    if len(rows) != expected or not inflater.eof or inflater.unused_data:
        raise fail("its pixel data inflate to another size than the image's")
    filters = np.frombuffer(rows, dtype=np.uint8)[:: 1 + 3 * width]
    if int(filters.max()) > _MAX_FILTER:
        raise fail("a row has an unknown PNG filter")


def _decode_one(data: bytes, height: int, width: int, fail: Any) -> np.ndarray:
    _check_png(data, height, width, fail)
    cv2 = _cv2()
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # pragma: no cover - the checks above leave libpng nothing to refuse
        raise fail(f"OpenCV cannot decode it ({exc})") from exc
    if image is None or image.shape != (height, width, 3) or image.dtype != np.uint8:
        raise fail("it decodes to another image than the header's")
    return image[..., ::-1]  # the file is RGB; OpenCV hands back BGR


def decode_images(
    stored: np.ndarray, lengths: Sequence[int], resolution: tuple[int, int], source: str
) -> np.ndarray:
    """uint8 [N, H, W, 3] RGB images of the PNG files end to end in uint8 ``stored``, one per
    entry of ``lengths`` (the header's, checked against ``max_png_bytes``; they sum to
    ``stored``'s size). MapCorruptedError naming the keyframe for any file that is not a PNG of
    that image (module docstring)."""
    height, width = resolution
    starts = np.concatenate(([0], np.cumsum(lengths)))
    data = stored.tobytes()

    def decode(k: int) -> np.ndarray:
        def fail(reason: str) -> MapCorruptedError:
            return MapCorruptedError(f"{source}: keyframe image {k} (keyframes.image_png): {reason}")

        return _decode_one(data[starts[k] : starts[k + 1]], height, width, fail)

    images = np.empty((len(lengths), height, width, 3), dtype=np.uint8)
    with ThreadPoolExecutor(max_workers=min(_WORKERS, max(1, len(lengths)))) as pool:
        for k, image in enumerate(pool.map(decode, range(len(lengths)))):
            images[k] = image
    return images
