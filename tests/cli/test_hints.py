"""Every error's hint fits that error: a camera gets camera advice, a missing [ros] extra the
[ros] install line, a bad frame no list of input kinds; a source that cannot be opened is its own
exit code and leaves no output behind."""

from __future__ import annotations

import inspect
import os
import sys
from pathlib import Path

import pytest
import tomllib

from kvtracker_sdk import errors
from kvtracker_sdk.cli.failures import EXIT_CODES, ExitCode, exit_code_for
from kvtracker_sdk.io.sources import live_sources
from tests.cli.invoke import invoke
from tests.io.fake_capture import FakeCapture

INPUT_KINDS = "INPUT is a video file"

# error -> (words its hint must contain, words it must not contain)
CASES: dict[type[errors.KVTrackerError], tuple[errors.KVTrackerError, list[str], list[str]]] = {
    errors.KVTrackerError: (errors.KVTrackerError("x"), ["-v"], []),
    errors.ConfigError: (errors.ConfigError("x"), ["--help"], []),
    errors.InputError: (errors.InputError("x"), ["frames"], [INPUT_KINDS]),
    errors.ImageShapeError: (errors.ImageShapeError("x"), ["HxWx3", "size"], [INPUT_KINDS]),
    errors.ImageDtypeError: (errors.ImageDtypeError("x"), ["frames"], [INPUT_KINDS]),
    errors.NonFiniteImageError: (errors.NonFiniteImageError("x"), ["frames"], [INPUT_KINDS]),
    errors.MaskError: (errors.MaskError("x"), ["mask"], [INPUT_KINDS]),
    errors.DepthError: (errors.DepthError("x"), ["--depth", "--depth-scale"], [INPUT_KINDS]),
    errors.GravityError: (errors.GravityError("x"), ["gravity", "camera frame"], [INPUT_KINDS]),
    errors.BBoxError: (errors.BBoxError("x"), ["--bbox", "x0,y0,x1,y1"], [INPUT_KINDS]),
    errors.ResolutionChangedError: (errors.ResolutionChangedError("x"), ["size"],
                                    [INPUT_KINDS]),
    errors.SourceError: (errors.SourceError("x"), [INPUT_KINDS], []),
    errors.SourceOpenError: (errors.SourceOpenError("x", kind="camera", target="3"),
                             ["camera index", "/dev/video"], [INPUT_KINDS, "URL"]),
    errors.FrameDecodeError: (errors.FrameDecodeError("x"), ["--on-bad-frame skip"],
                              [INPUT_KINDS]),
    errors.TrajectoryError: (errors.TrajectoryError("x"), ["TUM", "KITTI"], []),
    errors.IntrinsicsError: (errors.IntrinsicsError("x"), ["--camera", "--intrinsics"],
                             [INPUT_KINDS]),
    errors.EvaluationError: (errors.EvaluationError("x"), ["--max-diff"], []),
    errors.StateError: (errors.StateError("x"), ["-v"], []),
    errors.IllegalTransitionError: (errors.IllegalTransitionError("x"), ["-v"], []),
    errors.ModelError: (errors.ModelError("x"), ["--weights"], []),
    errors.WeightsNotFoundError: (errors.WeightsNotFoundError("x"), ["--weights", "demo"], []),
    errors.CheckpointMismatchError: (errors.CheckpointMismatchError("x"), ["--weights"], []),
    errors.CacheError: (errors.CacheError("x"), ["-v"], []),
    errors.OutputError: (errors.OutputError("x"), ["folder"], []),
    errors.BackendError: (errors.BackendError("x"), ["-v"], []),
    errors.CompileError: (errors.CompileError("x"), ["-v"], []),
    errors.BackendMismatchError: (errors.BackendMismatchError("x"), ["same weights"], []),
    errors.MappingFailedError: (errors.MappingFailedError("x"), ["-v"], []),
    errors.TrackingFailedError: (errors.TrackingFailedError("x"), ["-v"], []),
    errors.MissingDependencyError: (errors.MissingDependencyError.for_extra("ros", "x"),
                                    ['pip install -e ".[ros]"', "rosbags"], ["[viz]"]),
    errors.MapError: (errors.MapError("x"), [".kvmap"], ["map info"]),
    errors.MapFormatError: (errors.MapFormatError("x"), [".kvmap"], ["map info"]),
    errors.MapVersionError: (errors.MapVersionError("x"), ["upgrade"], ["map info"]),
    errors.MapModelMismatchError: (errors.MapModelMismatchError("x"), ["weights"],
                                   ["map info"]),
    errors.MapCorruptedError: (errors.MapCorruptedError("x"), ["truncated"], ["map info"]),
    errors.MapPreprocessingError: (errors.MapPreprocessingError("x"), ["--rebuild-map"],
                                   ["map info"]),
    errors.MapIOError: (errors.MapIOError("x"), ["exists", "readable"], ["map info"]),
}


def test_every_error_class_has_a_hint_case() -> None:
    classes = {c for _, c in inspect.getmembers(errors, inspect.isclass)
               if issubclass(c, errors.KVTrackerError)}
    assert classes == set(CASES)


@pytest.mark.parametrize("kind", sorted(CASES, key=lambda c: c.__name__), ids=lambda c: c.__name__)
def test_the_hint_fits_the_error(kind: type[errors.KVTrackerError]) -> None:
    error, wanted, unwanted = CASES[kind]
    _, hint = exit_code_for(error)
    for word in wanted:
        assert word in hint, f"{kind.__name__}: {word!r} not in {hint!r}"
    for word in unwanted:
        assert word not in hint, f"{kind.__name__}: {word!r} in {hint!r}"


@pytest.mark.parametrize(
    ("kind", "wanted", "unwanted"),
    [
        ("camera", ["camera index", "/dev/video"], ["URL", INPUT_KINDS]),
        ("stream", ["URL", "ffplay"], ["/dev/video", INPUT_KINDS]),
        ("video", ["ffmpeg", "folder of its frames"], ["/dev/video"]),
        ("path", ["check the path", INPUT_KINDS], ["/dev/video"]),
    ],
)
def test_a_source_that_cannot_be_opened_gets_advice_for_its_kind(
    kind: str, wanted: list[str], unwanted: list[str]
) -> None:
    code, hint = exit_code_for(errors.SourceOpenError("x", kind=kind, target="t"))
    assert code is ExitCode.SOURCE and "cannot be opened" in EXIT_CODES[ExitCode.SOURCE]
    assert all(w in hint for w in wanted) and not any(u in hint for u in unwanted), hint


def test_an_errors_own_hint_comes_first() -> None:
    own = errors.SourceError("camera file x: not valid JSON", hint="--camera takes a JSON file")
    assert exit_code_for(own) == (ExitCode.INPUT, "--camera takes a JSON file")


def test_the_install_command_lists_each_extras_packages_as_pyproject_does() -> None:
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    extras = pyproject["project"]["optional-dependencies"]
    listed = {name: tuple(packages) for name, packages in extras.items() if name != "dev"}
    assert listed == errors.EXTRA_PACKAGES
    command = errors.install_command("ros")
    assert 'pip install -e ".[ros]"' in command and "'rosbags>=0.10'" in command
    assert "kvtracker-sdk[" not in command  # the package is not on PyPI


def test_no_message_tells_users_to_install_from_pypi() -> None:
    package = Path(errors.__file__).parent
    offenders = [str(p) for p in package.rglob("*.py") if "pip install 'kvtracker-sdk[" in
                 p.read_text() or 'pip install "kvtracker-sdk[' in p.read_text()]
    assert offenders == []


def _fake_opencv(opened: bool) -> object:
    """A capture that, like OpenCV's, writes its complaint straight to descriptor 2."""

    def open_capture(target: object) -> FakeCapture:
        if not opened:
            os.write(2, f"[ WARN:0@0.010] global cap_v4l.cpp:914 open VIDEOIO(V4L2:/dev/video"
                        f"{target}): can't open camera by index\n".encode())
        return FakeCapture([], opened=opened)

    return open_capture


def test_a_camera_that_cannot_be_opened_is_exit_11_with_camera_advice_and_no_outputs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)  # "7" must not name a file or folder here
    monkeypatch.setattr(live_sources, "_video_capture", _fake_opencv(opened=False))
    result = invoke("track", "7", "--out", tmp_path / "out", "--weights", "nowhere")
    assert result.exit_code == ExitCode.SOURCE, result.output
    assert "cannot open camera 7" in result.stderr and "can't open camera by index" in result.stderr
    assert "camera index" in result.stderr.splitlines()[-1]  # the hint
    assert "0 frames" not in result.stdout + result.stderr  # no run summary of nothing
    assert not (tmp_path / "out").exists()
    sys.stderr.flush()
    assert "[ WARN" not in capfd.readouterr().err  # OpenCV's line went to the log, not the tty


def test_a_missing_input_path_is_exit_11_and_leaves_no_outputs(tmp_path: Path) -> None:
    result = invoke("track", tmp_path / "nowhere.mp4", "--out", tmp_path / "out")
    assert result.exit_code == ExitCode.SOURCE, result.output
    assert "does not exist" in result.stderr and "check the path" in result.stderr
    assert not (tmp_path / "out").exists()


def test_bad_weights_leave_no_empty_out_folder(tmp_path: Path, simulated_frames: Path) -> None:
    out = tmp_path / "a" / "b"  # two folders the checks create, both removed again
    result = invoke("track", simulated_frames, "--out", out, "--weights", tmp_path / "x.safetensors")
    assert result.exit_code == ExitCode.WEIGHTS, result.output
    assert not (tmp_path / "a").exists()


def test_a_save_map_into_a_missing_folder_leaves_no_empty_out(
    tmp_path: Path, simulated_frames: Path
) -> None:
    result = invoke("track", simulated_frames, "--out", tmp_path / "out",
                    "--save-map", tmp_path / "missing" / "m.kvmap")
    assert result.exit_code == ExitCode.OUTPUT, result.output
    assert not (tmp_path / "out").exists()


def test_an_existing_out_folder_is_never_removed(tmp_path: Path, simulated_frames: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    result = invoke("track", simulated_frames, "--out", out, "--weights", tmp_path / "x.safetensors")
    assert result.exit_code == ExitCode.WEIGHTS and out.is_dir()


def test_manifest_errors_are_one_plain_line_per_field(tmp_path: Path) -> None:
    manifest = tmp_path / "m.json"
    manifest.write_text('{"sequences": [{"source": "x"}, {"name": "b", "simulated": '
                        '{"orbit_frames": 1}}]}')
    result = invoke("eval-many", manifest, "--out", tmp_path / "out")
    assert result.exit_code == ExitCode.CONFIG, result.output
    lines = result.stderr.splitlines()
    assert lines[1:3] == ["  sequences[0].name: Field required",
                          "  sequences[1].simulated.orbit_frames: Input should be greater than "
                          "or equal to 2"]
    assert "pydantic" not in result.stderr and "https://" not in result.stderr
    assert "examples/manifests" in lines[-1]
