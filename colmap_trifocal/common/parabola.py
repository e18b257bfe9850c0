"""The minimum of a cost sampled on an evenly spaced grid, refined by a parabola."""

from __future__ import annotations


def parabola_step(before: float, centre: float, after: float) -> float:
    """Where the parabola through three evenly spaced costs has its minimum, in grid
    steps from the middle one (negative: towards ``before``); 0 where the three are not
    convex (the middle point is then kept)."""
    curvature = before - 2 * centre + after
    return 0.5 * (before - after) / curvature if curvature > 0 else 0.0
