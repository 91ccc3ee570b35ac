"""Tables and the FPS-vs-N plot of a ``tracking_vs_recompute`` result (its JSON dict).

A row of the result holds, per head set ``h``: ``track_h`` / ``recompute_h`` timing samples
(``{"wall": [...], "cpu": [...]}`` seconds; recompute only up to ``--max-recompute``) and
``track_h_flops`` / ``recompute_h_flops`` (the FLOP model by stage, with ``total``).

Re-render a saved result (e.g. on the other clock)::

    python -m benchmarks.tracking_report benchmarks/results/mid_308_bf16.json --clock cpu
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["best_seconds", "main", "markdown_table", "plot_fps", "print_tables"]


def best_seconds(row: dict[str, Any], key: str, clock: str) -> float | None:
    """Minimum sample of ``row[key]`` on ``clock`` (None when that side was not timed)."""
    samples = row.get(key)
    return min(samples[clock]) if samples else None


def _threads(result: dict[str, Any]) -> str:
    count = result["threads"]
    return f"{count} CPU thread{'' if count == 1 else 's'}"


def _fmt(value: float | None, spec: str) -> str:
    return "—" if value is None else format(value, spec)


def markdown_table(result: dict[str, Any], heads: str) -> str:
    """One markdown table for head set ``heads``: measured seconds beside the FLOP model.

    speedup = t_recompute / t_track; FLOP ratio = recompute FLOPs / tracking-step FLOPs; growth
    = t_track(N) / t_track(N0) (N0 the first N) measured, and the same ratio of FLOPs.
    """
    clock, rows = result["clock"], result["rows"]
    first = rows[0]
    t0 = best_seconds(first, f"track_{heads}", clock)
    f0 = first[f"track_{heads}_flops"]["total"]
    n0 = first["keyframes"]
    lines = [
        f"| N | track (s) | recompute N+1 (s) | speedup | FLOP ratio | track GFLOP "
        f"| track GFLOP/s | recompute GFLOP/s | t(N)/t({n0}) measured | t(N)/t({n0}) FLOP model |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        track = best_seconds(row, f"track_{heads}", clock)
        recompute = best_seconds(row, f"recompute_{heads}", clock)
        f_track = row[f"track_{heads}_flops"]["total"]
        f_recompute = row[f"recompute_{heads}_flops"]["total"]
        assert track is not None and t0 is not None
        speedup = None if recompute is None else recompute / track
        recompute_rate = None if recompute is None else f_recompute / recompute / 1e9
        cells = [
            str(row["keyframes"]),
            f"{track:.3f}",
            _fmt(recompute, ".3f"),
            _fmt(speedup, ".1f"),
            f"{f_recompute / f_track:.1f}",
            f"{f_track / 1e9:.1f}",
            f"{f_track / track / 1e9:.1f}",
            _fmt(recompute_rate, ".1f"),
            f"{track / t0:.2f}",
            f"{f_track / f0:.2f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def print_tables(result: dict[str, Any]) -> None:
    """Print one markdown table per head set, with a heading naming the run."""
    size = "x".join(map(str, dict.fromkeys(result["resolution"])))  # "308" or "196x252"
    for heads in result["heads"]:
        print(
            f"\n{result['config_name']} @ {size} px, {result['dtype']}, heads={heads}, "
            f"{_threads(result)}, best-of {result['clock']} seconds\n"
        )
        print(markdown_table(result, heads))


def plot_fps(result: dict[str, Any], path: Path) -> None:
    """FPS of tracking and recompute against N (log axes), like the paper's FPS-vs-N figure.

    Dotted lines: the FLOP model scaled to the first measured point of each curve.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    clock, rows = result["clock"], result["rows"]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for side, marker in (("track", "o"), ("recompute", "s")):
        for heads in result["heads"]:
            key = f"{side}_{heads}"
            points = [
                (row["keyframes"], seconds, row[f"{key}_flops"]["total"])
                for row in rows
                if (seconds := best_seconds(row, key, clock)) is not None
            ]
            if not points:
                continue
            ns = [n for n, _, _ in points]
            line = ax.plot(ns, [1 / s for _, s, _ in points], marker=marker,
                           label=f"{'tracking (cached)' if side == 'track' else 'recompute N+1'}, {heads}")  # fmt: skip
            _, s0, f0 = points[0]
            ax.plot(ns, [f0 / (s0 * f) for _, _, f in points], linestyle=":",
                    color=line[0].get_color(), linewidth=1)  # fmt: skip
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("keyframes N")
    ax.set_ylabel("frames per second")
    size = "x".join(map(str, dict.fromkeys(result["resolution"])))  # "308" or "196x252"
    ax.set_title(f"Pi3 {result['config_name']} @ {size} px, {result['dtype']}, "
                 f"{_threads(result)} (dotted: FLOP model)", fontsize=9)  # fmt: skip
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Tables and plot of a saved result.")
    parser.add_argument("result", type=Path, help="JSON written by tracking_vs_recompute")
    parser.add_argument("--clock", choices=["wall", "cpu"], help="default: the run's clock")
    parser.add_argument("--plot", type=Path, help="also save the FPS plot here")
    args = parser.parse_args(argv)
    result = json.loads(args.result.read_text())
    result["clock"] = args.clock or result["clock"]
    print_tables(result)
    if args.plot:
        plot_fps(result, args.plot)


if __name__ == "__main__":
    main()
