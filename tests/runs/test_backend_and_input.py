"""``open_backend`` / ``BackendSpec`` refuse what no runtime takes; ``open_input`` gives each kind
of input its camera; the eval-many manifest names a backend per config."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.io.sources.camera_files import DATASET_CAMERAS
from kvtracker_sdk.io.sources.live_sources import IterableSource
from kvtracker_sdk.runs import BackendSpec, open_backend, open_input
from kvtracker_sdk.scale import load_manifest
from tests.helpers import shared_path


@pytest.mark.parametrize(("kind", "dtype", "options", "message"), [
    ("tensorrt", "float32", None, "tensorrt"),
    ("torch", "float16", None, "float16"),
    ("onnx", "bfloat16", None, "drop --dtype"),
    ("torch", "float32", {"providers": ["CPUExecutionProvider"]}, "takes no option"),
    ("openvino", "float32", {"attention": "sdpa"}, "takes no option"),
])
def test_open_backend_refuses_what_the_runtime_does_not_take(
    kind: str, dtype: str, options: dict[str, object] | None, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        open_backend(kind, "never-read.safetensors", dtype=dtype, options=options)


def test_a_backend_spec_is_plain_data_with_a_label() -> None:
    spec = BackendSpec.of({"kind": "openvino", "weights": "x/", "dtype": "bfloat16",
                           "options": {"static_shapes": True}})
    assert spec.label() == "openvino/bfloat16"
    assert BackendSpec.model_validate_json(spec.model_dump_json()) == spec
    with pytest.raises(ConfigError, match="kind"):
        BackendSpec.of({"kind": "nope"})


def test_a_tum_folder_comes_with_its_published_camera_unless_one_is_given(tmp_path: Path) -> None:
    tum = shared_path("data", "tum_fr2_desk")
    run_input = open_input(tum)
    assert run_input.camera == DATASET_CAMERAS["tum_fr2"] and run_input.camera.has_distortion
    assert run_input.ground_truth is not None and not run_input.live
    file = tmp_path / "camera.json"
    file.write_text(json.dumps({"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5,
                                "width": 640, "height": 480}))
    assert open_input(tum, camera=file).camera.fx == 500.0  # type: ignore[union-attr]


def test_an_iterable_of_images_is_a_source_without_a_camera() -> None:
    images = [np.zeros((28, 28, 3), np.uint8)] * 3
    run_input = open_input([(image, 0.1 * k) for k, image in enumerate(images)])
    assert isinstance(run_input.source, IterableSource) and run_input.camera is None
    assert [f.timestamp for f in run_input.source] == [0.0, 0.1, 0.2]


def test_a_manifest_config_names_its_backend_and_inherits_the_model_weights(tmp_path: Path) -> None:
    document = {
        "model": {"weights": "pi3.safetensors"},
        "configs": {"torch": {"resolution": 224},
                    "onnx": {"resolution": 224, "backend": {"kind": "onnx", "weights": "x_onnx"}},
                    "ov": {"backend": {"kind": "openvino", "dtype": "bfloat16"}}},
        "sequences": [{"name": "real", "source": "seq", "camera": "cam.yaml"}],
    }
    path = tmp_path / "m.json"
    path.write_text(json.dumps(document))
    manifest = load_manifest(path)
    base = tmp_path.resolve()
    specs = {name: manifest.backend_spec(name) for name in manifest.configs}
    assert specs["torch"] == manifest.model
    assert specs["onnx"] == BackendSpec(kind="onnx", weights=str(base / "x_onnx"))
    assert specs["ov"] == BackendSpec(kind="openvino", weights=str(base / "pi3.safetensors"),
                                      dtype="bfloat16")
    assert manifest.tracker_config("onnx").resolution == 224  # "backend" is not a config field
    assert manifest.sequences[0].camera == base / "cam.yaml"
    document["configs"]["bad"] = {"backend": {"kind": "onnx", "dtype": "float16"}}
    path.write_text(json.dumps(document))
    with pytest.raises(ConfigError, match="float16"):
        load_manifest(path)
