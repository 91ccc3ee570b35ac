"""eval-many manifests and ground truths as a careless or hostile user writes them (seeded,
in-process, ~1 s), and output folders that stay inside ``--out``.

Every manifest holds something absurd and gives a ``ConfigError`` naming the field; every hostile
ground truth a ``TrajectoryError`` at once (a FIFO used to hang, two poses 1e8 s apart asked for
22 GiB, ``/dev/zero`` for 3.5 GB). ``benchmarks/fuzz_inputs.py`` runs more, each in a fresh
process under a 3 GB address-space limit.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from kvtracker_sdk.backends.simulated_scene import GroundTruth, orbit
from kvtracker_sdk.errors import ConfigError, KVTrackerError, TrajectoryError
from kvtracker_sdk.io.files.trajectory import read_trajectory
from kvtracker_sdk.scale.manifest import SequenceSpec, load_manifest
from kvtracker_sdk.scale.sequence_run import run_sequence
from tests.hostile_inputs import ground_truth_cases, manifest_cases

DEFAULT_CASES = 200


@pytest.fixture(autouse=True)
def no_hang() -> Iterator[None]:
    def fail(*_: object) -> None:
        raise TimeoutError("reading a manifest or ground truth hung")

    previous = signal.signal(signal.SIGALRM, fail)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def test_seeded_hostile_manifests_give_a_config_error_naming_the_field(tmp_path: Path) -> None:
    pytest.importorskip("yaml")
    unnamed, untyped, accepted = [], [], []
    for case in manifest_cases(DEFAULT_CASES, seed=34):
        path = case.make(tmp_path)
        try:
            load_manifest(path)
            accepted.append(case.name)
        except KVTrackerError as exc:
            if not any(field in str(exc) for field in case.fields) or len(str(exc)) > 4000:
                unnamed.append((case.name, str(exc)[:300]))
        except Exception as exc:  # noqa: BLE001 - counting what escapes
            untyped.append((case.name, type(exc).__name__, str(exc)[:100]))
    assert (untyped, unnamed, accepted) == ([], [], [])


@pytest.mark.parametrize(
    ("document", "field"),
    [
        ({"sequences": float("nan")}, "sequences"),
        ({"sequences": [{"name": "..", "simulated": {"orbit_frames": 30}}]}, "name"),
        ({"sequences": [{"name": "o", "simulated": {"orbit_frames": 10**9}}]}, "orbit_frames"),
    ],
)
def test_each_manifest_reported_is_refused_naming_its_field(
    tmp_path: Path, document: dict, field: str
) -> None:
    path = tmp_path / "m.json"
    path.write_text(json.dumps(document))
    with pytest.raises(ConfigError, match=field):
        load_manifest(path)


def test_a_yaml_alias_bomb_manifest_is_refused_quickly(tmp_path: Path) -> None:
    pytest.importorskip("yaml")
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    for i in range(9):
        previous, name = chr(97 + i), chr(98 + i)
        lines.append(f"{name}: &{name} [" + ", ".join([f"*{previous}"] * 9) + "]")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    start = time.perf_counter()
    with pytest.raises(ConfigError, match="alias"):
        load_manifest(path)
    assert time.perf_counter() - start < 2.0


def test_hostile_ground_truths_are_refused_at_once(tmp_path: Path) -> None:
    outcomes = {}
    for name, make in ground_truth_cases():
        path = make(tmp_path)
        for reader in (lambda p: GroundTruth.from_tum(p, rate_hz=30.0), read_trajectory):
            start = time.perf_counter()
            try:
                reader(path)
                outcome = "accepted"
            except TrajectoryError:
                outcome = "refused"
            outcomes[name] = outcomes.get(name, set()) | {outcome}
            assert time.perf_counter() - start < 2.0, name
    # read_trajectory keeps any stamps (it resamples nothing); the simulator's resampling refuses
    assert outcomes.pop("two-lines-1e8-s-apart") == {"refused", "accepted"}
    assert outcomes.pop("backwards-in-time") == {"refused", "accepted"}
    assert all(outcome == {"refused"} for outcome in outcomes.values()), outcomes


def test_the_manifest_frame_limit_is_the_simulators() -> None:
    from kvtracker_sdk.backends.simulated_scene import MAX_FRAMES
    from kvtracker_sdk.scale import manifest

    assert manifest.MAX_FRAMES == MAX_FRAMES


def test_an_orbit_of_a_billion_frames_is_refused_before_anything_is_built() -> None:
    with pytest.raises(TrajectoryError, match="num_frames"):
        orbit(10**9)


@pytest.mark.parametrize("name", ["..", ".", "/etc", "a/b", "a\\b", "../../x", ""])
def test_output_folders_from_user_names_stay_inside_out(tmp_path: Path, name: str) -> None:
    from kvtracker_sdk.scale.sequence_run import output_folder

    out = tmp_path / "out"
    with pytest.raises(ConfigError, match="name"):
        output_folder(out, name, "default")
    with pytest.raises(ConfigError, match="name"):
        output_folder(out, "seq", name)
    # a spec that skipped validation (model_construct) cannot write outside either
    spec = SequenceSpec.model_construct(name=name, source=None, ground_truth=None, frames=None,
                                        simulated=None)
    with pytest.raises(ConfigError):
        run_sequence(spec, "default", None, lambda: None, out)  # type: ignore[arg-type]
    assert not any(tmp_path.iterdir()) or [p.name for p in tmp_path.iterdir()] == ["out"]
    assert output_folder(out, "fr1.desk-2", "d224") == out / "fr1.desk-2" / "d224"
