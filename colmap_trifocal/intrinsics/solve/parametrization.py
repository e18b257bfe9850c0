"""Which intrinsics the solver estimates, and how they map to its unknowns.

The constraint solver works on the relative corrections
``θ = (fx/fx0 − 1, fy/fy0 − 1, (cx − cx0)/fx0, (cy − cy0)/fy0)`` of a start
``(fx0, fy0, cx0, cy0)`` (pixels; see :mod:`intrinsics.solve.constraints`). Not every
parameter is always estimated:

* single-focal COLMAP models (``SIMPLE_PINHOLE``, ...) have ``fx = fy``;
* when the images do not determine a parameter (planar or forward motion, pure
  translation, see :mod:`intrinsics.solve.observability`), it is *tied* (``fy = fx``, square
  pixels) or *held* at the prior rather than estimated from noise.

A :class:`FreeParameters` names the estimated parameters; its
:class:`Parametrization` is the affine map ``θ = A p + b`` from the free unknowns ``p`` (k of them,
0 ≤ k ≤ 4) to θ. Columns of ``A`` are unit vectors for free parameters and
``(1, r, 0, 0)`` for a tied focal length (``r = fx0 / fy0``, so that
``fy = fx``); ``b`` holds the held parameters' θ and the tie's offset ``r − 1``.
``p = 0`` is the start (held parameters at their held values).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product
from typing import Literal

import numpy as np

PARAMETER_NAMES = ("fx", "fy", "cx", "cy")
FocalMode = Literal["free", "tied", "held"]


@dataclass(frozen=True)
class FreeParameters:
    """Which of (fx, fy, cx, cy) a solve estimates; the others are tied (``fy = fx``)
    or held at given values.

    Attributes:
        focal: ``"free"``: fx and fy; ``"tied"``: one focal length, ``fy = fx``;
            ``"held"``: both at their held values.
        cx, cy: whether the principal point coordinate is estimated (else held).
    """

    focal: FocalMode = "free"
    cx: bool = True
    cy: bool = True

    @property
    def dimension(self) -> int:
        """Number of free unknowns k."""
        return {"free": 2, "tied": 1, "held": 0}[self.focal] + int(self.cx) + int(self.cy)

    def includes(self, other: FreeParameters) -> bool:
        """Whether ``other`` estimates a subset of what these estimate."""
        order = {"free": 2, "tied": 1, "held": 0}
        return (
            order[other.focal] <= order[self.focal]
            and (self.cx or not other.cx)
            and (self.cy or not other.cy)
        )

    def parametrization(self, start: np.ndarray, held: np.ndarray) -> Parametrization:
        """The map ``θ = A p + b`` for tensors normalised by ``start``.

        Args:
            start: (fx0, fy0, cx0, cy0) the tensors were normalised with, pixels.
            held: (fx, fy, cx, cy) that held parameters keep, pixels (the prior).
        """
        fx0, fy0, cx0, cy0 = np.asarray(start, dtype=float)
        held_theta = np.array(
            [held[0] / fx0 - 1.0, held[1] / fy0 - 1.0, (held[2] - cx0) / fx0, (held[3] - cy0) / fy0]
        )
        columns: list[np.ndarray] = []
        offset = np.zeros(4)
        if self.focal == "free":
            columns += [np.eye(4)[0], np.eye(4)[1]]
        elif self.focal == "tied":
            ratio = fx0 / fy0
            columns.append(np.array([1.0, ratio, 0.0, 0.0]))
            offset[1] = ratio - 1.0
        else:
            offset[:2] = held_theta[:2]
        for index, free in ((2, self.cx), (3, self.cy)):
            if free:
                columns.append(np.eye(4)[index])
            else:
                offset[index] = held_theta[index]
        matrix = np.stack(columns, axis=1) if columns else np.zeros((4, 0))
        return Parametrization(matrix, offset)

    def assumptions(self) -> list[str]:
        """What is assumed instead of estimated, e.g. ``["fy = fx"]``."""
        notes = []
        if self.focal == "tied":
            notes.append("fy = fx")
        elif self.focal == "held":
            notes.append("fx, fy held at the prior")
        held_pp = [name for name, free in (("cx", self.cx), ("cy", self.cy)) if not free]
        if held_pp:
            notes.append(f"{', '.join(held_pp)} held at the prior")
        return notes

    def estimated(self, *, single_focal: bool) -> dict[str, bool]:
        """Per parameter: determined by the data when these are estimated.

        A tied fy counts as estimated only for single-focal camera models, where
        ``fy = fx`` is the camera model itself rather than an assumption.
        """
        focal_free = self.focal == "free" or (self.focal == "tied" and single_focal)
        return {
            "fx": self.focal != "held",
            "fy": focal_free,
            "cx": self.cx,
            "cy": self.cy,
        }


#: What cameras with two focal lengths, and single-focal ones, can estimate at most.
FULL = FreeParameters("free")
SINGLE_FOCAL = FreeParameters("tied")
#: Nothing estimated: everything held.
HELD = FreeParameters("held", cx=False, cy=False)


def candidate_free_parameters(base: FreeParameters) -> list[FreeParameters]:
    """Every subset of ``base``, largest first (base included)."""
    focals: tuple[FocalMode, ...] = ("free", "tied", "held")
    subsets = [
        FreeParameters(focal, cx, cy)
        for focal, cx, cy in product(focals, (True, False), (True, False))
    ]
    return sorted((m for m in subsets if base.includes(m)), key=lambda m: -m.dimension)


@dataclass(frozen=True)
class Parametrization:
    """``θ = A p + b``: A (4, k), b (4,)."""

    matrix: np.ndarray
    offset: np.ndarray

    @property
    def dimension(self) -> int:
        return int(self.matrix.shape[1])

    def theta(self, free: np.ndarray) -> np.ndarray:
        """θ (..., 4) from free unknowns p (..., k)."""
        return np.asarray(free @ self.matrix.T + self.offset)

    def free(self, theta: np.ndarray) -> np.ndarray:
        """The p (..., k) whose θ is closest to ``theta`` (..., 4) (exact where θ is
        reachable: tied and held parameters at their values)."""
        pseudo_inverse = np.linalg.pinv(self.matrix) if self.dimension else np.zeros((0, 4))
        return np.asarray((theta - self.offset) @ pseudo_inverse.T)

    def covariance(self, covariance_free: np.ndarray) -> np.ndarray:
        """Covariance (4, 4) of θ from that of p (k, k)."""
        return np.asarray(self.matrix @ covariance_free @ self.matrix.T)
