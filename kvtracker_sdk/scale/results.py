"""The ``eval-many`` table: one row per (sequence, config) and the mean per config, like the
paper's tables, written as CSV, JSON, a Markdown summary and (with matplotlib) a bar plot."""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.io.files.atomic import atomic_write
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.scale.sequence_run import SequenceResult

__all__ = ["EvalManyResult"]

_log = get_logger(__name__)
_METRICS = ("ate_rmse_m", "rpe_translation_rmse_m", "rpe_rotation_rmse_deg")


@dataclass(frozen=True)
class EvalManyResult:
    """Every task's result, in manifest order."""

    results: tuple[SequenceResult, ...]
    engine: str
    workers: int

    def metrics(self) -> list[dict[str, Any]]:
        """Only the numbers (no worker names or times): equal across engines."""
        return [r.metrics() for r in self.results]

    def averages(self) -> dict[str, dict[str, float | int | None]]:
        """Per config: the mean of each metric over the sequences that have it."""
        table: dict[str, dict[str, float | int | None]] = {}
        for config in dict.fromkeys(r.config for r in self.results):
            rows = [r for r in self.results if r.config == config]
            means: dict[str, float | int | None] = {"sequences": len(rows)}
            for key in _METRICS:
                values = [getattr(r, key) for r in rows if getattr(r, key) is not None]
                means[key] = float(np.mean(values)) if values else None
            means["scored"] = sum(r.error is None for r in rows)
            table[config] = means
        return table

    def markdown(self) -> str:
        lines = [
            f"# eval-many ({len(self.results)} runs, engine {self.engine}, {self.workers} workers)",
            "",
            "| sequence | config | frames | valid | keyframes | ATE RMSE (m) | RPE t (m) | "
            "RPE r (deg) | backend | note |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in self.results:
            note = ("simulated" if r.simulated else "") + (f" {r.error}" if r.error else "")
            lines.append(
                f"| {r.sequence} | {r.config} | {r.frames} | {r.valid_poses} | {r.keyframes} | "
                f"{_fmt(r.ate_rmse_m)} | {_fmt(r.rpe_translation_rmse_m)} | "
                f"{_fmt(r.rpe_rotation_rmse_deg)} | {r.backend} | {note.strip()} |"
            )
        lines += ["", "| config | sequences scored | mean ATE (m) | mean RPE t (m) | "
                  "mean RPE r (deg) |", "|---|---|---|---|---|"]
        for config, means in self.averages().items():
            lines.append(
                f"| {config} | {means['scored']}/{means['sequences']} | "
                f"{_fmt(means['ate_rmse_m'])} | {_fmt(means['rpe_translation_rmse_m'])} | "
                f"{_fmt(means['rpe_rotation_rmse_deg'])} |"
            )
        return "\n".join(lines) + "\n"

    def write(self, out_dir: Path) -> dict[str, Path]:
        """results.csv, results.json, summary.md and (with matplotlib) results.png."""
        files = {
            "csv": out_dir / "results.csv",
            "json": out_dir / "results.json",
            "markdown": out_dir / "summary.md",
        }
        buffer = io.StringIO()
        fields = list(self.results[0].to_dict()) if self.results else []
        writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(r.to_dict() for r in self.results)
        with atomic_write(files["csv"]) as handle:
            handle.write(buffer.getvalue())
        document = {"engine": self.engine, "workers": self.workers,
                    "results": [r.to_dict() for r in self.results], "averages": self.averages()}
        with atomic_write(files["json"]) as handle:
            json.dump(document, handle, indent=2)
        with atomic_write(files["markdown"]) as handle:
            handle.write(self.markdown())
        plot = self._plot(out_dir / "results.png")
        if plot is not None:
            files["plot"] = plot
        return files

    def _plot(self, path: Path) -> Path | None:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:  # an optional output: the table files are written regardless
            _log.warning("results.png not written: matplotlib is not installed (extra [viz])")
            return None
        scored = [r for r in self.results if r.ate_rmse_m is not None]
        if not scored:
            return None
        figure, axis = plt.subplots(figsize=(max(4.0, 0.6 * len(scored)), 3.0))
        labels = [f"{r.sequence}\n{r.config}" for r in scored]
        axis.bar(range(len(scored)), [float(r.ate_rmse_m or 0.0) for r in scored], color="#4477aa")
        axis.set_xticks(range(len(scored)), labels, fontsize=7)
        axis.set_ylabel("ATE RMSE (Sim(3)-aligned, GT units)")
        figure.tight_layout()
        with atomic_write(path, binary=True) as handle:
            figure.savefig(handle, format="png", dpi=100)
        plt.close(figure)
        return path


def _fmt(value: float | None) -> str:
    return "—" if value is None else f"{value:.4f}"
