"""Compact maps' keyframe images as PNG: the int8 map's size against bf16's, and the codecs.

The golden Pi3 model (reduced, random weights, bf16 backend, 1 thread) tracks the 20 shared TUM
fr2_desk frames at resolution 224 with a keyframe every 5 frames, once with a bf16 cache and once
with ``cache_dtype="int8"``; both maps are saved. Reported: each file's bytes, the bf16 / int8
ratio, what the int8 file would be with raw images (format version 3's layout: the PNG bytes
swapped for the raw pixels), and that the reloaded int8 map's images equal the tracker's bit for
bit. Then the int8 map's keyframe images go through each candidate lossless codec (OpenCV):
bytes against raw, and encode / decode time per image (median of ``--repeats``, one thread,
process CPU time), and whether they decode bit for bit.

Run from the repository root::

    python -m benchmarks.map_images [--repeats 20] [--name map_images] [--out-dir benchmarks/results]

Writes ``benchmarks/results/<name>.json`` and prints the tables with the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info
from kvtracker_sdk.io.sources.sources import TumSource
from kvtracker_sdk.tracking.facade.tracker import Tracker

RESULTS = Path(__file__).parent / "results"
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
RESOLUTION, KEYFRAME_INTERVAL = 224, 5

# name -> (extension, OpenCV parameters); "png (SDK)" is what image_codec.py writes
CODECS: dict[str, tuple[str, list[int]]] = {
    "png (SDK): level 1, RLE": (
        ".png", [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    ),
    "png: level 1, default strategy": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "png: level 9, filtered": (
        ".png",
        [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_FILTERED],
    ),
    "webp: lossless": (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),
}


def _maps(folder: Path) -> dict[str, Any]:
    """Track the shared frames with a bf16 and an int8 cache; save, reload, measure the files."""
    frames = [frame.image for frame in TumSource(SHARED / "data" / "tum_fr2_desk")]
    backend = TorchBackend.from_pretrained(
        SHARED / "golden" / "pi3" / "weights.safetensors", dtype="bfloat16"
    )
    rows: dict[str, Any] = {}
    for name, cache_dtype in (("bf16", "backend"), ("int8", "int8")):
        config = {"resolution": RESOLUTION, "cache_dtype": cache_dtype,
                  "keyframing": {"interval_frames": KEYFRAME_INTERVAL}}  # fmt: skip
        path = folder / f"{name}.kvmap"
        with Tracker(config, backend) as tracker:
            for image in frames:
                tracker.push_frame(image)
            images = [kf.image.copy() for kf in tracker.keyframe_map.keyframes]
            tracker.save_map(path)
        info = read_map_info(path)
        reloaded = load_map(path).keyframe_map
        rows[name] = {
            "file_bytes": info.file_size, "format_version": info.format_version,
            "keyframes": info.num_keyframes, "resolution": list(info.resolution),
            "keyframe_encoding": info.keyframe_encoding, "image_codec": info.image_codec,
            "image_bytes": list(info.image_bytes or ()),
            "raw_image_bytes": int(sum(image.nbytes for image in images)),
            "images_reload_bit_for_bit": all(
                np.array_equal(kf.image, image) for kf, image in zip(reloaded.keyframes, images, strict=True)
            ),
        }  # fmt: skip
        rows[name]["images"] = images
    int8 = rows["int8"]
    stored_images = sum(int8["image_bytes"]) or int8["raw_image_bytes"]
    int8["file_bytes_with_raw_images"] = int8["file_bytes"] - stored_images + int8["raw_image_bytes"]
    rows["ratio_bf16_to_int8"] = rows["bf16"]["file_bytes"] / int8["file_bytes"]
    rows["ratio_with_raw_images"] = rows["bf16"]["file_bytes"] / int8["file_bytes_with_raw_images"]
    return rows


def _cpu_ms(work: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.process_time()
        work()
        times.append(time.process_time() - start)
    return 1000.0 * statistics.median(times)


def _codecs(images: list[np.ndarray], repeats: int) -> list[dict[str, Any]]:
    raw = sum(image.nbytes for image in images)
    bgr = [np.ascontiguousarray(image[..., ::-1]) for image in images]
    rows = []
    for name, (extension, params) in CODECS.items():
        encoded = [cv2.imencode(extension, image, params)[1] for image in bgr]
        decoded = [cv2.imdecode(data, cv2.IMREAD_UNCHANGED) for data in encoded]
        size = sum(int(data.nbytes) for data in encoded)
        rows.append({
            "codec": name, "bytes": size, "fraction_of_raw": size / raw,
            "encode_ms_per_image": _cpu_ms(
                lambda p=params, e=extension: [cv2.imencode(e, i, p) for i in bgr], repeats
            ) / len(images),
            "decode_ms_per_image": _cpu_ms(
                lambda enc=encoded: [cv2.imdecode(d, cv2.IMREAD_UNCHANGED) for d in enc], repeats
            ) / len(images),
            "lossless": all(np.array_equal(d, i) for d, i in zip(decoded, bgr, strict=True)),
        })  # fmt: skip
    return rows


def _print(result: dict[str, Any]) -> None:
    maps = result["maps"]
    print(f"load average {result['load_average']}")
    print("| map | file bytes | keyframes | images stored | images reload bit for bit |")
    print("|---|---|---|---|---|")
    for name in ("bf16", "int8"):
        row = maps[name]
        stored = sum(row["image_bytes"]) or row["raw_image_bytes"]
        print(f"| {name} | {row['file_bytes']:,} | {row['keyframes']} | {row['image_codec']} "
              f"{stored:,} B | {row['images_reload_bit_for_bit']} |")  # fmt: skip
    print(f"bf16 / int8 = {maps['ratio_bf16_to_int8']:.3f} "
          f"(with raw images: {maps['ratio_with_raw_images']:.3f})")  # fmt: skip
    print("| codec | bytes / raw | encode ms / image | decode ms / image | lossless |")
    print("|---|---|---|---|---|")
    for row in result["codecs"]:
        print(f"| {row['codec']} | {row['fraction_of_raw']:.3f} | {row['encode_ms_per_image']:.1f} "
              f"| {row['decode_ms_per_image']:.1f} | {row['lossless']} |")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--name", default="map_images")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as folder:
        maps = _maps(Path(folder))
    images = maps["int8"].pop("images")
    maps["bf16"].pop("images")
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": "python -m benchmarks.map_images --repeats " + str(args.repeats),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "processor": platform.processor(), "torch": torch.__version__,
                    "opencv": cv2.__version__},  # fmt: skip
        "model": "golden Pi3 (reduced, random weights), bf16 backend",
        "frames": "shared TUM fr2_desk, 20 frames",
        "resolution": RESOLUTION, "keyframe_interval_frames": KEYFRAME_INTERVAL,
        "maps": maps,
        "codecs": _codecs(images, args.repeats),
    }  # fmt: skip
    result["load_average"] = [round(x, 2) for x in (*load_before, *os.getloadavg())]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
    _print(result)


if __name__ == "__main__":
    main()
