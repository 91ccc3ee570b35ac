"""Two checkouts of ``kvtracker_sdk`` side by side on ``benchmarks/map_io.py``, in alternating runs.

Each pair runs ``map_io`` once with the ``--before`` checkout's package first on the path and
once with this one's (the order alternating from pair to pair), so that both see the same
stretch of the machine's load; the per-round ratios of all runs of a side are pooled and their
median reported, with every run's own JSON kept inside this one. Run from the repository root::

    python -m benchmarks.map_io_ab --before /path/to/old/checkout --pairs 3 --rounds 3

Writes ``benchmarks/results/<--name>.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


def run_side(package_root: Path, rounds: int, name: str) -> dict[str, Any]:
    """One ``map_io`` run with ``package_root``'s ``kvtracker_sdk`` imported; its JSON."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(package_root), str(ROOT)])}
    subprocess.run([sys.executable, "-m", "benchmarks.map_io", "--rounds", str(rounds),
                    "--name", name], cwd=ROOT, env=env, check=True, capture_output=True)  # fmt: skip
    path = RESULTS / f"{name}.json"
    result: dict[str, Any] = json.loads(path.read_text())
    path.unlink()
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout (or package root)")
    parser.add_argument("--before-label", default="", help="e.g. the commit it holds")
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--name", default="map_io_ab")
    args = parser.parse_args(argv)
    sides = {"before": args.before.resolve(), "after": ROOT}
    runs: dict[str, list[dict[str, Any]]] = {"before": [], "after": []}
    for pair in range(args.pairs):
        order = ["before", "after"] if pair % 2 == 0 else ["after", "before"]
        for side in order:
            runs[side].append(run_side(sides[side], args.rounds, f"_ab_{side}_{pair}"))
    pooled = {
        side: {
            key: statistics.median(r for run in side_runs for r in run[key]["rounds"])
            for key in ("save_over_write_fsync", "load_over_raw_read",
                        "load_over_raw_read_new_memory")
        }
        for side, side_runs in runs.items()
    }  # fmt: skip
    loads = [run["load_averages"][0][0] for side_runs in runs.values() for run in side_runs]
    lines = [f"{args.pairs} pairs x {args.rounds} rounds, alternating; 1-min load average "
             f"{min(loads):.1f}–{max(loads):.1f}; niceness {os.nice(0)}", "",
             "| code | save / (write + fsync) | verified cold load / raw cold read | "
             "same / raw read into new memory |", "|---|---:|---:|---:|"]  # fmt: skip
    for side, values in pooled.items():
        lines.append(f"| {side} | {values['save_over_write_fsync']:.2f}× | "
                     f"{values['load_over_raw_read']:.2f}× | "
                     f"{values['load_over_raw_read_new_memory']:.2f}× |")  # fmt: skip
    table = "\n".join(lines)
    print(table)
    result = {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": "python -m benchmarks.map_io_ab " + " ".join(argv or sys.argv[1:]),
        "before": {"path": str(sides["before"]), "label": args.before_label},
        "niceness": os.nice(0), "pooled_median_ratios": pooled, "table": table, "runs": runs,
    }  # fmt: skip
    path = RESULTS / f"{args.name}.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
