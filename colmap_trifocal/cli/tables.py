"""The tables ``calibrate`` prints: one line per camera group, and the estimate beside a
COLMAP model's own intrinsics (pixels)."""

from __future__ import annotations

from typing import TYPE_CHECKING, TextIO

from .output import warn

if TYPE_CHECKING:
    from ..intrinsics.results import CameraCalibration, SkippedGroup


def print_table(results: list[CameraCalibration], skipped: list[SkippedGroup], out: TextIO) -> None:
    """One line per camera group to ``out``; warnings and skipped groups to stderr."""
    from ..database.camera_groups import format_ids

    print(
        f"{'camera':>6} {'model':<14} {'method':<11} {'fx':>10} {'fy':>10} {'cx':>10} "
        f"{'cy':>10} {'triplets':>9} {'time':>7} {'ids':>4}",
        file=out,
    )
    for r in results:
        print(
            f"{r.camera_id:>6} {r.model:<14} {r.method:<11} {r.fx:>10.2f} {r.fy:>10.2f} "
            f"{r.cx:>10.2f} {r.cy:>10.2f} {r.num_inlier_triplets:>4}/{r.num_triplets:<4} "
            f"{r.seconds:>6.1f}s {len(r.camera_ids):>4}",
            file=out,
        )
        stds = [r.std[name] for name in ("fx", "fy", "cx", "cy")]
        cells = "".join(f" {'' if v is None else f'± {v:.2f}':>10}" for v in stds)
        print(f"{'':>6} {'':<14} {'std':<11}{cells}", file=out)
        distortion = _distortion_line(r)
        if distortion is not None:
            print(f"{'':>6} {distortion}", file=out)
        if len(r.camera_ids) > 1:
            print(f"{'':>6} shared by camera ids {format_ids(r.camera_ids)}", file=out)
        warning = r.warning()
        if warning is not None:
            warn(warning)
    for group in skipped:
        warn(group.message())


def print_comparisons(results: list[CameraCalibration], out: TextIO) -> None:
    """Each group's estimate (± std) beside the model's own intrinsics, to ``out``."""
    for r in results:
        print(f"\ncamera {r.camera_id}: the estimate beside the model's own intrinsics", file=out)
        print(r.compare_with_model(), file=out)


def _distortion_line(result: CameraCalibration) -> str | None:
    """The estimated distortion with its std (COLMAP's parameter order), or None where
    the stored distortion was kept."""
    from ..database.cameras import CameraInfo

    lens = result.lens_distortion
    if result.distortion is None or lens is None:
        return None
    names = CameraInfo.blank(lens["camera_model"]).distortion_names
    stds = lens.get("std") or [None] * len(result.distortion)
    parts = [
        f"{name} {value:+.4f}" + ("" if std is None else f" ± {std:.4f}")
        for name, value, std in zip(names, result.distortion, stds, strict=False)
    ]
    return f"distortion ({lens['camera_model']}): " + ", ".join(parts)
