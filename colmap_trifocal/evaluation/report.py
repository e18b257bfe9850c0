"""Summaries of evaluation records: CSV, Markdown table, boxplots (PNG) and JSON."""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..common.extras import missing_extra
from .records import RunRecord

#: Order of methods in tables and plots (others follow alphabetically).
METHOD_ORDER = (
    "msac-opt",
    "msac",
    "direct",
    "fundamental",
    "calibrate_view_graph",
    "mapping",
    "ba-floor",
    "prior",
)


@dataclass
class SummaryRow:
    """Error statistics (percent) of one method in one configuration."""

    scene: str
    num_images: int
    perturbation: str
    noise_px: float | None
    method: str
    runs: int
    failures: int
    mean: float
    median: float
    std: float

    def configuration(self) -> tuple:
        return (self.scene, self.num_images, self.perturbation, self.noise_px)


def _method_key(method: str) -> tuple[int, str]:
    return (METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER), method)


def with_prior_rows(records: list[RunRecord]) -> list[RunRecord]:
    """Add one "prior" record per run: the error of the perturbed prior itself."""
    seen = set()
    extra = []
    for r in records:
        key = (r.scene, r.num_images, r.perturbation, r.noise_px, r.run)
        if key in seen:
            continue
        seen.add(key)
        fields = dict(
            experiment=r.experiment,
            scene=r.scene,
            run=r.run,
            seed=r.seed,
            num_images=r.num_images,
            perturbation=r.perturbation,
            noise_px=r.noise_px,
        )
        extra.append(
            RunRecord.finished(
                np.array(r.prior), np.array(r.truth), np.array(r.prior), method="prior", **fields
            )
        )
    return records + extra


def summarize(records: list[RunRecord]) -> list[SummaryRow]:
    """Mean / median / std of the error per (scene, images, perturbation, noise, method).

    Failed runs are counted in ``failures`` and left out of the statistics.
    """
    groups: dict[tuple, list[RunRecord]] = defaultdict(list)
    for r in records:
        groups[(r.scene, r.num_images, r.perturbation, r.noise_px, r.method)].append(r)
    rows = []
    for (scene, count, perturbation, noise, method), group in groups.items():
        errors = np.array([r.error_percent for r in group if r.ok], dtype=float)
        rows.append(
            SummaryRow(
                scene=scene,
                num_images=count,
                perturbation=perturbation,
                noise_px=noise,
                method=method,
                runs=len(group),
                failures=len(group) - len(errors),
                mean=float(errors.mean()) if len(errors) else float("nan"),
                median=float(np.median(errors)) if len(errors) else float("nan"),
                std=float(errors.std()) if len(errors) else float("nan"),
            )
        )
    rows.sort(key=lambda row: (*_sortable(row.configuration()), _method_key(row.method)))
    return rows


def _sortable(configuration: tuple) -> tuple:
    return tuple(-1 if v is None else v for v in configuration)


def write_csv(rows: list[SummaryRow], path: Path) -> None:
    fields = list(SummaryRow.__dataclass_fields__)
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(fields)
        for row in rows:
            writer.writerow([getattr(row, f) for f in fields])


def markdown_table(rows: list[SummaryRow]) -> str:
    """One line per configuration and method: mean / median / std of the error in %."""
    synthetic = any(row.noise_px is not None for row in rows)
    head = "| scene | noise px |" if synthetic else "| scene | images | prior perturbation % |"
    lines = [
        head + " method | mean % | median % | std % | runs (failed) |",
        "|---" * (6 + (1 if synthetic else 2) - 1) + "|---|",
    ]
    for row in rows:
        where = (
            f"| {row.scene} | {row.noise_px:g} |"
            if synthetic
            else f"| {row.scene} | {row.num_images} | {row.perturbation} |"
        )
        lines.append(
            f"{where} {row.method} | {row.mean:.3f} | {row.median:.3f} | {row.std:.3f} | "
            f"{row.runs} ({row.failures}) |"
        )
    return "\n".join(lines) + "\n"


def boxplots(records: list[RunRecord], path: Path, title: str = "") -> None:
    """One panel per configuration, one box per method (error in %, log scale).

    Drawn on a :class:`matplotlib.figure.Figure` without pyplot, so the caller's
    backend (a notebook's inline plots, say) is left alone.
    """
    try:
        from matplotlib.figure import Figure
    except ModuleNotFoundError as exc:
        raise missing_extra("matplotlib", "the plots") from exc

    groups: dict[tuple, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        if r.ok:
            key = (r.scene, r.num_images, r.perturbation, r.noise_px)
            if r.error_percent is not None:
                groups[key][r.method].append(float(r.error_percent))
    keys = sorted(groups, key=_sortable)
    if not keys:
        raise ValueError("no successful run to plot")
    columns = min(len(keys), 4)
    rows = int(np.ceil(len(keys) / columns))
    figure = Figure(figsize=(4.2 * columns, 3.6 * rows))
    axes = figure.subplots(rows, columns, squeeze=False, sharey=True)
    for axis, key in zip(axes.ravel(), keys, strict=False):
        methods = sorted(groups[key], key=_method_key)
        data = [np.maximum(groups[key][m], 1e-4) for m in methods]
        axis.boxplot(data, showfliers=True)
        axis.set_xticks(range(1, len(methods) + 1), methods, rotation=35, ha="right", fontsize=8)
        axis.set_yscale("log")
        scene, count, perturbation, noise = key
        label = (
            f"noise ±{noise:g} px" if noise is not None else f"{count} images, ±{perturbation} %"
        )
        axis.set_title(f"{scene}\n{label}", fontsize=9)
        axis.grid(axis="y", alpha=0.3)
    for axis in axes.ravel()[len(keys) :]:
        axis.axis("off")
    for axis in axes[:, 0]:
        axis.set_ylabel("mean relative error of fx, fy, cx, cy (%)")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def write_json(records: list[RunRecord], path: Path) -> None:
    path.write_text(json.dumps([r.to_json() for r in records], indent=1))


def write_outputs(records: list[RunRecord], folder: Path, stem: str, title: str = "") -> dict:
    """``<stem>.csv``, ``<stem>.md`` and ``<stem>.png`` in folder; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = summarize(with_prior_rows(records))
    paths = {
        "csv": folder / f"{stem}.csv",
        "markdown": folder / f"{stem}.md",
        "png": folder / f"{stem}.png",
    }
    write_csv(rows, paths["csv"])
    paths["markdown"].write_text(markdown_table(rows))
    boxplots(with_prior_rows(records), paths["png"], title)
    return paths
