"""Object keyframe rules on synthetic orbits: the view-direction rule against the paper's rule.

A camera looks at an object at the origin from 1.5 m while it moves along a path given in degrees
of azimuth and elevation (0.5 degrees per frame), and each rule decides, frame by frame, exactly
as ``MapKeeper`` does (frame 0 is keyframe 0; a frame becomes a keyframe when the rule calls it
novel against every keyframe so far; no budget). Paths:

* ``one ring``: one turn at 0 degrees of elevation;
* ``two rings``: that turn, then one at 30 degrees (the second part: the higher ring);
* ``orbit at 85``: one turn at 85 degrees (all its views lie within 10 degrees of each other);
* ``revisit``: 0 -> 180 -> 0 -> 180 degrees of azimuth at 0 degrees (second part: the way back
  and forth again, every view seen before).

Columns: keyframes in all, keyframes the second part added, **coverage** (the share of the path's
frames whose view direction lies within τ of a keyframe's at the end) and the **worst gap** (the
largest angle from a frame's view direction to the nearest keyframe's). The paper's rule reads
azimuth and elevation in a world frame with the true up (keyframe 0 held level); the tracker's
world up is keyframe 0's -y, so for a first view from above it would measure around a tilted axis.

    python -m benchmarks.object_keyframe_rules [--tau 10]

Prints a markdown table and writes ``benchmarks/results/object_keyframe_rules.json``. Counting, not
timing: the numbers do not depend on the machine.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from kvtracker_sdk.backends.simulated_scene import look_at
from kvtracker_sdk.config import ObjectKeyframeRule
from kvtracker_sdk.tracking.mapping.keyframes import novel_object_view, view_direction

RESULTS = Path(__file__).parent / "results"
STEP_DEG = 0.5
RADIUS_M = 1.5


@dataclass(frozen=True)
class Row:
    path: str
    rule: str
    keyframes: int
    added_in_second_part: int | None
    coverage: float
    worst_gap_deg: float


def sweep(start: float, stop: float) -> np.ndarray:
    """Angles from ``start`` towards ``stop`` (degrees) at ``STEP_DEG``, ``stop`` excluded."""
    count = int(round(abs(stop - start) / STEP_DEG))
    return start + np.sign(stop - start) * STEP_DEG * np.arange(count)


def ring(elevation: float, azimuths: np.ndarray) -> np.ndarray:
    return np.stack([azimuths, np.full_like(azimuths, elevation)], axis=1)


def paths() -> dict[str, tuple[np.ndarray, int | None]]:
    """name -> ([F, 2] azimuth/elevation in degrees, first frame of the second part or None)."""
    turn = sweep(0.0, 360.0)
    out = sweep(0.0, 180.0)
    back = sweep(180.0, 0.0)
    return {
        "one ring": (ring(0.0, turn), None),
        "two rings (0 and 30 deg)": (np.concatenate([ring(0.0, turn), ring(30.0, turn)]), len(turn)),
        "orbit at 85 deg": (ring(85.0, turn), None),
        "revisit (0-180-0-180 deg)": (
            np.concatenate([ring(0.0, out), ring(0.0, back), ring(0.0, out)]), len(out)),
    }


def camera_poses(angles: np.ndarray) -> np.ndarray:
    """[F, 4, 4] T_world_cam looking at the origin; world with OpenCV-style axes and up = -y
    (the convention ``keyframes.view_angles_deg`` reads azimuth and elevation in)."""
    azimuth, elevation = np.radians(angles[:, 0]), np.radians(angles[:, 1])
    centres = RADIUS_M * np.stack([
        np.cos(elevation) * np.sin(azimuth), -np.sin(elevation), np.cos(elevation) * np.cos(azimuth),
    ], axis=1)  # fmt: skip
    up = np.array([0.0, -1.0, 0.0])
    return np.stack([look_at(c, np.zeros(3), up) for c in centres])


def run_rule(poses: np.ndarray, rule: ObjectKeyframeRule, tau: float) -> list[int]:
    """Frame indices of the keyframes the rule picks along ``poses``."""
    keyframes = [0]
    centre = np.zeros(3)
    for index in range(1, len(poses)):
        if novel_object_view(rule, poses[index], poses[keyframes], centre, tau):
            keyframes.append(index)
    return keyframes


def measure(tau: float) -> list[Row]:
    rows = []
    for name, (angles, second) in paths().items():
        poses = camera_poses(angles)
        directions = view_direction(poses, np.zeros(3))
        for rule in ObjectKeyframeRule:
            keyframes = run_rule(poses, rule, tau)
            cosines = np.clip(directions @ directions[keyframes].T, -1.0, 1.0).max(axis=1)
            gaps = np.degrees(np.arccos(cosines))
            added = None if second is None else sum(k >= second for k in keyframes)
            rows.append(Row(name, rule.value, len(keyframes), added,
                            float(np.mean(gaps <= tau + 1e-9)), float(gaps.max())))
    return rows


def table(rows: list[Row], tau: float) -> str:
    lines = [
        f"| path (τ = {tau:g}°, {STEP_DEG:g}° per frame) | rule | keyframes | added by the second "
        "part | coverage | worst gap |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        added = "–" if row.added_in_second_part is None else str(row.added_in_second_part)
        lines.append(f"| {row.path} | {row.rule} | {row.keyframes} | {added} | "
                     f"{100 * row.coverage:.0f} % | {row.worst_gap_deg:.1f}° |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tau", type=float, default=10.0, help="view angle threshold (degrees)")
    parser.add_argument("--out", type=Path, default=RESULTS / "object_keyframe_rules.json")
    args = parser.parse_args(argv)
    rows = measure(args.tau)
    print(table(rows, args.tau))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(
        {"tau_deg": args.tau, "step_deg": STEP_DEG, "rows": [asdict(r) for r in rows]}, indent=2
    ) + "\n")
    return rows


if __name__ == "__main__":
    main()
