"""Map files: bit-identical round trips (also across processes), header info, model checks."""

from __future__ import annotations

import enum
import json
import os
import subprocess
import sys
from datetime import timezone
from pathlib import Path

import pytest
import torch

from kvtracker_sdk import __version__
from kvtracker_sdk.cache import CacheLayout
from kvtracker_sdk.errors import (
    BackendMismatchError,
    MapCorruptedError,
    MapError,
    MapFormatError,
    MapIOError,
    MapModelMismatchError,
    MapVersionError,
)
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from tests.helpers import PROJECT_ROOT
from tests.io.map_factory import (
    TRACKER_CONFIG,
    backend_info,
    make_map,
    map_digest,
    maps_equal,
    rewrite_header,
    split_file,
)

DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


def saved(
    tmp_path: Path, name: str = "scan.kvmap", dtype: str = "float32", **map_args: object
) -> Path:
    path = tmp_path / name
    keyframe_map = make_map(dtype=DTYPES[dtype], **map_args)  # type: ignore[arg-type]
    save_map(
        path, keyframe_map, backend_info=backend_info(dtype=dtype),
        tracker_config_json=TRACKER_CONFIG, mode="object",
    )  # fmt: skip
    return path


_CHILD = """
import json, sys
from kvtracker_sdk.io.map_file.map_file import load_map
from tests.io.map_factory import map_digest
print(json.dumps({p: map_digest(load_map(p).keyframe_map) for p in sys.argv[1:]}))
"""


def test_round_trip_in_a_new_process_is_bit_identical(tmp_path: Path) -> None:
    originals = {}
    for dtype in ("float32", "bfloat16"):
        path = saved(tmp_path, f"{dtype}.kvmap", dtype)
        originals[str(path)] = make_map(dtype=DTYPES[dtype])  # same seed: the saved content
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, *originals],
        cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    loaded = json.loads(out.stdout)
    for path, original in originals.items():
        # JSON round trip of the reference digest: tuples become lists like the child's
        assert loaded[path] == json.loads(json.dumps(map_digest(original))), path


@pytest.mark.parametrize("dtype", sorted(DTYPES))
def test_round_trip_keeps_every_array_and_scalar(tmp_path: Path, dtype: str) -> None:
    path = saved(tmp_path, dtype=dtype)
    loaded = load_map(path)
    assert maps_equal(loaded.keyframe_map, make_map(dtype=DTYPES[dtype]))
    assert loaded.keyframe_map.cache.dtype == DTYPES[dtype]
    assert loaded.info.tracker_config == json.loads(TRACKER_CONFIG) and loaded.mode == "object"
    assert os.listdir(tmp_path) == [path.name]  # no temporary file left behind


def test_header_info_describes_the_map(tmp_path: Path) -> None:
    path = saved(tmp_path, dtype="bfloat16", num_keyframes=4, generation=7)
    info = read_map_info(path)
    backend = backend_info(dtype="bfloat16")
    assert info.fingerprint == backend.fingerprint and info.backend == backend
    assert info.layout == backend.layout and info.dtype == "bfloat16"
    assert info.resolution == (28, 42) and info.tokens_per_frame == 5 + 2 * 3
    assert info.keyframe_ids == (1, 4, 7, 10) == info.cache_keyframe_ids
    assert info.generation == 7 and info.mode == "object" and info.sdk_version == __version__
    assert (
        info.created_utc.tzinfo is not None
        and info.created_utc.utcoffset() == timezone.utc.utcoffset(None)
    )
    assert info.file_size == path.stat().st_size
    assert info.cache_nbytes == 2 * 4 * 2 * (4 * 11) * 8 * 2
    assert json.loads(info.tracker_config_json) == json.loads(TRACKER_CONFIG)
    assert dict(info.user_metadata) == {"scene": "desk"}


def test_save_returns_the_header_it_wrote(tmp_path: Path) -> None:
    path = tmp_path / "m.kvmap"
    written = save_map(
        path, make_map(), backend_info=backend_info(), tracker_config_json="{}", mode="scene"
    )
    read = read_map_info(path)
    assert dict(written.tensor_sha256) == dict(read.tensor_sha256)
    assert (written.created_utc, written.file_size, written.mode) == (
        read.created_utc,
        read.file_size,
        "scene",
    )


def test_mode_enum_is_stored_as_its_value(tmp_path: Path) -> None:
    class Mode(str, enum.Enum):
        OBJECT = "object"

    path = tmp_path / "m.kvmap"
    save_map(
        path, make_map(), backend_info=backend_info(), tracker_config_json="{}", mode=Mode.OBJECT
    )
    assert read_map_info(path).mode == "object"


def test_header_info_does_not_read_tensor_data(tmp_path: Path) -> None:
    path = saved(tmp_path)
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF  # inside the last tensor's bytes
    path.write_bytes(bytes(data))
    assert read_map_info(path).num_keyframes == 3  # header alone: still fine
    with pytest.raises(MapCorruptedError, match="checksum mismatch"):
        load_map(path)
    assert load_map(path, verify_checksums=False).info.num_keyframes == 3  # checks were skipped


def test_a_flipped_kv_byte_is_named_in_the_error(tmp_path: Path) -> None:
    path = saved(tmp_path)
    header, body = split_file(path.read_bytes())
    begin, _ = header["layers.2.value"]["data_offsets"]
    data = bytearray(path.read_bytes())
    data[len(data) - len(body) + begin + 5] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(MapCorruptedError, match=r"layers\.2\.value"):
        load_map(path)


@pytest.mark.parametrize(
    "override",
    [
        {"family": "da3"},
        {"config_hash": "another-config"},
        {"weights_fingerprint": "other-weights"},
        {"layout": CacheLayout((1, 3, 5, 7), 4, 8)},
        {"patch_size": 16},
    ],
    ids=["family", "config", "weights", "layout", "patch"],
)
def test_another_model_is_refused_naming_both(tmp_path: Path, override: dict[str, object]) -> None:
    path = saved(tmp_path)
    other = backend_info(**override)
    with pytest.raises(MapModelMismatchError) as caught:
        load_map(path, expected_backend=other)
    message = str(caught.value)
    assert backend_info().fingerprint in message and other.fingerprint in message
    ((field, value),) = override.items()
    assert str(value) in message and str(getattr(backend_info(), field)) in message


def test_another_resolution_is_refused_naming_both(tmp_path: Path) -> None:
    path = saved(tmp_path)
    with pytest.raises(MapModelMismatchError, match=r"\(28, 42\) vs \(42, 42\)"):
        load_map(path, expected_backend=backend_info(), expected_resolution=(42, 42))


def test_same_fingerprint_on_another_runtime_loads(tmp_path: Path) -> None:
    path = saved(tmp_path)
    onnx = backend_info(backend="onnx", model="pi3-test-onnx", accelerations=("cuda-graphs",))
    assert onnx.fingerprint == backend_info().fingerprint
    loaded = load_map(path, expected_backend=onnx, expected_resolution=(28, 42))
    assert maps_equal(loaded.keyframe_map, make_map())


def test_cache_comes_back_in_the_expected_backends_dtype(tmp_path: Path) -> None:
    path = saved(tmp_path, dtype="float32")
    loaded = load_map(path, expected_backend=backend_info(dtype="bfloat16"))
    cache = loaded.keyframe_map.cache
    assert cache.dtype == torch.bfloat16
    assert torch.equal(cache.keys(0), make_map().cache.keys(0).to(torch.bfloat16))


@pytest.mark.parametrize("version", ["0", "5", "17"])
def test_unsupported_versions_name_both_versions(tmp_path: Path, version: str) -> None:
    path = saved(tmp_path)
    path.write_bytes(
        rewrite_header(
            path.read_bytes(), lambda h: h["__metadata__"].update(format_version=version)
        )
    )
    with pytest.raises(MapVersionError) as caught:
        read_map_info(path)
    assert f"version {version} is too {'old' if version == '0' else 'new'}" in str(caught.value)
    assert "1 to 4" in str(caught.value)  # this SDK's range


def test_an_edited_header_field_is_caught_by_the_header_checksum(tmp_path: Path) -> None:
    path = saved(tmp_path)
    original = path.read_bytes()

    def edit(header: dict) -> None:
        header["__metadata__"]["tracker_config"] = TRACKER_CONFIG.replace("10.0", "90.0")

    path.write_bytes(rewrite_header(original, edit, reseal=False))
    with pytest.raises(MapCorruptedError, match="header checksum"):
        read_map_info(path)
    path.write_bytes(rewrite_header(original, edit))  # re-sealed: the digest was the only guard
    assert "90.0" in read_map_info(path).tracker_config_json


def test_missing_file_and_directory_are_typed_errors(tmp_path: Path) -> None:
    with pytest.raises(MapIOError) as caught:
        load_map(tmp_path / "absent.kvmap")
    assert isinstance(caught.value, OSError) and isinstance(caught.value, MapError)
    (tmp_path / "dir.kvmap").mkdir()
    with pytest.raises(MapFormatError, match="not a regular file"):
        read_map_info(tmp_path / "dir.kvmap")


def test_saving_a_cache_of_another_layout_is_refused(tmp_path: Path) -> None:
    other = backend_info(layout=CacheLayout((0, 1, 2, 3), 2, 8))
    with pytest.raises(BackendMismatchError, match="layout"):
        save_map(
            tmp_path / "m.kvmap",
            make_map(),
            backend_info=other,
            tracker_config_json="{}",
            mode="scene",
        )
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("config", ["not json", "[1, 2]", '{"a": NaN}'])
def test_saving_a_malformed_tracker_config_is_refused(tmp_path: Path, config: str) -> None:
    with pytest.raises(MapFormatError, match="tracker config"):
        save_map(
            tmp_path / "m.kvmap",
            make_map(),
            backend_info=backend_info(),
            tracker_config_json=config,
            mode="scene",
        )
    assert not list(tmp_path.iterdir())


def test_saved_map_permissions_follow_the_umask_like_a_plain_open(tmp_path: Path) -> None:
    path = saved(tmp_path)
    (tmp_path / "plain.txt").write_text("x")
    assert path.stat().st_mode & 0o777 == (tmp_path / "plain.txt").stat().st_mode & 0o777
