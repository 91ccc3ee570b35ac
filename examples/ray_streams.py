"""Serve several camera streams from Ray actors: one actor per device, many sessions each.

Each "device" is a Ray actor holding a ``TrackerHost`` (one model, many sessions). Four simulated
camera streams are spread over two actors and fed concurrently, frame by frame, as PNG bytes with
their capture times; then stream 0's session is saved on its actor and resumed on the other one.
With ``--check`` every stream is also run in this process and compared (they must be identical).

    python examples/ray_streams.py --streams 4 --frames 90 --check

Ray is started bound to 127.0.0.1, dashboard off, usage statistics off
(``kvtracker_sdk.scale.ray_runtime``). Needs the ``[ray]`` extra (``pip install -e ".[ray]"`` in the clone).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import cv2

from kvtracker_sdk.scale.manifest import SimulatedSpec
from kvtracker_sdk.scale.sequence_run import simulated_sequence
from kvtracker_sdk.scale.service import TrackerHost

CONFIG = {"resolution": 224, "keyframing": {"interval_frames": 20}}


def stream_specs(count: int, frames: int) -> list[dict[str, Any]]:
    """Stream k: a simulated orbit of its own (length, turns and noise seed differ)."""
    return [
        {"orbit_frames": frames + 10 * k, "orbit_turns": 0.3 + 0.1 * k, "seed": 100 + k}
        for k in range(count)
    ]


def encoded_frames(spec: dict[str, Any]) -> list[tuple[bytes, float]]:
    """The stream's frames as PNG bytes (lossless: the simulation reads its frame index back)."""
    _backend, frames, _truth = simulated_sequence(SimulatedSpec.model_validate(spec))
    return [
        (cv2.imencode(".png", frame.image[:, :, ::-1])[1].tobytes(), frame.timestamp)
        for frame in frames
    ]


def run_in_process(specs: list[dict[str, Any]], split: int) -> dict[str, list[dict[str, Any]]]:
    """The reference: each stream alone in this process; stream 0 saved at ``split`` and
    resumed on a second host."""
    out: dict[str, list[dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory() as folder:
        for k, spec in enumerate(specs):
            frames, host = encoded_frames(spec), TrackerHost()
            host.open_session("s", config=CONFIG, simulated=spec)
            stop = split if k == 0 else len(frames)
            out[f"stream{k}"] = [host.push("s", f, t) for f, t in frames[:stop]]
            if k == 0:
                path = str(Path(folder) / "stream0.kvmap")
                host.save_session("s", path)
                other = TrackerHost()
                other.open_session("s", map_path=path, simulated=spec)
                out["stream0-resumed"] = [other.push("s", f, t) for f, t in frames[split:]]
                other.close()
            host.close()
    return out


def run_on_ray(specs: list[dict[str, Any]], split: int, devices: int = 2) -> dict[str, Any]:
    """All streams at once on ``devices`` actors; stream 0 saved on its actor at ``split`` and
    resumed on the next actor."""
    from kvtracker_sdk.scale.ray_runtime import actor_class, ensure_ray

    ray = ensure_ray(num_cpus=devices)
    hosts = [actor_class(TrackerHost).remote() for _ in range(devices)]
    owner = {f"stream{k}": hosts[k % devices] for k in range(len(specs))}
    feeds = {f"stream{k}": encoded_frames(spec) for k, spec in enumerate(specs)}
    ray.get([owner[name].open_session.remote(name, config=CONFIG, simulated=specs[k])
             for k, name in enumerate(feeds)])
    out: dict[str, list[dict[str, Any]]] = {name: [] for name in feeds}
    limit = {name: (split if name == "stream0" else len(frames)) for name, frames in feeds.items()}
    for i in range(max(limit.values())):  # one frame of every stream in flight at a time
        live = [name for name in feeds if i < limit[name]]
        results = ray.get([owner[n].push.remote(n, *feeds[n][i]) for n in live])
        for name, result in zip(live, results, strict=True):
            out[name].append(result)
    with tempfile.TemporaryDirectory() as folder:
        path = str(Path(folder) / "stream0.kvmap")
        ray.get(owner["stream0"].save_session.remote("stream0", path))
        other = hosts[1 % devices]
        ray.get(other.open_session.remote("stream0-resumed", map_path=path, simulated=specs[0]))
        out["stream0-resumed"] = ray.get(
            [other.push.remote("stream0-resumed", f, t) for f, t in feeds["stream0"][split:]]
        )
    for host in hosts:
        ray.kill(host)
    return out


def summary(results: dict[str, list[dict[str, Any]]]) -> list[str]:
    lines = ["stream           frames  valid  last state"]
    for name, rows in results.items():
        valid = sum(r["pose_valid"] for r in rows)
        lines.append(f"{name:<16} {len(rows):>6} {valid:>6}  {rows[-1]['state'] if rows else '-'}")
    return lines


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--streams", type=int, default=4)
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--check", action="store_true", help="compare with in-process runs")
    args = parser.parse_args(argv)
    specs = stream_specs(args.streams, args.frames)
    split = args.frames // 2
    on_ray = run_on_ray(specs, split)
    print("\n".join(summary(on_ray)))
    report: dict[str, Any] = {"ray": on_ray}
    if args.check:
        alone = run_in_process(specs, split)
        report["equal"] = {name: alone[name] == on_ray[name] for name in alone}
        print("identical to single-process runs:", report["equal"])
    return report


if __name__ == "__main__":
    main()
