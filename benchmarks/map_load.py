"""Map file load rate: 20 keyframes at 308x308 with Pi3 ``large()``'s cache layout, bfloat16.

18 cached layers x 16 heads x head_dim 64, T = 5 + 22*22 = 489 tokens per frame: about 0.72 GB of
K/V plus ~36 MB of keyframe images, confidences and points. The map is written to a temporary
folder, then loaded repeatedly (warm page cache) with and without checksum verification, and once
from a cold page cache (the file's pages dropped with ``posix_fadvise``). A breakdown separates the
header, the ``pread`` of every tensor straight into its buffer (the K/V into the cache's), and
the same with sha256 hashing, next to three references: the previous loader (safetensors memory
map, sha256, copy into the cache; measured in the same run), reading the file with ``readinto``,
and a plain in-memory copy of the cache's size.

Run: ``python benchmarks/map_load.py [--repeats 3] [--out benchmarks/results/map_load.json]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import safetensors
import torch
from safetensors import safe_open

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.cache import CacheLayout, Keyframe, KeyframeMap, KVCache
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.io.map_file.map_format import MapInfo, parse_header
from kvtracker_sdk.io.map_file.map_reader import open_map_file, read_map_tensors
from kvtracker_sdk.io.map_file.map_tensors import map_from_tensors, verify_checksums

KEYFRAMES, SIZE, PATCH, EXTRA = 20, 308, 14, 5
LAYOUT = CacheLayout(block_indices=tuple(range(1, 36, 2)), num_heads=16, head_dim=64)
TOKENS = EXTRA + (SIZE // PATCH) ** 2  # 489


def build_map(seed: int = 0) -> tuple[KeyframeMap, BackendInfo]:
    """A random map with the benchmark's shape (content does not affect load speed)."""
    generator = torch.Generator().manual_seed(seed)
    shape = (1, LAYOUT.num_heads, KEYFRAMES * TOKENS, LAYOUT.head_dim)
    layers = [
        torch.randn(shape, generator=generator, dtype=torch.bfloat16)
        for _ in range(2 * LAYOUT.num_layers)
    ]
    cache = KVCache.from_layers(
        layers[0::2],
        layers[1::2],
        layout=LAYOUT,
        tokens_per_frame=TOKENS,
        keyframe_ids=list(range(KEYFRAMES)),
    )
    rng = np.random.default_rng(seed)
    keyframes = tuple(
        Keyframe(
            keyframe_id=i, frame_index=10 * i, timestamp=float(i),
            image=rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8), mask=None,
            T_world_cam=np.eye(4), confidence_map=rng.random((SIZE, SIZE), dtype=np.float32),
            local_points=rng.random((SIZE, SIZE, 3), dtype=np.float32), mean_confidence=0.5,
        )
        for i in range(KEYFRAMES)
    )  # fmt: skip
    info = BackendInfo(
        backend="torch", model="pi3", family="pi3", config_hash="bench", weights_fingerprint="bench",
        patch_size=PATCH, extra_tokens_per_frame=EXTRA, layout=LAYOUT, dtype="bfloat16",
    )  # fmt: skip
    keyframe_map = KeyframeMap(keyframes, cache, Sim3.identity(), resolution=(SIZE, SIZE))
    return keyframe_map, info


def timed(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Median wall time in seconds over ``repeats`` calls, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        result = None  # free the previous result first: one map in memory at a time
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def drop_page_cache(path: Path) -> bool:
    """Evict this file's pages (only this file) so the next read comes from disk."""
    if not hasattr(os, "posix_fadvise"):
        return False
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)
    return True


_MEMORY_PROBE = """
import sys
from pathlib import Path
from kvtracker_sdk.io.map_file.map_file import load_map
def anon():
    line = next(l for l in Path("/proc/self/status").read_text().splitlines() if l.startswith("RssAnon:"))
    return int(line.split()[1]) * 1024
before = anon()
loaded = load_map(sys.argv[1])
print(anon() - before, loaded.keyframe_map.cache.allocated_nbytes)
"""


def load_memory(path: Path) -> tuple[int, int] | None:
    """(anonymous memory a fresh process holds after one load, the cache's buffer bytes).

    Measured in a new process so that no allocator reuse hides the growth; Linux only. File
    pages touched through the memory map are page cache, not anonymous memory.
    """
    if not Path("/proc/self/status").exists():
        return None
    out = subprocess.run(
        [sys.executable, "-c", _MEMORY_PROBE, str(path)], capture_output=True, text=True, check=True
    )
    growth, allocated = out.stdout.split()
    return int(growth), int(allocated)


def read_file(path: Path, buffer: bytearray) -> int:
    with open(path, "rb", buffering=0) as handle:
        return handle.readinto(buffer)  # type: ignore[no-any-return]


def mmap_load(path: Path) -> KeyframeMap:
    """The earlier loader (reference): safetensors memory map, sha256, copy into a cache.

    Kept here only to measure the one-descriptor loader against it in the same run; a file
    truncated underneath it raises SIGBUS (``tests/io/test_map_changed_while_loading.py``).
    """
    info = read_map_info(path)
    with safe_open(str(path), framework="pt") as reader:
        tensors = {name: reader.get_tensor(name) for name in info.tensor_schema()}
    verify_checksums(tensors, info.tensor_sha256, str(path))
    return map_from_tensors(tensors, info, str(path))


def breakdown(path: Path, repeats: int) -> dict[str, float]:
    """Seconds spent in each stage of ``load_map`` (same calls, timed one by one)."""

    def header() -> MapInfo:
        with open_map_file(path) as file:
            return parse_header(file.read_header(), file_size=file.size, source=str(path))[0]

    def read(verify: bool) -> Any:
        with open_map_file(path) as file:
            info, _, offsets = parse_header(
                file.read_header(), file_size=file.size, source=str(path)
            )
            return read_map_tensors(file, info, offsets, verify=verify)

    t_header, _ = timed(header, repeats)
    t_read, _ = timed(lambda: read(False), repeats)
    t_read_hash, _ = timed(lambda: read(True), repeats)
    return {"header": t_header, "pread_into_cache": t_read, "pread_and_sha256": t_read_hash}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "map_load.json"
    )
    args = parser.parse_args()

    keyframe_map, backend = build_map()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bench.kvmap"
        start = time.perf_counter()
        info = save_map(
            path, keyframe_map, backend_info=backend, tracker_config_json="{}", mode="scene"
        )
        t_save = time.perf_counter() - start
        del keyframe_map  # free the source cache before measuring loads
        size_gb = info.file_size / 1e9
        cache_gb = info.cache_nbytes / 1e9
        cold_dropped = drop_page_cache(path)
        start = time.perf_counter()
        load_map(path)
        t_cold = time.perf_counter() - start
        t_verified, loaded = timed(lambda: load_map(path), args.repeats)
        t_unverified, _ = timed(lambda: load_map(path, verify_checksums=False), args.repeats)
        stages = breakdown(path, args.repeats)
        t_mmap, _ = timed(lambda: mmap_load(path), args.repeats)
        buffer = bytearray(info.file_size)
        t_read, _ = timed(lambda: read_file(path, buffer), args.repeats)
        flat = torch.ones(info.cache_nbytes // 2, dtype=torch.bfloat16)
        t_memcpy, _ = timed(flat.clone, args.repeats)
        del flat, loaded
        memory = load_memory(path)

    rows = [
        ("save_map (hash + write + fsync)", t_save, size_gb),
        ("load_map, cold page cache" + ("" if cold_dropped else " (not dropped)"), t_cold, size_gb),
        ("load_map, verified (default)", t_verified, size_gb),
        ("load_map, verify_checksums=False", t_unverified, size_gb),
        ("  header only (open + pread + parse)", stages["header"], None),
        ("  pread into the cache, no hashing", stages["pread_into_cache"], size_gb),
        ("  pread into the cache + sha256", stages["pread_and_sha256"], size_gb),
        ("reference: previous mmap loader, verified", t_mmap, size_gb),
        ("reference: readinto whole file", t_read, size_gb),
        ("reference: in-memory copy of cache size", t_memcpy, cache_gb),
    ]
    print(f"map: {KEYFRAMES} keyframes, {SIZE}x{SIZE}, {LAYOUT.num_layers} layers x {LAYOUT.num_heads} "
          f"heads x {LAYOUT.head_dim}, T={TOKENS}, bfloat16; file {size_gb:.3f} GB, K/V {cache_gb:.3f} GB")  # fmt: skip
    print(f"{'stage':44s} {'seconds':>9s} {'GB/s':>8s}")
    for name, seconds, gigabytes in rows:
        rate = f"{gigabytes / seconds:8.2f}" if gigabytes else f"{'':8s}"
        print(f"{name:44s} {seconds:9.3f} {rate}")

    result = {
        "map": {"keyframes": KEYFRAMES, "resolution": [SIZE, SIZE], "layers": LAYOUT.num_layers,
                "heads": LAYOUT.num_heads, "head_dim": LAYOUT.head_dim, "tokens_per_frame": TOKENS,
                "dtype": "bfloat16", "file_bytes": info.file_size, "cache_bytes": info.cache_nbytes},
        "seconds": {name.strip(): seconds for name, seconds, _ in rows},
        "gb_per_s": {name.strip(): gb / s for name, s, gb in rows if gb},
        "anon_memory_after_load_bytes": None if memory is None else memory[0],
        "cache_allocated_bytes": None if memory is None else memory[1],
        "repeats": args.repeats,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__,
                    "safetensors": safetensors.__version__, "python": platform.python_version()},
    }  # fmt: skip
    if memory is not None:
        print(
            f"anonymous memory held by a fresh process after one load: {memory[0] / 1e9:.3f} GB "
            f"(the cache's buffers, spare capacity included: {memory[1] / 1e9:.3f} GB)"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
