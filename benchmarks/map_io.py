"""Map files at disk speed? ``save_map`` against writing the same bytes with ``fsync``, and a
verified cold ``load_map`` against a raw cold read of the file, in the same rounds.

The map: Pi3 ``large()``'s cache layout (18 cached layers x 16 heads x head_dim 64) at 224x224
(T = 5 + 16*16 = 261 tokens per frame), bfloat16, ``--keyframes`` keyframes (default 20: about
0.4 GB of K/V plus the keyframes' images, confidences and points). Random content (the speed
does not depend on it).

After one unmeasured round (the first write of a new file costs more), each round, in
rotating order:

- ``save_map``: the whole save (snapshot of the cache, sha256 of every tensor, write, fsync,
  rename, directory fsync) over the previous file;
- ``save_map from a snapshot copy``: the same with the K/V first copied out of the cache into
  new memory (the path before the save wrote from the cache's buffers), for comparison;
- ``write + fsync``: the saved file's bytes (held in memory) written to a new file in the same
  folder with ``os.write`` in 8 MB chunks, then ``fsync`` (what ``dd conv=fsync`` does);
- ``load_map`` cold, verified (the default): the file's pages dropped first
  (``posix_fadvise(DONTNEED)`` after an ``fsync``), then the whole load, sha256 checked;
- ``raw read`` cold: the pages dropped, then the file read once, sequentially, into a
  preallocated buffer reused every round (``readinto``; nothing parsed or hashed: its pages are
  already mapped, which no loader's new memory is);
- ``raw read`` cold into new memory: the same into a buffer allocated for the read
  (``bytearray`` of the file's size, as any reader of the whole file needs).

The ratios are per round (save / write, load / read), reported as their median, with every
sample, the process CPU time of each step (all its threads) and the load averages in the JSON.
On a machine busy with other work, a step's wall time grows with the CPU it needs (hashing:
CPU work, the bulk of a save's and a verified load's) while the references mostly wait on the disk, so the
ratios are worth reading with the load average and the CPU column. Run from the repository root::

    python -m benchmarks.map_io --rounds 5 --name map_io

Writes ``benchmarks/results/<--name>.json`` (with the process's niceness: a run under
``nice -n -19`` measures the machine as if the other work on it were paused) and prints a
markdown table.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.cache import CacheLayout, Keyframe, KeyframeMap, KVCache
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file import map_file
from kvtracker_sdk.io.map_file.map_file import load_map, save_map

RESULTS = Path(__file__).parent / "results"
SIZE, PATCH, EXTRA = 224, 14, 5
LAYOUT = CacheLayout(block_indices=tuple(range(1, 36, 2)), num_heads=16, head_dim=64)
TOKENS = EXTRA + (SIZE // PATCH) ** 2
CHUNK = 8 << 20


def build_map(keyframes: int, seed: int = 0) -> tuple[KeyframeMap, BackendInfo]:
    """A random map of ``keyframes`` keyframes with the benchmark's layout."""
    generator = torch.Generator().manual_seed(seed)
    shape = (1, LAYOUT.num_heads, keyframes * TOKENS, LAYOUT.head_dim)
    layers = [torch.randn(shape, generator=generator).to(torch.bfloat16)
              for _ in range(2 * LAYOUT.num_layers)]  # fmt: skip
    cache = KVCache.from_layers(layers[0::2], layers[1::2], layout=LAYOUT, tokens_per_frame=TOKENS,
                                keyframe_ids=list(range(keyframes)))  # fmt: skip
    rng = np.random.default_rng(seed)
    frames = tuple(
        Keyframe(
            keyframe_id=i, frame_index=10 * i, timestamp=float(i),
            image=rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8), mask=None,
            T_world_cam=np.eye(4), confidence_map=rng.random((SIZE, SIZE), dtype=np.float32),
            local_points=rng.random((SIZE, SIZE, 3), dtype=np.float32), mean_confidence=0.5,
        )
        for i in range(keyframes)
    )  # fmt: skip
    info = BackendInfo(
        backend="torch", model="pi3", family="pi3", config_hash="bench", weights_fingerprint="bench",
        patch_size=PATCH, extra_tokens_per_frame=EXTRA, layout=LAYOUT, dtype="bfloat16",
    )  # fmt: skip
    return KeyframeMap(frames, cache, Sim3.identity(), resolution=(SIZE, SIZE)), info


def drop_page_cache(path: Path) -> None:
    """Evict this file's pages (only this file) so that the next read comes from the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def write_fsync(path: Path, data: memoryview) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        for start in range(0, len(data), CHUNK):
            view = data[start : start + CHUNK]
            while view:
                view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)


def raw_read(path: Path, buffer: bytearray) -> int:
    with open(path, "rb", buffering=0) as handle:
        return handle.readinto(buffer)  # type: ignore[no-any-return]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--name", default="map_io")
    parser.add_argument("--dir", type=Path, default=None, help="folder on the disk to measure")
    args = parser.parse_args(argv)

    keyframe_map, backend = build_map(args.keyframes)
    with tempfile.TemporaryDirectory(dir=args.dir) as folder:
        target, copy = Path(folder) / "bench.kvmap", Path(folder) / "copy.bin"

        def save() -> None:
            save_map(target, keyframe_map, backend_info=backend, tracker_config_json="{}",
                     mode="scene")  # fmt: skip

        def save_from_snapshot() -> None:
            """The previous path, for comparison: the K/V copied out of the cache first."""
            views = map_file.map_to_tensors
            map_file.map_to_tensors = functools.partial(views, cache_views=False)  # type: ignore[assignment]
            try:
                save()
            finally:
                map_file.map_to_tensors = views

        save()
        data = memoryview(target.read_bytes())
        buffer = bytearray(len(data))

        def load() -> None:
            drop_page_cache(target)
            load_map(target)

        def read() -> None:
            drop_page_cache(target)
            raw_read(target, buffer)

        def read_new() -> None:
            drop_page_cache(target)
            raw_read(target, bytearray(len(data)))

        steps: dict[str, Callable[[], object]] = {
            "save_map": save, "save_map from a snapshot copy": save_from_snapshot,
            "write + fsync": lambda: write_fsync(copy, data),
            "load_map cold verified": load, "raw read cold": read,
            "raw read cold, new memory": read_new,
        }  # fmt: skip
        samples: dict[str, list[float]] = {name: [] for name in steps}
        cpu: dict[str, list[float]] = {name: [] for name in steps}
        for step in steps.values():  # one unmeasured round: first writes of new files, etc.
            step()
        loads = [os.getloadavg()]
        for round_index in range(args.rounds):
            names = list(steps)
            shift = round_index % len(names)
            for name in names[shift:] + names[:shift]:
                start, start_cpu = time.perf_counter(), time.process_time()
                steps[name]()
                samples[name].append(time.perf_counter() - start)
                cpu[name].append(time.process_time() - start_cpu)
            loads.append(os.getloadavg())
        size = len(data)
    save_ratios = [s / w for s, w in zip(samples["save_map"], samples["write + fsync"], strict=True)]
    snapshot_ratios = [s / w for s, w in zip(samples["save_map from a snapshot copy"],
                                             samples["write + fsync"], strict=True)]  # fmt: skip
    load_ratios = [lo / r for lo, r in zip(samples["load_map cold verified"],
                                           samples["raw read cold"], strict=True)]  # fmt: skip
    load_new_ratios = [lo / r for lo, r in zip(samples["load_map cold verified"],
                                               samples["raw read cold, new memory"], strict=True)]  # fmt: skip
    result = {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": "python -m benchmarks.map_io " + " ".join(argv or []),
        "machine": {"cpu": _cpu(), "cpus": os.cpu_count(), "platform": platform.platform(),
                    "torch": torch.__version__},
        "file_bytes": size, "keyframes": args.keyframes, "rounds": args.rounds,
        "code": _code(), "niceness": os.nice(0),
        "samples_s": samples, "cpu_s": cpu, "load_averages": loads,
        "median_s": {name: statistics.median(s) for name, s in samples.items()},
        "median_cpu_s": {name: statistics.median(s) for name, s in cpu.items()},
        "save_over_write_fsync": {"median": statistics.median(save_ratios), "rounds": save_ratios},
        "snapshot_save_over_write_fsync": {"median": statistics.median(snapshot_ratios),
                                           "rounds": snapshot_ratios},
        "load_over_raw_read": {"median": statistics.median(load_ratios), "rounds": load_ratios},
        "load_over_raw_read_new_memory": {"median": statistics.median(load_new_ratios),
                                          "rounds": load_new_ratios},
    }  # fmt: skip
    lines = [f"map file {size / 1e6:.0f} MB ({args.keyframes} keyframes, Pi3 large layout, "
             f"224, bf16); {args.rounds} rounds; load average {loads[0][0]:.1f}→{loads[-1][0]:.1f}",
             "", "| step | median (s) | GB/s | CPU (s, all threads) | ratio (median of rounds) |",
             "|---|---:|---:|---:|---:|"]  # fmt: skip
    ratio = {"save_map": result["save_over_write_fsync"]["median"],
             "save_map from a snapshot copy": result["snapshot_save_over_write_fsync"]["median"],
             "load_map cold verified": result["load_over_raw_read"]["median"]}  # fmt: skip
    for name, seconds in result["median_s"].items():
        text = f"{ratio[name]:.2f}×" if name in ratio else "reference"
        if name == "load_map cold verified":
            text += f" ({result['load_over_raw_read_new_memory']['median']:.2f}× new memory)"
        cpu_seconds = result["median_cpu_s"][name]
        lines.append(f"| {name} | {seconds:.3f} | {size / 1e9 / seconds:.2f} | {cpu_seconds:.2f} "
                     f"| {text} |")  # fmt: skip
    table = "\n".join(lines)
    result["table"] = table
    print(table)
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{args.name}.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path}")
    return result


def _code() -> dict[str, str]:
    """Which ``kvtracker_sdk`` was measured: its folder and that checkout's commit."""
    import kvtracker_sdk

    folder = Path(kvtracker_sdk.__file__).parent
    try:
        commit = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"],
                                capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown (not a git checkout)"
    return {"package": folder.name, "commit": commit}  # no machine paths in committed results


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    main()
