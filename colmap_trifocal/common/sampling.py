"""Deterministic subsets of tracks and matches."""

from __future__ import annotations

import numpy as np


def evenly_spaced(count: int, at_most: int) -> np.ndarray:
    """Indices (≤ ``at_most``,) of ``count`` items, evenly spaced over them (all of them
    when there are at most ``at_most``): a subset that bounds the cost of a RANSAC or an
    adjustment, reaches every part of the list, and is the same on every run."""
    if count <= at_most:
        return np.arange(count)
    return np.linspace(0, count - 1, at_most).round().astype(int)
