"""Record what the tracker does on a fixed set of runs, and check that a change left it unchanged.

A refactor that should not change behaviour must give the same bytes: every frame's pose, state
and reason, the keyframes and their poses, and every tensor of every saved map. This script
records those for a fixed set of runs and compares two recordings:

* ``scene_sync``: the simulated backend over the shared TUM trajectory (a loss in the middle),
  synchronous mapping; its map is saved;
* ``scene_async``: the same frames with the mapping worker on its own thread
  (``threading.async_mapping``); the script waits for each pending rebuild after every frame
  (``wait_for_map``), so the frame a rebuild lands on does not depend on timing;
* ``scene_reload``: ``scene_sync``'s map loaded into a new tracker (``Tracker.from_map``), which
  tracks on and extends it; its map is saved again;
* ``object_desk``: object mode on the simulated desk scene (a box on a table beside another; the
  true mask on frame 0 only), then ``object_reload``: its map loaded, tracked on without a mask;
* ``pi3_tum`` / ``da3_tum``: the golden (reduced) Pi3 and DA3 models of ``../shared/golden`` on the
  20 shared TUM frames (224 px, a keyframe every 5 frames);
* ``pi3_tum_int8``: the same Pi3 run with ``cache_dtype="int8"``: a compact map file.

What is recorded per run (``<run>.json`` + ``<run>.npz``): each frame's state, reason,
``pose_valid``, keyframe id, map generation, confidence (``float.hex``), intrinsics, object region
and error type; its ``T_world_cam`` (and ``T_cam_object``) as float64; the keyframes' ids, frame
indices and poses at the end of the run; for a saved map: every tensor of the safetensors file
(dtype, shape, sha256 of its raw bytes), every header metadata field (decoded JSON), the config a
tracker loading it reports, and each keyframe's image and mask as decoded by loading the map.

Comparing two recordings (``check``, ``compare``) asks for equality of all of that, except the
allow-list below: fields a new map format version may add or change (its version, the config
stored as structured JSON, the way keyframe images are stored). The keyframe images are compared
decoded (uint8 after loading), so a lossless re-encoding passes and a lossy one does not.

The bytes of floating-point results depend on the CPU (ISA, SIMD width), the torch build and the
thread count: **a reference is for comparing two commits on the same machine and environment**.
The committed reference (``benchmarks/behaviour/reference``) says where it was recorded
(``environment.json``); on another machine, record the base commit yourself (``compare``).

Usage, from the repository root (``PYTHONPATH=$PWD``)::

    python benchmarks/behaviour/record.py record --out DIR [--runs ...]
    python benchmarks/behaviour/record.py check [--reference DIR] [--against DIR2]
    python benchmarks/behaviour/record.py compare --base main   # base commit vs this tree

``check`` records this tree now (or takes ``--against``, a recording made before) and compares it
with ``--reference`` (default: the committed one). ``compare`` checks the base commit out into a temporary ``git worktree``, records it with *this*
script (which uses only the public API, so it runs at older commits), records the working tree,
and compares the two. ``--shared`` names the ``shared`` folder (default: beside the repository).

Only the public API is used (``kvtracker_sdk``'s top-level names, the ``Tracker`` facade, its
``save_map``/``from_map``), plus the safetensors file layout itself; the few internals it needs
(the simulated desk scene, the keyframes of a tracker's map) are in the adapter functions under
"Adapters" below, so a move of internal modules means editing those only.
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # not when imported (by a test): the env of that process is its own
    # one thread everywhere, before numpy, torch or OpenMP load: results must not depend on
    # how work is split between threads
    for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_variable] = "1"

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import struct  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterable, Iterator  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
DEFAULT_SHARED = REPO.parent / "shared"
REFERENCE = HERE / "reference"
SIM_SIZE = (240, 320)  # (H, W) of the simulated scene's frames
DESK_SIZE = (196, 252)  # of the desk scene's frames (as benchmarks/object_desk.py)
SCENE_FRAMES = 150
SCENE_LOSS = (70, 85)  # frames the simulated network is lost on (relocalisation)
RELOAD_FRAMES = 60  # frames tracked after a reload
OBJECT_FRAMES = 90
TUM_FRAMES = 20

# --------------------------------------------------------------------------- allow-list
# Header metadata fields that differ between any two saves, so never compared.
IGNORED_FIELDS = frozenset({
    "created_utc",  # the time of the save
    "metadata_sha256",  # a checksum over the other fields: follows any of them
})
# Header fields a new map format version may change, add or drop; each difference is reported
# ("allowed: ..."), none fails. What they carry is compared another way:
# * ``tracker_config`` (the saved TrackerConfig, a JSON string today; structured JSON in a new
#   version) and ``mode`` (stored twice today): the config a tracker loading the map reports is
#   compared field by field instead (``loaded_config``);
# * ``keyframe_encoding`` (and the checksums ``tensor_sha256.<tensor>`` of the tensors matched by
#   ``ALLOWED_TENSOR_PREFIXES``): how keyframe images are stored; the images are compared decoded
#   instead (``keyframe_images``).
# A new version's *new* field fails until it is named here (or with ``--allow-field NAME``).
ALLOWED_FIELDS = frozenset({
    "format_version",
    "sdk_version",
    "tracker_config",
    "mode",
    "keyframe_encoding",
    # format version 4: compact maps' keyframe images stored as PNG (checked decoded instead)
    "keyframe_image_codec",
    "keyframe_image_bytes",
})
# Header fields holding a JSON object compared entry by entry (``field.entry``).
FLATTENED_FIELDS = frozenset({"tensor_sha256"})
# Tensors whose stored form may change, be renamed or be added (``keyframes.image*``): compared
# decoded, through loading the map.
ALLOWED_TENSOR_PREFIXES = ("keyframes.image",)


# --------------------------------------------------------------------------- adapters
# The only places that touch internals; keep them small (see the module docstring).
def desk_scene(frames: int) -> tuple[Any, Any]:
    """(ground truth, scene) of the object-on-a-desk walk of ``benchmarks/object_desk.py``."""
    from kvtracker_sdk.backends.simulated_scene import SimulatedScene
    from kvtracker_sdk.cli.demo_trajectory import desk_orbit

    truth = desk_orbit(frames, seed=3)
    return truth, SimulatedScene.desk(truth.poses)


def map_keyframes(tracker: Any) -> list[Any]:
    """The keyframes of ``tracker``'s map (objects with ``keyframe_id``, ``frame_index``,
    ``T_world_cam``, ``image``, ``mask``); empty without a map."""
    kf_map = tracker.keyframe_map
    return [] if kf_map is None else list(kf_map.keyframes)


# --------------------------------------------------------------------------- recording
def _sha(data: bytes | np.ndarray) -> str:
    raw = data.tobytes() if isinstance(data, np.ndarray) else data
    return hashlib.sha256(raw).hexdigest()


def _short_sha(data: np.ndarray) -> str:
    """64 bits of sha256: plenty to tell two values apart, small enough for one row per frame."""
    return _sha(data)[:16]


def _name(value: Any) -> str | None:
    return None if value is None else str(getattr(value, "name", value))


def _hexfloat(value: float | None) -> str | None:
    return None if value is None else float(value).hex()


def _matrix(value: Any) -> np.ndarray:
    out = np.full((4, 4), np.nan)
    if value is not None:
        out[:] = np.asarray(getattr(value, "T_world_cam", value), dtype=np.float64)
    return out


def _frame_row(result: Any) -> dict[str, Any]:
    camera = result.intrinsics
    region = result.region
    return {
        "frame": result.frame_index, "state": _name(result.state), "reason": _name(result.reason),
        "pose": result.pose is not None, "pose_valid": bool(result.pose_valid),
        "keyframe_id": result.keyframe_id, "map_generation": result.map_generation,
        "confidence": _hexfloat(result.confidence),
        "error": None if result.error is None else type(result.error).__name__,
        "intrinsics": None if camera is None else _short_sha(np.array(
            [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height],
            dtype=np.float64)),
        "intrinsics_source": _name(result.intrinsics_source),
        "region": None if region is None else {
            "box": [float(v).hex() for v in region.box], "source": _name(region.source),
            "frame": region.frame_index, "mask": _short_sha(np.packbits(np.asarray(region.mask)))},
    }


def _line(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


class Recorder:
    """Collects one run's frames, keyframes and saved map; writes ``<run>.json`` / ``.npz``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.rows: list[dict[str, Any]] = []
        self.poses: list[np.ndarray] = []
        self.object_poses: list[np.ndarray] = []
        self.keyframes: list[dict[str, Any]] = []
        self.keyframe_poses = np.zeros((0, 4, 4))
        self.map: dict[str, Any] | None = None

    def frame(self, result: Any) -> None:
        self.rows.append(_frame_row(result))
        self.poses.append(_matrix(result.pose))
        self.object_poses.append(_matrix(result.T_cam_object))

    def end(self, tracker: Any) -> None:
        keyframes = map_keyframes(tracker)
        self.keyframes = [{"id": kf.keyframe_id, "frame": kf.frame_index} for kf in keyframes]
        self.keyframe_poses = np.array([_matrix(kf.T_world_cam) for kf in keyframes]).reshape(
            -1, 4, 4)

    def write(self, out: Path) -> None:
        # one line per frame and per keyframe: small files that diff readably
        lines = ["{", '"frames": [', ",\n".join(_line(r) for r in self.rows), "],",
                 '"keyframes": [', ",\n".join(_line(k) for k in self.keyframes), "],",
                 f'"map": {json.dumps(self.map, indent=1, sort_keys=True)}', "}"]
        (out / f"{self.name}.json").write_text("\n".join(lines) + "\n")
        np.savez_compressed(
            out / f"{self.name}.npz", poses=np.array(self.poses).reshape(-1, 4, 4),
            object_poses=np.array(self.object_poses).reshape(-1, 4, 4),
            keyframe_poses=self.keyframe_poses)


def safetensors_header(path: Path) -> tuple[dict[str, Any], int]:
    """The JSON header of a safetensors file and the offset of its data section."""
    with path.open("rb") as file:
        (length,) = struct.unpack("<Q", file.read(8))
        return json.loads(file.read(length)), 8 + length


def _decoded(value: str) -> Any:
    try:
        return json.loads(value)
    except ValueError:
        return value


def describe_map(path: Path, load: Callable[[Path], Any]) -> dict[str, Any]:
    """Every tensor (dtype, shape, sha256 of its bytes) and header field of the map at ``path``,
    and what a tracker made by ``load(path)`` reports: its config and keyframes (decoded)."""
    header, start = safetensors_header(path)
    metadata = header.pop("__metadata__", {})
    data = path.read_bytes()[start:]
    tensors = {
        name: {"dtype": spec["dtype"], "shape": spec["shape"],
               "sha256": _sha(data[spec["data_offsets"][0]:spec["data_offsets"][1]])}
        for name, spec in sorted(header.items())}
    fields: dict[str, Any] = {}
    for key, value in sorted(metadata.items()):
        decoded = _decoded(value)
        if key in FLATTENED_FIELDS and isinstance(decoded, dict):
            fields.update({f"{key}.{entry}": v for entry, v in sorted(decoded.items())})
        else:
            fields[key] = decoded
    with load(path) as tracker:
        config = tracker.config.to_dict()
        keyframes = [{
            "id": kf.keyframe_id, "frame": kf.frame_index,
            "T_world_cam_sha256": _sha(np.asarray(kf.T_world_cam, dtype=np.float64)),
            "image": [str(kf.image.dtype), list(kf.image.shape), _sha(np.ascontiguousarray(
                kf.image))],
            "mask": None if kf.mask is None else _sha(np.packbits(np.asarray(kf.mask))),
        } for kf in map_keyframes(tracker)]
    return {"tensors": tensors, "fields": fields, "loaded_config": config,
            "keyframe_images": keyframes, "file_bytes": path.stat().st_size}


def track(tracker: Any, frames: Iterable[tuple[Any, dict[str, Any]]], recorder: Recorder, *,
          settle: bool = False) -> None:
    """Push ``frames`` ((image, push_frame options)); with ``settle``, install each pending
    rebuild before the next frame (asynchronous mapping, made deterministic)."""
    for image, options in frames:
        recorder.frame(tracker.push_frame(image, **options))
        if settle:
            tracker.wait_for_map()


def _sim_frames(backend: Any, size: tuple[int, int], start: int, stop: int,
                first_mask: bool = False) -> Iterator[tuple[Any, dict[str, Any]]]:
    for frame in backend.frames(size, start=start, stop=stop, textured=not first_mask,
                                with_mask=first_mask):
        options: dict[str, Any] = {"timestamp": frame.timestamp}
        if first_mask and frame.index == start:
            options["mask"] = frame.mask
        yield frame.image, options


def _read_png(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path))
    if image is None:
        raise SystemExit(f"cannot read {path}")
    return image


class Runs:
    """The recorded runs; each method records one or more ``Recorder`` s into ``out``."""

    def __init__(self, shared: Path, out: Path) -> None:
        self.shared = shared
        self.out = out
        self.maps = out / "maps"  # saved maps (not kept: only their description is)
        self.maps.mkdir(parents=True, exist_ok=True)

    def _scene_backend(self) -> Any:
        from kvtracker_sdk import SimulatedBackend

        truth = self.shared / "data" / "tum_fr2_desk" / "groundtruth.txt"
        return SimulatedBackend.from_tum(truth, loss_segments=[SCENE_LOSS], seed=1)

    def _save(self, recorder: Recorder, tracker: Any, backend: Any) -> Path:
        from kvtracker_sdk import Tracker

        path = self.maps / f"{recorder.name}.kvmap"
        tracker.save_map(path)
        recorder.map = describe_map(path, lambda p: Tracker.from_map(p, backend))
        return path

    def scene(self, *, asynchronous: bool) -> list[Recorder]:
        from kvtracker_sdk import Tracker

        name = "scene_async" if asynchronous else "scene_sync"
        recorder, backend = Recorder(name), self._scene_backend()
        config = {"keyframing": {"interval_frames": 10},
                  "threading": {"async_mapping": asynchronous}}
        with Tracker(config, backend) as tracker:
            track(tracker, _sim_frames(backend, SIM_SIZE, 0, SCENE_FRAMES), recorder,
                  settle=asynchronous)
            tracker.wait_for_map()
            recorder.end(tracker)
            path = self._save(recorder, tracker, backend)
        if asynchronous:
            return [recorder]
        reload = Recorder("scene_reload")
        with Tracker.from_map(path, backend) as tracker:
            track(tracker, _sim_frames(backend, SIM_SIZE, SCENE_FRAMES,
                                       SCENE_FRAMES + RELOAD_FRAMES), reload)
            reload.end(tracker)
            self._save(reload, tracker, backend)
        return [recorder, reload]

    def object_desk(self) -> list[Recorder]:
        from kvtracker_sdk import SimulatedBackend, Tracker

        truth, scene = desk_scene(OBJECT_FRAMES + RELOAD_FRAMES)
        backend = SimulatedBackend(truth, scene=scene, seed=2, translation_noise_m=0.003,
                                   rotation_noise_deg=0.1, object_in_view=True)
        recorder = Recorder("object_desk")
        config = {"mode": "object", "resolution": 224, "keyframing": {"interval_frames": 10}}
        with Tracker(config, backend) as tracker:
            track(tracker, _sim_frames(backend, DESK_SIZE, 0, OBJECT_FRAMES, True), recorder)
            recorder.end(tracker)
            path = self._save(recorder, tracker, backend)
        reload = Recorder("object_reload")
        with Tracker.from_map(path, backend) as tracker:
            frames = _sim_frames(backend, DESK_SIZE, OBJECT_FRAMES, OBJECT_FRAMES + RELOAD_FRAMES)
            track(tracker, ((image, {"timestamp": o["timestamp"]}) for image, o in frames),
                  reload)
            reload.end(tracker)
        return [recorder, reload]

    def golden(self, family: str, *, cache_dtype: str = "backend") -> list[Recorder]:
        import cv2

        from kvtracker_sdk import TorchBackend, Tracker

        tum = self.shared / "data" / "tum_fr2_desk"
        files = sorted((tum / "rgb").glob("*.png"))[:TUM_FRAMES]
        images = [cv2.cvtColor(_read_png(f), cv2.COLOR_BGR2RGB) for f in files]
        stamps = [float(f.stem) for f in files]
        name = f"{family}_tum" + ("" if cache_dtype == "backend" else f"_{cache_dtype}")
        recorder = Recorder(name)
        backend = TorchBackend.from_pretrained(self.shared / "golden" / family /
                                               "weights.safetensors")
        config = {"resolution": 224, "cache_dtype": cache_dtype,
                  "keyframing": {"interval_frames": 5}}
        try:
            with Tracker(config, backend) as tracker:
                track(tracker, ((im, {"timestamp": t}) for im, t in zip(images, stamps,
                                                                         strict=True)),
                      recorder)
                recorder.end(tracker)
                self._save(recorder, tracker, backend)
        finally:
            backend.close()
        return [recorder]


RUNS: dict[str, Callable[[Runs], list[Recorder]]] = {
    "scene": lambda r: r.scene(asynchronous=False),  # scene_sync + scene_reload
    "scene_async": lambda r: r.scene(asynchronous=True),
    "object": lambda r: r.object_desk(),  # object_desk + object_reload
    "pi3": lambda r: r.golden("pi3"),
    "da3": lambda r: r.golden("da3"),
    "pi3_int8": lambda r: r.golden("pi3", cache_dtype="int8"),
}


def environment() -> dict[str, Any]:
    import torch

    import kvtracker_sdk

    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", *args], cwd=Path(kvtracker_sdk.__file__).parent,
                                  capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None

    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    dirty = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": git("rev-parse", "HEAD"), "dirty": bool(dirty),
            "sdk_version": kvtracker_sdk.__version__, "python": platform.python_version(),
            "torch": torch.__version__, "numpy": np.__version__, "cpu": cpu,
            "machine": platform.machine(), "torch_threads": torch.get_num_threads(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability()}


def record(out: Path, shared: Path, runs: list[str]) -> None:
    import torch

    torch.set_num_threads(1)
    torch.manual_seed(0)
    np.random.seed(0)
    out.mkdir(parents=True, exist_ok=True)
    wall, cpu = time.perf_counter(), time.process_time()
    runner = Runs(shared, out)
    try:
        for run in runs:
            for recorder in RUNS[run](runner):
                recorder.write(out)
    finally:
        shutil.rmtree(runner.maps, ignore_errors=True)
    env = environment() | {"runs": runs, "record_wall_s": round(time.perf_counter() - wall, 1),
                           "record_cpu_s": round(time.process_time() - cpu, 1)}
    (out / "environment.json").write_text(json.dumps(env, indent=1, sort_keys=True))
    print(f"recorded {runs} into {out} in {env['record_wall_s']} s wall, "
          f"{env['record_cpu_s']} s CPU")


# --------------------------------------------------------------------------- comparing
def _array_diff(name: str, base: np.ndarray, new: np.ndarray) -> list[str]:
    if base.shape != new.shape:
        return [f"{name}: shape {base.shape} -> {new.shape}"]
    if base.tobytes() == new.tobytes():
        return []
    differ = np.argwhere(~((base == new) | (np.isnan(base) & np.isnan(new))))
    first = tuple(int(i) for i in differ[0])
    both = np.isfinite(base) & np.isfinite(new)
    largest = float(np.abs(base - new)[both].max()) if both.any() else float("nan")
    return [f"{name}: {len(differ)} values differ (first at {first}: {base[first]!r} -> "
            f"{new[first]!r}; largest difference {largest:.3g})"]


def _rows_diff(name: str, base: list[Any], new: list[Any]) -> list[str]:
    problems = [f"{name}: {len(base)} -> {len(new)} entries"] if len(base) != len(new) else []
    for i, (a, b) in enumerate(zip(base, new, strict=False)):
        if a != b:
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            problems.append(f"{name}[{i}]: " + "; ".join(
                f"{k} {a.get(k)!r} -> {b.get(k)!r}" for k in keys))
            if len(problems) >= 5:
                problems.append(f"{name}: (further differences not listed)")
                break
    return problems


def _dotted(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            out.update(_dotted(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _map_diff(run: str, base: dict[str, Any], new: dict[str, Any], allowed: frozenset[str],
              notes: list[str]) -> list[str]:
    problems: list[str] = []
    for name in sorted(set(base["tensors"]) | set(new["tensors"])):
        a, b = base["tensors"].get(name), new["tensors"].get(name)
        if a != b:
            where = f"{run} map tensor {name}: {a} -> {b}"
            (notes if name.startswith(ALLOWED_TENSOR_PREFIXES) else problems).append(where)
    for key in sorted(set(base["fields"]) | set(new["fields"])):
        if key in IGNORED_FIELDS:
            continue
        a, b = base["fields"].get(key, "<absent>"), new["fields"].get(key, "<absent>")
        if a != b:
            where = f"{run} map field {key}: {a!r} -> {b!r}"
            stored_image = key.startswith(tuple(f"tensor_sha256.{prefix}"
                                                for prefix in ALLOWED_TENSOR_PREFIXES))
            (notes if key in allowed or stored_image else problems).append(where)
    a_config, b_config = _dotted(base["loaded_config"]), _dotted(new["loaded_config"])
    for key in sorted(set(a_config) | set(b_config)):
        if key not in a_config:  # a new option; the runs above show whether its default acts
            notes.append(f"{run} loaded config: new field {key} = {b_config[key]!r}")
        elif a_config[key] != b_config.get(key, "<absent>"):
            problems.append(f"{run} loaded config {key}: {a_config[key]!r} -> "
                            f"{b_config.get(key, '<absent>')!r}")
    problems += _rows_diff(f"{run} map keyframe_images", base["keyframe_images"],
                           new["keyframe_images"])
    if base["file_bytes"] != new["file_bytes"]:
        notes.append(f"{run} map file: {base['file_bytes']} -> {new['file_bytes']} bytes")
    return problems


def compare(base: Path, new: Path, allowed: frozenset[str] = ALLOWED_FIELDS) -> int:
    """Print the differences between two recordings; 0 when none outside the allow-list."""
    problems: list[str] = []
    notes: list[str] = []
    runs = sorted(p.stem for p in new.glob("*.json") if p.name != "environment.json")
    left = sorted(p.stem for p in base.glob("*.json") if p.name != "environment.json")
    if set(left) - set(runs):
        notes.append(f"not recorded this time (not compared): {sorted(set(left) - set(runs))}")
    for run in runs:
        if not (base / f"{run}.json").exists():
            problems.append(f"{run}: not in the base recording {base}")
            continue
        a, b = (json.loads((d / f"{run}.json").read_text()) for d in (base, new))
        problems += _rows_diff(f"{run} frames", a["frames"], b["frames"])
        problems += _rows_diff(f"{run} keyframes", a["keyframes"], b["keyframes"])
        with np.load(base / f"{run}.npz") as x, np.load(new / f"{run}.npz") as y:
            for key in sorted(set(x.files) | set(y.files)):
                problems += _array_diff(f"{run} {key}", x[key], y[key])
        if (a["map"] is None) != (b["map"] is None):
            problems.append(f"{run}: map saved in one recording only")
        elif a["map"] is not None:
            problems += _map_diff(run, a["map"], b["map"], allowed, notes)
    envs = [json.loads((d / "environment.json").read_text()) for d in (base, new)]
    for key in ("torch", "numpy", "cpu", "cpu_capability", "machine"):
        if envs[0].get(key) != envs[1].get(key):
            notes.append(f"environment {key}: {envs[0].get(key)} -> {envs[1].get(key)} "
                         "(bytes of float results may differ for this reason alone)")
    for note in notes:
        print(f"allowed: {note}")
    for problem in problems:
        print(f"DIFFERS: {problem}")
    print(f"{len(runs)} runs compared: " + (
        "identical (outside the allow-list)" if not problems else f"{len(problems)} differences"))
    return 1 if problems else 0


def _record_commit(commit: str, out: Path, shared: Path, runs: list[str]) -> None:
    """Record ``commit`` (a temporary git worktree) with this script."""
    with tempfile.TemporaryDirectory(prefix="behaviour-base-") as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), commit], cwd=REPO,
                       check=True, capture_output=True)
        try:
            script = Path(tmp) / "record.py"
            shutil.copy(__file__, script)
            env = os.environ | {"PYTHONPATH": str(tree)}
            subprocess.run([sys.executable, str(script), "record", "--out", str(out),
                            "--shared", str(shared), "--runs", *runs], cwd=tree, env=env,
                           check=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO,
                           check=False, capture_output=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("mode", choices=["record", "check", "compare"])
    parser.add_argument("--out", type=Path, help="record: the folder to write")
    parser.add_argument("--reference", type=Path, default=REFERENCE,
                        help="check: the recording to compare with")
    parser.add_argument("--against", type=Path,
                        help="check: compare with this recording instead of recording now")
    parser.add_argument("--base", help="compare: the commit to compare this tree with")
    parser.add_argument("--shared", type=Path, default=DEFAULT_SHARED)
    parser.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS))
    parser.add_argument("--allow-field", action="append", default=[],
                        help="a further header field that may differ (repeatable)")
    args = parser.parse_args(argv)
    allowed = ALLOWED_FIELDS | frozenset(args.allow_field)
    if args.mode == "record":
        if args.out is None:
            parser.error("record needs --out")
        record(args.out, args.shared.resolve(), args.runs)
        return 0
    if args.mode == "check" and args.against is not None:
        return compare(args.reference, args.against, allowed)
    with tempfile.TemporaryDirectory(prefix="behaviour-") as tmp:
        if args.mode == "compare":
            if args.base is None:
                parser.error("compare needs --base")
            base = Path(tmp) / "base"
            _record_commit(args.base, base, args.shared.resolve(), args.runs)
        else:
            base = args.reference
        new = Path(tmp) / "new"
        record(new, args.shared.resolve(), args.runs)
        return compare(base, new, allowed)


if __name__ == "__main__":
    sys.exit(main())
