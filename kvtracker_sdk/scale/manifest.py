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

The file is read with ``user_files`` (regular files only, at most 1 MB, bounded nesting, safe
YAML with alias-bomb protection) and every number is checked against a plausible range (frame
counts up to ``MAX_FRAMES``, rendered sizes, noise, threads): ``ConfigError`` naming the field.
Sequence and config names become folder names under ``--out``: letters, digits, ``_``, ``-``
and ``.``, never ``.`` or ``..`` (``safe_name``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.runs.backends import BackendSpec
from kvtracker_sdk.user_files import load_user_document

__all__ = [
    "MAX_FRAMES",
    "EvalManifest",
    "ModelSpec",
    "SequenceSpec",
    "SimulatedSpec",
    "load_manifest",
    "safe_name",
]

_MAX_MANIFEST_BYTES = 1 << 20  # a manifest lists sequences; anything larger is not one
# backends.simulated_scene.MAX_FRAMES, the frames a simulated camera can number (a test pins the
# two equal): not imported, so that reading a manifest does not load torch
MAX_FRAMES = 224 * 224
_MAX_SEQUENCES = 10_000
_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_MAX_SIDE = 4096  # rendered frame side (px); the networks run at a few hundred
_SEED_MAX = 2**63 - 1  # numpy's generators take a non-negative 64-bit seed


def safe_name(name: object, field: str = "name") -> str:
    """``name`` if it can be one folder name under an output folder: 1-64 letters, digits,
    ``_``, ``-`` or ``.``, and not ``.`` or ``..``; ``ConfigError`` naming ``field`` otherwise.
    (No separator, no absolute path, no parent: a joined path stays inside the folder.)"""
    if not isinstance(name, str) or not _NAME.fullmatch(name) or name in (".", ".."):
        raise ConfigError(
            f"{field} {name!r:.80} must be 1-64 letters, digits, '_', '-' or '.' "
            "(and not '.' or '..'): it names a folder inside --out"
        )
    return name


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
    # first N poses of the ground truth
    frames: int | None = Field(default=None, ge=1, le=MAX_FRAMES, strict=True)
    orbit_frames: int | None = Field(default=None, ge=2, le=MAX_FRAMES, strict=True)
    orbit_turns: float = Field(default=1.0, gt=0, le=1000, allow_inf_nan=False, strict=True)
    # rendered frame HxW (Pi3's model size at d=224: no resize)
    size: tuple[
        Annotated[int, Field(ge=14, le=_MAX_SIDE, strict=True)],
        Annotated[int, Field(ge=14, le=_MAX_SIDE, strict=True)],
    ] = (196, 252)
    noise_cm: float = Field(default=1.0, ge=0, le=1000, allow_inf_nan=False, strict=True)  # up to 10 m
    noise_deg: float = Field(default=0.3, ge=0, le=180, allow_inf_nan=False, strict=True)
    # frames [start, stop) with the camera covered
    loss: tuple[
        Annotated[int, Field(ge=0, le=MAX_FRAMES, strict=True)],
        Annotated[int, Field(ge=0, le=MAX_FRAMES, strict=True)],
    ] | None = None
    seed: int = Field(default=0, ge=0, le=_SEED_MAX, strict=True)

    @model_validator(mode="after")
    def _one_trajectory(self) -> SimulatedSpec:
        if (self.ground_truth is None) == (self.orbit_frames is None):
            raise ValueError("give exactly one of ground_truth and orbit_frames")
        if self.loss is not None and self.loss[0] >= self.loss[1]:
            raise ValueError(f"loss [start, stop) needs start < stop, got {list(self.loss)}")
        return self


class SequenceSpec(_Strict):
    """One sequence: a real ``source`` with its ``ground_truth``, or a ``simulated`` camera."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")  # a folder under --out: safe_name
    source: Path | None = None
    ground_truth: Path | None = None
    camera: Path | None = None  # intrinsics file; None: the dataset's published camera, if any
    # first N frames of the source
    frames: int | None = Field(default=None, ge=1, le=10_000_000, strict=True)
    simulated: SimulatedSpec | None = None

    @field_validator("name")
    @classmethod
    def _folder_name(cls, name: str) -> str:
        try:
            return safe_name(name, "sequence name")
        except ConfigError as exc:
            raise ValueError(str(exc)) from exc

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
    sequences: tuple[SequenceSpec, ...] = Field(min_length=1, max_length=_MAX_SEQUENCES)
    # torch threads per task: results are bit-identical whatever engine runs them only when
    # every run uses the same thread count (reductions split differently otherwise)
    threads_per_task: int = Field(default=1, ge=1, le=1024, strict=True)

    @model_validator(mode="after")
    def _checked(self) -> EvalManifest:
        names = [s.name for s in self.sequences]
        if len(set(names)) != len(names):
            raise ValueError(f"sequence names must be unique, got {names}")
        if not self.configs:
            raise ValueError("configs must name at least one configuration")
        real = any(s.source is not None for s in self.sequences)
        for name in self.configs:
            if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", name):
                raise ValueError(f"config name {name!r:.80}: 1-64 letters, digits, '-' and '_' only")
            try:
                self.tracker_config(name)  # ConfigError now, not in a worker later
                spec = self.backend_spec(name)
            except ConfigError as exc:
                raise ValueError(f"configs.{name}: {exc}") from exc
            if real and spec is None:
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
    """Relative paths in the known path fields, made absolute against ``base``. Fields of the
    wrong type are left as they are, for the schema to name."""
    if not isinstance(document, dict):
        return document
    sequences = document.get("sequences")
    for sequence in sequences if isinstance(sequences, list) else []:
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
    """Read and validate a manifest (JSON, or YAML if PyYAML is installed). ConfigError, naming
    the field, if it is not a regular file, too large, malformed or holds a value out of range."""
    document = load_user_document(path, ConfigError, what="manifest", max_bytes=_MAX_MANIFEST_BYTES)
    target = Path(path)  # load_user_document checked its type
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
    problems = error.errors(include_url=False, include_input=False)[:20]  # never echo values
    lines = []
    for problem in problems:
        inner = [p for p in problems if p["loc"][: len(problem["loc"])] == problem["loc"]]
        if problem["type"] == "too_short" and len(inner) > 1:
            continue  # "no sequences left" only because a sequence itself is invalid
        where = ""
        for part in problem["loc"]:
            where += f"[{part}]" if isinstance(part, int) else (f".{part}" if where else str(part))
        message = str(problem["msg"]).removeprefix("Value error, ")[:300]
        lines.append(f"{where or 'manifest'}: {message}")
    return lines

