"""Is a change behaviour-identical? Every result of a fixed set of calibrations, saved or compared.

``--save FILE`` runs the set and writes each result's JSON (``to_json()`` without the
seconds); ``--compare FILE`` runs it again and lists every value that differs (numbers
beyond ``--rtol``, anything else by equality). Use it around a refactor: save on the
code before, compare on the code after.

The set: every real scene's two databases (``real_scenes.py``, cached in ``--out``) from
COLMAP's guess and from a ±5 % prior (seed 0), and the synthetic classes of
``cost.py``: the demo, the 1 %-relief facade, a straight drive, a 10° ring from the
default camera and the distorted drone survey, each with seeds ``--seeds``.

    python benchmarks/identity.py --save before.json [--real] [--seeds 0,1]
    python benchmarks/identity.py --compare before.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from colmap_trifocal import CalibrationOptions, calibrate_contents, calibrate_database
from colmap_trifocal.datasets.strecha import default_datasets_root
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.facade import facade_scene
from colmap_trifocal.synthetic.lenses import narrow_lens
from colmap_trifocal.synthetic.motions import forward_driving

BENCHMARKS = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCHMARKS))
from cost import drone_database, prior_5  # noqa: E402
from real import databases  # noqa: E402
from real_scenes import SCENES  # noqa: E402
from real_scenes import prior_5 as real_prior  # noqa: E402

#: Keys that are not behaviour: wall-clock seconds.
UNTIMED = ("seconds", "stage_seconds")


def cases(out: Path, seeds: list[int], real: bool) -> Iterator[tuple[str, list[dict[str, Any]]]]:
    """(name, the results' JSON) of every calibration of the set."""
    from colmap_trifocal.synthetic.demo import make_demo_database

    if real:
        root = default_datasets_root(BENCHMARKS.parent)
        for scene in SCENES:
            truth = scene.truth(root)
            for kind, database in databases(scene, root, out).items():
                for start, prior in (("guess", None), ("prior", real_prior(truth, 0))):
                    results = calibrate_database(database, CalibrationOptions(prior=prior))
                    yield f"{scene.name} {kind} {start}", [r.to_json() for r in results]
    demo = out / "demo.db"
    if not demo.exists():
        make_demo_database(demo, seed=0)
    for seed in seeds:
        options = CalibrationOptions(seed=seed)
        yield f"demo {seed}", [r.to_json() for r in calibrate_database(demo, options)]
        drone, _ = drone_database(out, seed)
        options = CalibrationOptions(seed=seed, no_prior=True)
        yield f"drone {seed}", [r.to_json() for r in calibrate_database(drone, options)]
        scenes = {
            "facade": facade_scene(relief=0.01, seed=seed, noise_px=1.0, num_points=1000),
            "straight": forward_driving(seed=seed, yaw_deg=0.0),
            "telephoto": narrow_lens(seed=seed),
        }
        for name, scene in scenes.items():
            if name == "telephoto":
                options = CalibrationOptions(seed=seed, no_prior=True)
            else:
                options = CalibrationOptions(seed=seed, prior=prior_5(scene.intrinsics, seed))
            results = calibrate_contents(scene_contents(scene), options)
            yield f"{name} {seed}", [r.to_json() for r in results]


def untimed(value: Any) -> Any:
    """``value`` without its wall-clock seconds, numbers as plain floats."""
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items() if k not in UNTIMED}
    if isinstance(value, list | tuple):
        return [untimed(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def differences(before: Any, after: Any, rtol: float, where: str = "") -> Iterator[str]:
    """Where ``after`` differs from ``before``."""
    if isinstance(before, dict) and isinstance(after, dict):
        for key in sorted(set(before) | set(after)):
            if key not in before or key not in after:
                yield f"{where}.{key}: only {'after' if key in after else 'before'}"
            else:
                yield from differences(before[key], after[key], rtol, f"{where}.{key}")
    elif isinstance(before, list) and isinstance(after, list):
        if len(before) != len(after):
            yield f"{where}: {len(before)} items before, {len(after)} after"
        for i, (b, a) in enumerate(zip(before, after, strict=False)):
            yield from differences(b, a, rtol, f"{where}[{i}]")
    elif isinstance(before, float | int) and isinstance(after, float | int):
        same = math.isclose(before, after, rel_tol=rtol, abs_tol=1e-12) or (
            math.isnan(before) and math.isnan(after)
        )
        if not same and not isinstance(before, bool):
            yield f"{where}: {before!r} -> {after!r}"
    elif before != after:
        yield f"{where}: {before!r} -> {after!r}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--save", type=Path)
    action.add_argument("--compare", type=Path)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--real", action="store_true", help="also every real scene")
    parser.add_argument("--rtol", type=float, default=1e-9)
    parser.add_argument("--out", type=Path, default=Path("benchmark_output/real"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.save:
        results = {}
        for name, result in cases(args.out, seeds, args.real):
            results[name] = untimed(result)
            print(name, flush=True)
        args.save.write_text(json.dumps(results, indent=1, default=float))
        return
    saved = json.loads(args.compare.read_text())
    changed = 0
    for name, result in cases(args.out, seeds, args.real):
        found = list(
            differences(
                saved.get(name), json.loads(json.dumps(untimed(result), default=float)), args.rtol
            )
        )
        changed += bool(found)
        print(f"{name}: {'identical' if not found else f'{len(found)} differences'}", flush=True)
        for line in found[:20]:
            print("   ", line)
    print(f"{changed} of the set changed")


if __name__ == "__main__":
    main()
