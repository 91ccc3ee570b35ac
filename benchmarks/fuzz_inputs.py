"""Hostile user files, each in its own process: camera files, eval-many manifests and ground
truths, output names, edited export folders and version-2/3 maps with impossible numbers.

Every case runs in a new process forked from this one (the SDK already imported, so a case costs
milliseconds, not an interpreter start) with a 3 GB address-space limit (``RLIMIT_AS``) and a
60 s timeout. Counted per surface: cases; refused with a typed SDK error (and, of those, with
the expected field named); accepted; untyped errors (any other exception, a crash or a
``MemoryError``); hangs (killed at 60 s); cases whose peak RSS passed 1 GB; files written outside
``--out``. The cases are the seeded generators the test suite uses on fewer cases
(``tests/hostile_inputs.py``, ``tests/backends/export_edits.py``, ``tests/io/impossible_maps.py``).

Run: ``python benchmarks/fuzz_inputs.py [--cameras 320] [--manifests 220] [--exports 56]
[--maps 240] [--export-dir DIR]`` (without ``--export-dir`` the golden Pi3 weights are exported
once into a temporary folder). Writes ``benchmarks/results/fuzz_inputs.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import select
import signal
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from kvtracker_sdk.backends.simulated_scene import GroundTruth  # noqa: E402
from kvtracker_sdk.errors import KVTrackerError  # noqa: E402
from kvtracker_sdk.io.files.trajectory import read_trajectory  # noqa: E402
from kvtracker_sdk.io.map_file.map_file import load_map  # noqa: E402
from kvtracker_sdk.io.sources.camera_files import read_camera_file  # noqa: E402
from kvtracker_sdk.scale.manifest import SequenceSpec, load_manifest  # noqa: E402
from kvtracker_sdk.scale.sequence_run import run_sequence  # noqa: E402
from tests.backends.export_edits import edited_folder, edited_manifests  # noqa: E402
from tests.hostile_inputs import camera_cases, ground_truth_cases, manifest_cases  # noqa: E402
from tests.io.impossible_maps import base_files, impossible_maps  # noqa: E402

ADDRESS_SPACE = 3 << 30
TIMEOUT_S = 60.0
BIG_RSS = 1 << 30
Job = Callable[[], Any]


def run_isolated(job: Job, fields: tuple[str, ...]) -> dict[str, Any]:
    """``job()`` in a forked child under the limits; what it gave, as a dict."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read_end)
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))
        try:
            job()
            report = {"outcome": "accepted"}
        except KVTrackerError as exc:
            message = str(exc)
            named = any(field in message for field in fields)
            report = {"outcome": "refused", "type": type(exc).__name__, "named": named,
                      "message": message[:300], "message_chars": len(message)}
        except BaseException as exc:  # noqa: BLE001 - what escapes is what we count
            report = {"outcome": "untyped", "type": type(exc).__name__, "message": str(exc)[:300]}
        os.write(write_end, json.dumps(report).encode())
        os._exit(0)
    os.close(write_end)
    ready, _, _ = select.select([read_end], [], [], TIMEOUT_S)
    if not ready:
        os.kill(pid, signal.SIGKILL)
        report = {"outcome": "hang"}
    else:
        chunks = []
        while chunk := os.read(read_end, 65536):
            chunks.append(chunk)
        text = b"".join(chunks).decode()
        report = json.loads(text) if text else {"outcome": "untyped", "type": "crash"}
    os.close(read_end)
    _, status, usage = os.wait4(pid, 0)
    if os.WIFSIGNALED(status) and report["outcome"] != "hang":
        report = {"outcome": "untyped", "type": f"signal {os.WTERMSIG(status)}"}
    report["max_rss_bytes"] = usage.ru_maxrss * 1024  # Linux: kilobytes
    return report


class Tally:
    def __init__(self) -> None:
        self.surfaces: dict[str, Counter[str]] = {}
        self.examples: dict[str, list[dict[str, Any]]] = {}

    def add(self, surface: str, name: str, report: dict[str, Any], must_refuse: bool) -> None:
        counts = self.surfaces.setdefault(surface, Counter())
        counts["cases"] += 1
        counts[report["outcome"]] += 1
        if report["outcome"] == "refused" and report.get("named"):
            counts["refused_field_named"] += 1
        if report["max_rss_bytes"] > BIG_RSS:
            counts["over_1gb"] += 1
        bad = (report["outcome"] in ("untyped", "hang")
               or (must_refuse and report["outcome"] == "accepted")
               or (report["outcome"] == "refused" and not report.get("named")))
        if bad:
            self.examples.setdefault(surface, []).append({"case": name, **report})


def camera_surface(tally: Tally, folder: Path, count: int) -> None:
    for case in camera_cases(count, seed=2026):
        path = case.make(folder)
        tally.add("camera files", case.name,
                  run_isolated(lambda p=path: read_camera_file(p), case.fields), must_refuse=True)


def manifest_surface(tally: Tally, folder: Path, count: int) -> None:
    for case in manifest_cases(count, seed=2026):
        path = case.make(folder)
        tally.add("manifests", case.name,
                  run_isolated(lambda p=path: load_manifest(p), case.fields), must_refuse=True)
    for name, make in ground_truth_cases():
        path = make(folder)
        tally.add("ground truths (simulator)", name, run_isolated(
            lambda p=path: GroundTruth.from_tum(p, rate_hz=30.0), ("",)), must_refuse=True)
        lenient = name in ("two-lines-1e8-s-apart", "backwards-in-time")  # stamps kept as given
        tally.add("ground truths (evaluation)", name, run_isolated(
            lambda p=path: read_trajectory(p), ("",)), must_refuse=not lenient)


def output_name_surface(tally: Tally, folder: Path) -> None:
    """Sequence and config names that would lead out of ``--out``, through ``run_sequence`` with
    a spec that skipped the manifest's validation; every file under ``folder`` outside ``out``
    afterwards is a write outside."""
    names = ["..", ".", "/tmp/escape", "a/b", "a\\b", "../../x", "", "..\\..", "x/../..", "~"]
    out = folder / "out"
    out.mkdir(parents=True, exist_ok=True)
    before = {p for p in folder.rglob("*") if not p.is_relative_to(out)}
    for name in names:
        spec = SequenceSpec.model_construct(name=name, source=None, ground_truth=None, frames=None,
                                            simulated=None)
        for sequence, config in ((spec, "default"), (None, name)):
            target = sequence or SequenceSpec.model_construct(
                name="seq", source=None, ground_truth=None, frames=None, simulated=None)
            report = run_isolated(
                lambda s=target, c=config: run_sequence(s, c, None, lambda: None, out),  # type: ignore[arg-type]
                ("name",))
            tally.add("output names", f"{'config' if sequence is None else 'sequence'} {name!r}",
                      report, must_refuse=True)
    after = {p for p in folder.rglob("*") if not p.is_relative_to(out)}
    tally.surfaces["output names"]["writes_outside_out"] = len(after - before) + int(
        Path("/tmp/escape").exists())


def export_surface(tally: Tally, folder: Path, export: Path, count: int) -> None:
    from kvtracker_sdk.backends.onnx import OnnxBackend

    manifest = json.loads((export / "manifest.json").read_text())
    tally.add("export folders (unedited)", "unedited", run_isolated(
        lambda: OnnxBackend(edited_folder(export, folder / "ok", manifest)), ()), must_refuse=False)
    for name, edited in edited_manifests(manifest, count, seed=2026):
        kind = name.split("-", 1)[1]
        fields = {"weights_bytes": ("weights_bytes",), "layout": ("layout",),
                  "config": ("config_hash", "'config'"), "swap": ("wrong role",), "spec": ("graphs.",),
                  "patch_size": ("patch_size",), "extra_tokens": ("extra_tokens_per_frame",),
                  "drop_role": ("graph", "sha256")}[kind]
        target = edited_folder(export, folder / "edited", edited)
        tally.add("export folders", name, run_isolated(lambda t=target: OnnxBackend(t), fields),
                  must_refuse=True)


def map_surface(tally: Tally, folder: Path, count: int) -> None:
    bases = base_files(folder)
    path = folder / "case.kvmap"
    for name, data in impossible_maps(bases, count, seed=2026):
        path.write_bytes(data)
        field = name.split("-", 3)[3]
        fields = {"scale": ("scale",), "gauge": ("gauge",), "keyframe": ("translation", "pose"),
                  "points": ("points_scale", "point scales"), "int8": ("int8",)}[field.split("-")[0]]
        tally.add("v2/v3 maps", name, run_isolated(lambda: load_map(path), fields),
                  must_refuse=True)


def _export_golden(folder: Path) -> Path:
    from tests.cli.invoke import invoke

    out = folder / "pi3-golden"
    result = invoke("export-onnx", "--weights", ROOT.parent / "shared" / "golden" / "pi3" /
                    "weights.safetensors", "--out", out)
    assert result.exit_code == 0, result.output
    return out


def markdown(document: dict[str, Any]) -> str:
    columns = ["cases", "refused", "refused_field_named", "accepted", "untyped", "hang",
               "over_1gb", "writes_outside_out"]
    lines = [f"# fuzz_inputs ({document['date']}, {document['machine']})", "",
             f"Command: `{document['command']}`; load average {document['load_average_start']} "
             f"-> {document['load_average_end']}; {document['seconds']:.0f} s.", "",
             "| surface | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for surface, counts in document["surfaces"].items():
        lines.append(f"| {surface} | " + " | ".join(str(counts.get(c, 0)) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cameras", type=int, default=320)
    parser.add_argument("--manifests", type=int, default=220)
    parser.add_argument("--exports", type=int, default=56)
    parser.add_argument("--maps", type=int, default=240)
    parser.add_argument("--export-dir", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "fuzz_inputs.json")
    args = parser.parse_args()
    start, load_start = time.perf_counter(), os.getloadavg()
    tally = Tally()
    with tempfile.TemporaryDirectory() as temp:
        scratch = Path(temp)
        for name in ("camera", "manifest", "names", "export", "maps"):
            (scratch / name).mkdir()
        camera_surface(tally, scratch / "camera", args.cameras)
        manifest_surface(tally, scratch / "manifest", args.manifests)
        output_name_surface(tally, scratch / "names")
        export = args.export_dir or _export_golden(scratch / "export")
        export_surface(tally, scratch / "export", export, args.exports)
        map_surface(tally, scratch / "maps", args.maps)
    document = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {os.cpu_count()} CPUs, {platform.platform()}",
        "command": "python " + " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
        "limits": {"address_space_bytes": ADDRESS_SPACE, "timeout_s": TIMEOUT_S,
                   "big_rss_bytes": BIG_RSS},
        "load_average_start": [round(x, 2) for x in load_start],
        "load_average_end": [round(x, 2) for x in os.getloadavg()],
        "seconds": time.perf_counter() - start,
        "surfaces": {name: dict(counts) for name, counts in tally.surfaces.items()},
        "failures": tally.examples,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    args.out.with_suffix(".md").write_text(markdown(document))
    print(markdown(document))
    if tally.examples:
        print(json.dumps(tally.examples, indent=2)[:4000])


if __name__ == "__main__":
    main()
