"""How far float32 model outputs move between CPU kernel variants, against the tests' tolerances.

Each variant of ``tests/cpu_variants.py`` (AVX2, AVX-512 without BF16/VNNI/AMX, the machine's
default, one and two threads) runs in a fresh interpreter: the golden Pi3 (both cases) and the
golden DA3 full forward passes on the golden inputs, and the Pi3 backend's first raw pose
through the SDK (how far its rotation is from orthonormal: what keyframe 0's pose inherited
before it was set to the identity). The table gives, per output, the largest deviation of any
variant from the machine's default, from the official reference outputs (``../shared/golden``),
and the tolerance the parity tests allow; the margin is tolerance / worst deviation.

    python benchmarks/cpu_variant_spread.py        # writes benchmarks/results/cpu_variant_spread.{md,json}
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.cpu_variants import VARIANTS, cpu_model, variant_environment  # noqa: E402

GOLDEN = ROOT.parent / "shared" / "golden"
# the parity tests' tolerances (tests/models/*/test_golden_parity.py): (atol, rtol)
TOLERANCES = {
    "pi3.camera_poses": (1e-5, 0.0), "pi3.conf": (1e-4, 0.0),
    "pi3.local_points": (1e-4, 1e-4), "pi3.points": (1e-4, 1e-4),
    "da3.pose_enc": (1e-5, 0.0), "da3.extrinsics": (1e-5, 0.0),
    "da3.depth": (1e-4, 1e-5), "da3.depth_conf": (1e-4, 1e-5),
}

CHILD = r"""
import sys
import numpy as np
import torch
from safetensors.torch import load_file
from kvtracker_sdk.models.pi3 import load_pi3
from kvtracker_sdk.models.da3 import load_da3
from kvtracker_sdk.backends.torch_backend import TorchBackend

golden, out = sys.argv[1], sys.argv[2]
threads = int(__import__("os").environ.get("KVTRACKER_TEST_TORCH_THREADS", "1"))
torch.set_num_threads(threads)  # as the test session does
arrays = {"capability": np.array(torch.backends.cpu.get_cpu_capability())}
with torch.no_grad():
    pi3 = load_pi3(golden + "/pi3/weights.safetensors").model
    for case in ("case1", "case2"):
        output = pi3(load_file(f"{golden}/pi3/{case}/inputs.safetensors")["imgs"])
        for name in ("camera_poses", "conf", "local_points", "points"):
            arrays[f"pi3.{case}.{name}"] = getattr(output, name).numpy()
    da3 = load_da3(golden + "/da3/weights.safetensors").model
    output = da3(load_file(golden + "/da3/inputs.safetensors")["imgs_01"],
                 ref_view_strategy="saddle_balanced", with_rays=True)
    for name in ("pose_enc", "extrinsics", "depth", "depth_conf"):
        arrays[f"da3.{name}"] = getattr(output, name).numpy()
    backend = TorchBackend.from_pretrained(golden + "/pi3/weights.safetensors")
    images = (load_file(golden + "/pi3/case1/inputs.safetensors")["imgs"][0].permute(0, 2, 3, 1)
              .mul(255).round().to(torch.uint8).numpy())
    pose = backend.map(images[:2]).poses[0]
    R = pose[:3, :3]
    arrays["first_pose_orthonormality"] = np.array(np.abs(R.T @ R - np.eye(3)).max())
np.savez(out, **arrays)
"""


def reference(name: str) -> np.ndarray | None:
    from safetensors.numpy import load_file

    family, *rest = name.split(".")
    if family == "pi3":
        case, output = rest
        return load_file(str(GOLDEN / "pi3" / case / "outputs.safetensors"))[output]
    if family == "da3":
        return load_file(str(GOLDEN / "da3" / "outputs.safetensors"))[rest[0]]
    return None


def main() -> None:
    load_before = os.getloadavg()[0]
    start = time.monotonic()
    runs: dict[str, dict[str, np.ndarray]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        for variant in VARIANTS:
            out = Path(scratch) / f"{variant}.npz"
            env = variant_environment(variant)
            env["PYTHONPATH"] = str(ROOT)
            subprocess.run([sys.executable, "-c", CHILD, str(GOLDEN), str(out)], env=env,
                           check=True)
            with np.load(out) as data:
                runs[variant] = {k: data[k] for k in data.files}
    names = [k for k in runs["default"] if k.startswith(("pi3.", "da3."))]
    rows = []
    for name in names:
        base = runs["default"][name]
        spread = max(float(np.abs(run[name] - base).max()) for run in runs.values())
        ref = reference(name)
        from_reference = max(float(np.abs(run[name] - ref).max()) for run in runs.values())
        key = ".".join([name.split(".")[0], name.split(".")[-1]])
        atol, rtol = TOLERANCES.get(key, (float("nan"), 0.0))
        allowed = atol + rtol * float(np.abs(ref).max())
        rows.append({"output": name, "max_abs": float(np.abs(base).max()),
                     "spread_between_variants": spread, "from_reference": from_reference,
                     "tolerance": allowed, "margin": allowed / max(from_reference, 1e-30)})
    orthonormality = {v: float(r["first_pose_orthonormality"]) for v, r in runs.items()}
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{cpu_model()}, {os.cpu_count()} cores",
        "load_average_before_after": [load_before, os.getloadavg()[0]],
        "command": "python benchmarks/cpu_variant_spread.py",
        "variants": {v: dict(VARIANTS[v]) for v in VARIANTS},
        "aten_capability": {v: str(r["capability"]) for v, r in runs.items()},
        "outputs": rows,
        "first_raw_pose_max_abs_RtR_minus_I": orthonormality,
        "seconds": time.monotonic() - start,
    }
    folder = ROOT / "benchmarks" / "results"
    (folder / "cpu_variant_spread.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        "# Float32 outputs across CPU kernel variants", "",
        f"{result['date']}, {result['machine']}, load average {load_before:.1f} before, "
        f"{result['load_average_before_after'][1]:.1f} after; `{result['command']}`.", "",
        "ATen capability per variant: " + ", ".join(
            f"{v} {c}" for v, c in result["aten_capability"].items()), "",
        "| output | max abs value | spread between variants | worst deviation from the "
        "official output | tolerance | margin |", "|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(f"| {row['output']} | {row['max_abs']:.3g} | "
                     f"{row['spread_between_variants']:.2e} | {row['from_reference']:.2e} | "
                     f"{row['tolerance']:.2e} | {row['margin']:.0f}x |")
    lines += ["", "Pi3 backend's first raw pose, max |R^T R - I| (what keyframe 0's pose carried "
              "before it was set to the identity): " + ", ".join(
                  f"{v} {e:.1e}" for v, e in orthonormality.items()), ""]
    (folder / "cpu_variant_spread.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
