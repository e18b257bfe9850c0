"""Cost of checking a binary COLMAP model against its header counts (issue 15, item 6).

Writes a pycolmap synthetic model with many points, then times
``check_binary_model`` (the walk of cameras.bin and images.bin, the size of
points3D.bin) against pycolmap's own read of the same folder, and shows what the
check reports for an empty and a truncated ``points3D.bin`` (pycolmap itself grew to
several GB on those).

    python benchmarks/model_check.py --frames 60 --points 100000 --out /tmp/model_check
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import pycolmap

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.database.model_files import check_binary_model


def _seconds(function, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--points", type=int, default=100000)
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "model_check")
    args = parser.parse_args()
    model = args.out / "model"
    shutil.rmtree(args.out, ignore_errors=True)
    model.mkdir(parents=True)
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_cameras_per_rig=1,
        num_frames_per_rig=args.frames,
        num_points3D=args.points,
    )
    with pycolmap.Database.open(str(args.out / "database.db")) as db:
        pycolmap.synthesize_dataset(options, db).write(str(model))
    sizes = {p.name: p.stat().st_size for p in sorted(model.glob("*.bin"))}
    print(f"model: {args.frames} images, {args.points} points; bytes: {sizes}")
    check = _seconds(lambda: check_binary_model(model))
    read = _seconds(lambda: pycolmap.Reconstruction(str(model)), repeats=1)
    print(f"check_binary_model: {check * 1000:.1f} ms; pycolmap read: {read * 1000:.0f} ms")
    points = model / "points3D.bin"
    data = points.read_bytes()
    for label, content in (("empty", b""), ("cut in half", data[: len(data) // 2])):
        points.write_bytes(content)
        start = time.perf_counter()
        try:
            check_binary_model(model)
            outcome = "accepted"
        except CalibrationError as exc:
            outcome = f"refused: {exc}"
        print(f"points3D.bin {label}: {(time.perf_counter() - start) * 1000:.1f} ms, {outcome}")
    points.write_bytes(data)


if __name__ == "__main__":
    main()
