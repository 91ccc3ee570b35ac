"""The ``eval-many`` manifest: which sequences, which configurations, which backends.

A JSON or YAML file; relative paths are resolved against the manifest's folder::

    {
      "model": {"weights": "pi3/model.safetensors"},      # loaded once per worker (a path)
      "configs": {
        "default": {},
        "d224": {"resolution": 224},
        "onnx": {"backend": {"kind": "onnx", "weights": "pi3_onnx/"}},
        "ov_bf16": {"backend": {"kind": "openvino", "weights": "pi3_onnx/", "dtype": "bfloat16"}}
      },
      "sequences": [
        {"name": "fr2_desk", "source": "data/fr2_desk", "ground_truth": "data/fr2_desk/gt.txt"},
        {"name": "calibrated", "source": "data/video.mp4", "camera": "data/camera.yaml", ...},
        {"name": "sim_orbit", "simulated": {"orbit_frames": 600, "seed": 1}}
      ]
    }

``model`` is a backend (``runs.backends.BackendSpec``: ``kind`` torch | onnx | openvino,
``weights``, ``dtype``, ``device``, ``threads``, ``options``; PyTorch by default). A config's
``backend`` names another one for that config (its ``weights`` default to the model's); the rest
of a config is ``TrackerConfig`` fields. Each worker opens each backend at most once.

A *real* sequence is any source ``kvtracker track`` reads (video, image folder, TUM or 7-Scenes
folder) with a ground-truth trajectory (given, or shipped by the source) and its camera (an
intrinsics file given as ``camera``, or the one the dataset publishes). A *simulated* sequence
drives ``SimulatedBackend`` over a ground-truth trajectory (a TUM file or a generated orbit): it
needs no weights. Every sequence runs once per configuration.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import ConfigError, install_command
from kvtracker_sdk.runs.backends import BackendSpec

__all__ = ["EvalManifest", "ModelSpec", "SequenceSpec", "SimulatedSpec", "load_manifest"]

_MAX_MANIFEST_BYTES = 1 << 20  # a manifest lists sequences; anything larger is not one


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# The network real sequences run on: weights the workers share by path (never shipped through a
# task queue or an object store: each worker loads them once). The name is kept for manifests'
# readers; it is the library's backend spec.
ModelSpec = BackendSpec
_BACKEND_KEY = "backend"  # in a config: its backend; every other key is a TrackerConfig field


class SimulatedSpec(_Strict):
    """A simulated camera: ``ground_truth`` (TUM file) or a generated orbit of ``orbit_frames``."""

    ground_truth: Path | None = None
    frames: int | None = Field(default=None, ge=1)  # first N poses of the ground truth
    orbit_frames: int | None = Field(default=None, ge=2)
    orbit_turns: float = Field(default=1.0, gt=0)
    size: tuple[int, int] = (196, 252)  # rendered frame HxW (Pi3's model size at d=224: no resize)
    noise_cm: float = Field(default=1.0, ge=0)
    noise_deg: float = Field(default=0.3, ge=0)
    loss: tuple[int, int] | None = None  # frames [start, stop) with the camera covered
    seed: int = 0

    @model_validator(mode="after")
    def _one_trajectory(self) -> SimulatedSpec:
        if (self.ground_truth is None) == (self.orbit_frames is None):
            raise ValueError("give exactly one of ground_truth and orbit_frames")
        return self


class SequenceSpec(_Strict):
    """One sequence: a real ``source`` with its ``ground_truth``, or a ``simulated`` camera."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    source: Path | None = None
    ground_truth: Path | None = None
    camera: Path | None = None  # intrinsics file; None: the dataset's published camera, if any
    frames: int | None = Field(default=None, ge=1)  # first N frames of the source
    simulated: SimulatedSpec | None = None

    @model_validator(mode="after")
    def _real_or_simulated(self) -> SequenceSpec:
        if (self.source is None) == (self.simulated is None):
            raise ValueError("give exactly one of source and simulated")
        return self


def _default_configs() -> dict[str, dict[str, Any]]:
    return {"default": {}}


class EvalManifest(_Strict):
    """Sequences x configurations (and the model, if any sequence is real)."""

    model: ModelSpec | None = None
    configs: dict[str, dict[str, Any]] = Field(default_factory=_default_configs)
    sequences: tuple[SequenceSpec, ...] = Field(min_length=1)
    # torch threads per task: results are bit-identical whatever engine runs them only when
    # every run uses the same thread count (reductions split differently otherwise)
    threads_per_task: int = Field(default=1, ge=1)

    @model_validator(mode="after")
    def _checked(self) -> EvalManifest:
        names = [s.name for s in self.sequences]
        if len(set(names)) != len(names):
            raise ValueError(f"sequence names must be unique, got {names}")
        real = any(s.source is not None for s in self.sequences)
        for name in self.configs:
            if not name or not name.replace("_", "").replace("-", "").isalnum():
                raise ValueError(f"config name {name!r}: letters, digits, '-' and '_' only")
            self.tracker_config(name)  # ConfigError now, not in a worker later
            if real and self.backend_spec(name) is None:
                raise ValueError("real sequences need a model (model.weights) or a backend in "
                                 f"config {name!r}")
        return self

    def tracker_config(self, name: str) -> TrackerConfig:
        fields = {k: v for k, v in self.configs[name].items() if k != _BACKEND_KEY}
        return TrackerConfig.from_dict(fields)

    def backend_spec(self, name: str) -> BackendSpec | None:
        """The backend of config ``name``: its own ``backend``, else the manifest's model."""
        own = self.configs[name].get(_BACKEND_KEY)
        if own is None:
            return self.model
        if not isinstance(own, dict):
            raise ValueError(f"config {name!r}: backend must be a mapping, got {own!r}")
        if "weights" not in own and self.model is not None:
            own = {**own, "weights": self.model.weights}
        return BackendSpec.of(own)

    def tasks(self) -> list[tuple[SequenceSpec, str]]:
        """Every (sequence, config name) pair, in manifest order."""
        return [(s, c) for s in self.sequences for c in self.configs]


def _resolve(document: Any, base: Path) -> Any:
    """Relative paths in the known path fields, made absolute against ``base``."""
    for sequence in document.get("sequences", []) if isinstance(document, dict) else []:
        if not isinstance(sequence, dict):
            continue
        for key in ("source", "ground_truth", "camera"):
            if isinstance(sequence.get(key), str):
                sequence[key] = str(base / sequence[key])
        simulated = sequence.get("simulated")
        if isinstance(simulated, dict) and isinstance(simulated.get("ground_truth"), str):
            simulated["ground_truth"] = str(base / simulated["ground_truth"])
    model = document.get("model") if isinstance(document, dict) else None
    configs = document.get("configs") if isinstance(document, dict) else None
    backends = [c.get(_BACKEND_KEY) for c in configs.values() if isinstance(c, dict)] \
        if isinstance(configs, dict) else []
    for spec in (model, *backends):
        if isinstance(spec, dict) and isinstance(spec.get("weights"), str):
            spec["weights"] = str(base / spec["weights"])
    return document


def load_manifest(path: str | Path) -> EvalManifest:
    """Read and validate a manifest (JSON, or YAML if PyYAML is installed). ConfigError if bad."""
    target = Path(path)
    try:
        if not target.is_file():
            raise ConfigError(f"manifest {target}: not a regular file")
        if target.stat().st_size > _MAX_MANIFEST_BYTES:
            raise ConfigError(f"manifest {target}: larger than {_MAX_MANIFEST_BYTES} bytes")
        text = target.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"manifest {target}: cannot read it ({exc})") from exc
    try:
        if target.suffix.lower() in (".yaml", ".yml"):
            document = _load_yaml(target, text)
        else:
            document = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ConfigError(f"manifest {target}: not valid JSON/YAML ({exc})") from exc
    try:
        return EvalManifest.model_validate(_resolve(document, target.parent.resolve()))
    except ValidationError as exc:
        raise ConfigError(
            f"manifest {target} is invalid:\n" + "\n".join(_field_problems(exc)), hint=_HINT
        ) from exc


_HINT = ("see `kvtracker eval-many --help` and the example manifests in examples/manifests/ "
         "(every sequence needs a name, and a source or a simulated camera)")


def _field_problems(error: ValidationError) -> list[str]:
    """One plain line per invalid field, e.g. ``sequences[0].name: Field required``."""
    problems = error.errors(include_url=False)
    lines = []
    for problem in problems:
        inner = [p for p in problems if p["loc"][: len(problem["loc"])] == problem["loc"]]
        if problem["type"] == "too_short" and len(inner) > 1:
            continue  # "no sequences left" only because a sequence itself is invalid
        where = ""
        for part in problem["loc"]:
            where += f"[{part}]" if isinstance(part, int) else (f".{part}" if where else str(part))
        message = str(problem["msg"]).removeprefix("Value error, ")
        lines.append(f"{where or 'manifest'}: {message}")
    return lines


def _load_yaml(target: Path, text: str) -> Any:
    try:
        import yaml  # optional: PyYAML
    except ImportError as exc:
        raise ConfigError(f"manifest {target}: YAML needs PyYAML ({install_command('yaml')})") from exc
    try:
        return yaml.safe_load(text)  # safe_load: never constructs Python objects
    except yaml.YAMLError as exc:
        raise ConfigError(f"manifest {target}: not valid YAML ({exc})") from exc
