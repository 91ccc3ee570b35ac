"""OpenVinoBackend on each family's session export (``onnx_exports``: no export of its own).

Golden parity: the official golden vectors (``../shared/golden/pi3/case1``, ``golden/da3``: a
mapping pass over frames 0-2, frame 3 tracked against its cache) through ``OpenVinoBackend`` in
fp32, poses within 1e-4 (the issue's tolerance; measured ~1e-6), confidence within 1e-4, depth
within 1e-4 + rtol 1e-4. Cross-backend: identity equal to ``TorchBackend``'s, and frames tracked
on a map made by torch, onnx or openvino give the torch poses within 1e-4. bf16: the precision
hint takes effect and the cache stays float32 (DA3 mapping + query in bf16 against the golden
fp32 query pose: below 0.05 on these random weights; measured 1.8e-2).
"""

from __future__ import annotations

import shutil
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file

from kvtracker_sdk.backends.base import Backend, MapResult
from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.onnx_manifest import WEIGHTS_NAME
from kvtracker_sdk.backends.openvino import OpenVinoBackend
from kvtracker_sdk.backends.openvino_runtime import (
    MIXED_FP32_GRAPHS,
    graph_precisions,
    static_graphs,
)
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import ConfigError, MissingDependencyError, ModelError, StateError
from kvtracker_sdk.geometry.se3 import invert_rigid
from kvtracker_sdk.types import HeadSet
from tests.conftest import OnnxExport
from tests.helpers import dev_dependency, openvino_bf16_or_skip, shared_path

MODELS = {"pi3": "pi3-custom", "da3": "da3-custom"}


@dataclass(frozen=True)
class Golden:
    """A family's golden mapping pass (frames 0-2) and query (frame 3), in SDK conventions."""

    images: np.ndarray  # float32 [4, H, W, 3] RGB in [0, 1]
    keyframe_poses: np.ndarray  # [3, 4, 4] T_world_cam
    confidence: np.ndarray  # [3, H, W] in [0, 1]
    depth: np.ndarray  # [3, H, W]: the local points' z
    query_pose: np.ndarray  # [4, 4]


def _T_world_cam(extrinsics: np.ndarray) -> np.ndarray:
    """DA3's world-to-camera [..., 3, 4] -> camera-to-world [..., 4, 4]."""
    bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (*extrinsics.shape[:-2], 1, 4))
    return invert_rigid(np.concatenate((extrinsics.astype(np.float64), bottom), axis=-2))


def golden(family: str) -> Golden:
    if family == "pi3":
        folder = shared_path("golden", "pi3", "case1")
        imgs = load_file(folder / "inputs.safetensors")["imgs"][0]
        out = load_file(folder / "outputs_query.safetensors")
        return Golden(
            np.ascontiguousarray(imgs.transpose(0, 2, 3, 1)),
            out["keyframes.camera_poses"][0],
            1.0 / (1.0 + np.exp(-out["keyframes.conf"][0, ..., 0])),  # logits -> [0, 1]
            out["keyframes.local_points"][0, ..., 2],
            out["query.camera_poses"][0, 0],
        )
    folder = shared_path("golden", "da3")
    imgs = load_file(folder / "inputs.safetensors")["imgs_01"][0]
    out = load_file(folder / "outputs_query.safetensors")
    return Golden(
        np.ascontiguousarray(imgs.transpose(0, 2, 3, 1)),
        _T_world_cam(out["keyframes.extrinsics"][0]),
        1.0 - 1.0 / out["keyframes.depth_conf"][0],
        out["keyframes.depth"][0],
        _T_world_cam(out["query.extrinsics"][0])[0],
    )


@dataclass(frozen=True)
class Runtimes:
    family: str
    export: OnnxExport
    openvino: OpenVinoBackend
    torch: TorchBackend
    golden: Golden
    openvino_map: MapResult
    other_maps: dict[str, MapResult]  # the golden mapping pass made by torch and by onnx


@pytest.fixture(scope="module", params=sorted(MODELS))
def runtimes(
    request: pytest.FixtureRequest, onnx_exports: Callable[[str], OnnxExport]
) -> Runtimes:
    dev_dependency("openvino")
    family = str(request.param)
    export, case = onnx_exports(family), golden(family)
    backend = OpenVinoBackend(export.folder, threads=1)
    torch_backend = TorchBackend.from_pretrained(export.weights)
    onnx_backend = OnnxBackend(export.folder, threads=1)
    keyframes = case.images[:3]
    others = {"torch": torch_backend.map(keyframes), "onnx": onnx_backend.map(keyframes)}
    onnx_backend.close()
    return Runtimes(
        family, export, backend, torch_backend, case, backend.map(keyframes), others
    )


def test_info_equals_the_torch_backends(runtimes: Runtimes) -> None:
    info, reference = runtimes.openvino.info, runtimes.torch.info
    assert isinstance(runtimes.openvino, Backend)
    assert (info.backend, info.family, info.model, info.dtype, info.device) == (
        "openvino", runtimes.family, MODELS[runtimes.family], "float32", "cpu",
    )  # fmt: skip
    assert info.fingerprint == reference.fingerprint  # caches and maps cross between them
    assert info.layout == reference.layout
    assert info.tokens_per_frame(112, 154) == reference.tokens_per_frame(112, 154)
    assert info.accelerations[:3] == ("openvino:CPU", "precision:f32", "threads:1")
    static = {"da3": "static-shapes", "pi3": "static:decoder_track,head_camera,head_conf,head_points"}
    assert info.accelerations[3:] == (static[runtimes.family],)  # Pi3's encoder stays dynamic


def test_tracking_compiles_each_map_shape_once(runtimes: Runtimes) -> None:
    """Static shapes: the tracking graphs are compiled per map shape (``past_length`` folded in,
    here with scratch capacity past it) and give the torch step's pose (fp32, within 1e-4)."""
    backend, query = runtimes.openvino, runtimes.golden.images[3]
    smaller = runtimes.openvino_map.cache.clone()
    smaller.drop_keyframes(smaller.keyframe_ids[:1])
    assert smaller.capacity > smaller.length  # the dropped keyframe's tokens stay as scratch
    backend.track(query, runtimes.openvino_map.cache, heads=HeadSet.CAMERA)
    before = [graph for graph, _ in backend.static_compiles]
    assert "decoder_track" in before  # (Pi3's encoder stays dynamic: openvino_static)
    for _ in range(2):
        pose = backend.track(query, smaller, heads=HeadSet.CAMERA).pose
    after = [graph for graph, _ in backend.static_compiles]
    assert after == [*before, "decoder_track"]  # one compile for the new length, reused
    expected = runtimes.torch.track(query, smaller, heads=HeadSet.CAMERA).pose
    np.testing.assert_allclose(pose, expected, atol=1e-4, rtol=0)


def test_static_shapes_choose_the_tracking_graphs(runtimes: Runtimes) -> None:
    manifest, every = runtimes.openvino.manifest, {"encoder", "decoder_track", "head_camera"}
    assert static_graphs(None, manifest, "float32") >= every  # fp32: every tracking graph
    assert static_graphs(None, manifest, "mixed") == static_graphs(None, manifest, "float32")
    # bf16: every tracking graph but the decoder (see static_graphs)
    every_but_decoder = static_graphs(True, manifest, "bfloat16") - {"decoder_track"}
    assert static_graphs(None, manifest, "bfloat16") == every_but_decoder
    assert "encoder" in static_graphs(None, manifest, "bfloat16")
    assert static_graphs(False, manifest, "float32") == set()
    assert "decoder_map" not in static_graphs(True, manifest, "bfloat16")
    with pytest.raises(ConfigError, match="decoder_map"):
        static_graphs({"decoder_map"}, manifest, "float32")


def test_golden_mapping_pass(runtimes: Runtimes) -> None:
    mapped, expected = runtimes.openvino_map, runtimes.golden
    assert mapped.poses.dtype == np.float64 and mapped.poses.shape == (3, 4, 4)
    np.testing.assert_allclose(mapped.poses, expected.keyframe_poses, atol=1e-4, rtol=0)
    np.testing.assert_allclose(mapped.confidence, expected.confidence, atol=1e-4, rtol=0)
    np.testing.assert_allclose(mapped.local_points[..., 2], expected.depth, atol=1e-4, rtol=1e-4)
    assert mapped.cache.keyframe_ids == (0, 1, 2) and str(mapped.cache.dtype) == "torch.float32"


@pytest.mark.parametrize("heads", list(HeadSet))
def test_golden_query_on_a_map_of_each_runtime(runtimes: Runtimes, heads: HeadSet) -> None:
    query = runtimes.golden.images[3]
    maps = {"openvino": runtimes.openvino_map, **runtimes.other_maps}
    before = runtimes.openvino_map.cache.clone()
    expected = runtimes.torch.track(query, maps["torch"].cache, heads=heads)
    for made_by, mapped in maps.items():
        result = runtimes.openvino.track(query, mapped.cache, heads=heads)
        golden_pose = runtimes.golden.query_pose
        np.testing.assert_allclose(result.pose, golden_pose, atol=1e-4, err_msg=made_by)
        np.testing.assert_allclose(result.pose, expected.pose, atol=1e-4, err_msg=made_by)
        assert (result.confidence is None) == (heads is HeadSet.CAMERA)
        if result.confidence_map is not None:
            assert expected.confidence_map is not None
            np.testing.assert_allclose(result.confidence_map, expected.confidence_map, atol=1e-4)
        assert (result.local_points is None) == (heads is not HeadSet.ALL)
        if result.local_points is not None:
            assert expected.local_points is not None
            np.testing.assert_allclose(
                result.local_points, expected.local_points, atol=1e-4, rtol=1e-4
            )
        assert result.timings_ms["track"] > 0 and not result.pose.flags.writeable
    assert runtimes.openvino_map.cache.equals(before)  # tracking only reads the cache


def test_bfloat16_hint_keeps_a_float32_cache(onnx_exports: Callable[[str], OnnxExport]) -> None:
    """DA3 (the CPU model; Pi3 runs bf16 in ``test_openvino_network.py``): a whole bf16 pass,
    mapping and tracking, against the golden fp32 query."""
    dev_dependency("openvino")
    openvino_bf16_or_skip()
    from kvtracker_sdk.backends.openvino_core import shared_core

    export, case = onnx_exports("da3"), golden("da3")
    fast = OpenVinoBackend.from_pretrained(export.folder, precision="bfloat16", threads=1)
    assert fast.info.dtype == "float32"
    assert fast.info.fingerprint == TorchBackend.from_pretrained(export.weights).info.fingerprint
    mapped = fast.map(case.images[:3])
    assert str(mapped.cache.dtype) == "torch.float32"  # shared with every fp32 backend
    deviation = np.abs(fast.track(case.images[3], mapped.cache).pose - case.query_pose).max()
    assert deviation < 0.05
    if "BF16" in shared_core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"):
        assert "precision:bf16" in fast.info.accelerations
        assert deviation > 1e-5  # the hint took effect: bf16 products round differently
    static = next(name for name in fast.info.accelerations if name.startswith("static:"))
    assert "encoder" in static and "decoder_track" not in static  # bf16: the decoder stays dynamic
    fast.close()
    fast.close()  # idempotent
    with pytest.raises(StateError, match="this OpenVinoBackend is closed"):
        fast.track(case.images[3], mapped.cache)


def test_mixed_precision_keeps_the_graphs_the_pose_passes_float32(
    onnx_exports: Callable[[str], OnnxExport],
) -> None:
    """"mixed": bf16 encoder and dense heads, fp32 decoders and camera head, as the plugin
    reports them back; a map and a query against the golden fp32 query pose."""
    dev_dependency("openvino")
    openvino_bf16_or_skip()
    from kvtracker_sdk.backends.openvino_core import shared_core

    graphs = ("encoder", "decoder_map", "decoder_track", "head_camera", "head_depth")
    assert graph_precisions("mixed", graphs) == {
        "encoder": "bfloat16", "decoder_map": "float32", "decoder_track": "float32",
        "head_camera": "float32", "head_depth": "bfloat16"}  # fmt: skip
    assert set(graph_precisions("bfloat16", graphs).values()) == {"bfloat16"}
    assert set(graphs) >= MIXED_FP32_GRAPHS
    with pytest.raises(ConfigError, match="mixed"):  # the message lists what is known
        graph_precisions("int8", graphs)
    export, case = onnx_exports("da3"), golden("da3")
    mixed = OpenVinoBackend(export.folder, precision="mixed", threads=1)
    has_bf16 = "BF16" in shared_core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
    assert f"precision:mixed({'bf16' if has_bf16 else 'f32'}/f32)" in mixed.info.accelerations
    mapped = mixed.map(case.images[:3])
    assert str(mapped.cache.dtype) == "torch.float32"
    deviation = np.abs(mixed.track(case.images[3], mapped.cache).pose - case.query_pose).max()
    assert deviation < 0.05  # bf16 encoder on random weights (bf16's bound above)
    mixed.close()


def test_mixed_is_refused_outside_openvino(tmp_path: Path) -> None:
    from kvtracker_sdk.runs.backends import open_backend

    for kind in ("torch", "onnx"):
        with pytest.raises(ConfigError, match="OpenVINO's per-graph precision"):
            open_backend(kind, tmp_path / "absent.safetensors", dtype="mixed")


def test_requests_are_per_thread(runtimes: Runtimes) -> None:
    """A tracker maps on a worker while it tracks: both passes run the encoder at once."""
    query, cache = runtimes.golden.images[3], runtimes.openvino_map.cache
    expected = runtimes.openvino.track(query, cache).pose
    start = threading.Barrier(3, timeout=60)
    poses: list[np.ndarray] = []
    errors: list[BaseException] = []

    def work() -> None:
        start.wait()
        try:
            for _ in range(4):
                runtimes.openvino.map(runtimes.golden.images[:1])
                poses.append(runtimes.openvino.track(query, cache).pose)
        except BaseException as exc:  # reported below, with the thread's error
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(2)]
    for thread in threads:
        thread.start()
    start.wait()
    for thread in threads:
        thread.join(timeout=120)
    assert errors == [] and len(poses) == 8
    for pose in poses:
        np.testing.assert_array_equal(pose, expected)


# ---------------------------------------------------------------- refusals (Pi3 export only)
@pytest.fixture(scope="module")
def pi3_folder(onnx_exports: Callable[[str], OnnxExport]) -> Path:
    dev_dependency("openvino")
    return onnx_exports("pi3").folder


def test_bad_settings_raise_typed_errors(pi3_folder: Path) -> None:
    with pytest.raises(ConfigError, match="unknown OpenVINO device"):
        OpenVinoBackend(pi3_folder, device="tpu")
    with pytest.raises(MissingDependencyError, match="no GPU.9 device"):
        OpenVinoBackend(pi3_folder, device="gpu:9")
    with pytest.raises(ConfigError, match="unknown precision"):
        OpenVinoBackend(pi3_folder, precision="int4")
    with pytest.raises(ConfigError, match="threads"):
        OpenVinoBackend(pi3_folder, threads=0)
    with pytest.raises(ModelError, match="not an ONNX export"):
        OpenVinoBackend.from_pretrained(shared_path("golden", "pi3", "weights.safetensors"))


def test_without_openvino_the_error_names_the_extra(
    pi3_folder: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "openvino", None)  # import openvino raises ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install -e \"\.\[openvino\]\""):
        OpenVinoBackend(pi3_folder)


def test_changed_weights_are_refused_before_openvino_reads_them(
    pi3_folder: Path, tmp_path: Path
) -> None:
    copied = Path(shutil.copytree(pi3_folder, tmp_path / "export"))
    weights = np.fromfile(copied / WEIGHTS_NAME, dtype=np.float32)
    (weights * np.float32(1.5)).tofile(copied / WEIGHTS_NAME)
    with pytest.raises(ModelError, match=r"\['weights.bin'\] changed since the export"):
        OpenVinoBackend(copied)


def test_a_checkpoint_is_exported_once_and_served(
    pi3_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kvtracker_sdk.export_onnx import reuse

    exports: list[Path] = []
    served: list[tuple[Path, dict[str, object]]] = []

    def export(model: object, folder: Path, **options: object) -> None:  # the real one: 30 s
        exports.append(folder)
        shutil.copytree(pi3_folder, folder, dirs_exist_ok=True)

    def backend(folder: Path, **options: object) -> str:  # compiling is tested above
        served.append((folder, options))
        return "served"

    monkeypatch.setattr(reuse, "export_model", export)
    monkeypatch.setattr(reuse, "OpenVinoBackend", backend)
    weights = shared_path("golden", "pi3", "weights.safetensors")
    for _ in range(2):
        assert reuse.openvino_backend(weights, cache_dir=tmp_path, precision="bfloat16") == "served"
    assert len(exports) == 1 and exports[0].parent == tmp_path  # exported once
    options = {"device": "cpu", "precision": "bfloat16", "threads": None, "static_shapes": None}
    assert served == [(exports[0], options)] * 2
    assert reuse.openvino_backend(exports[0], threads=1) == "served"  # a folder is served as is
    assert served[-1] == (exports[0], {**options, "precision": "float32", "threads": 1})
