"""The manifests the scale-out tests run: five simulated sequences over different ground-truth
trajectories and one real sequence (the golden Pi3 weights over the 20 real TUM frames)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from tests.helpers import shared_path


def simulated_sequences() -> list[dict[str, Any]]:
    gt = str(shared_path("data", "tum_fr2_desk", "groundtruth.txt"))
    return [
        {"name": "orbit_a", "simulated": {"orbit_frames": 120, "orbit_turns": 0.5, "seed": 1}},
        {"name": "orbit_b", "simulated": {"orbit_frames": 90, "orbit_turns": 1.0, "seed": 2}},
        {"name": "orbit_lossy", "simulated": {"orbit_frames": 150, "seed": 3, "loss": [60, 80]}},
        {"name": "tum_head", "simulated": {"ground_truth": gt, "frames": 150, "seed": 4}},
        {"name": "tum_noisy", "simulated": {"ground_truth": gt, "frames": 120, "seed": 5,
                                            "noise_cm": 3.0}},
    ]


def write_manifest(folder: Path, *, with_golden: bool = True) -> Path:
    sequences = simulated_sequences()
    document: dict[str, Any] = {
        "configs": {"d224": {"resolution": 224, "keyframing": {"interval_frames": 30}}},
        "sequences": sequences,
    }
    if with_golden:
        tum = shared_path("data", "tum_fr2_desk")
        document["model"] = {"weights": str(shared_path("golden", "pi3", "weights.safetensors"))}
        sequences.append({"name": "tum_golden_pi3", "source": str(tum),
                          "ground_truth": str(tum / "groundtruth.txt")})
    path = folder / "manifest.json"
    path.write_text(json.dumps(document, indent=2))
    return path
