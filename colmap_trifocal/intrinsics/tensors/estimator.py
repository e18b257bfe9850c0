"""The tensors stage: one trifocal tensor per triplet, estimated once and reused.

Each triplet's tensor is first refined from one start, the best MSAC hypothesis
(:func:`..geometry.tensor_estimation.fit_triplet` with ``second_start=False``). Only
the tensors that disagree with the solve's estimate get the second start, the
calibrated hypothesis, refined as well (it matters where the first ends in a
plane-dominated local minimum); at the same K the fit made then is completed, not
made again. When the calibration
moves to a new start K, the tensors that agree with K are carried over exactly
(:meth:`..geometry.tensor_estimation.TripletTensor.renormalised`) and only the
others are estimated again from K.

Every triplet keeps its own seed, so the result does not depend on the order or the
number of workers. A call of at least ``MIN_STARTS_IN_PROCESSES`` starts runs its fits
in the calling thread and forked worker processes where that is safe
(:func:`..common.parallel.map_jobs`): each is Python-bound numpy that threads cannot
run side by side. The work is counted in refinement starts and bounded by
``MAX_STARTS_PER_TRIPLET`` per triplet.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from ...common.errors import NoEstimate
from ...common.log import logger
from ...common.parallel import map_jobs
from ...geometry.tensor_estimation import TripletTensor
from ...geometry.trifocal import intrinsics_matrix
from ...geometry.triplet_fit import TripletFit, fit_triplet
from ..inputs.triplet_selection import CameraTracks
from ..options import CalibrationOptions
from ..solve.constraints import ConstraintProblem
from ..solve.theta import intrinsics_to_theta

#: Refinement starts per triplet over one camera's calibration: a restart, another
#: start or second starts are run only while they fit (the first start always runs).
MAX_STARTS_PER_TRIPLET = 8
#: Refinement starts from which one call's fits go to forked worker processes (threads
#: below): every call of two or more. A start is 6–70 ms of GIL-bound numpy on the real
#: scenes, and two threads run two starts no faster than one; a fork costs 1–3 ms and a
#: few thousand copy-on-write faults (0.01–0.02 s), less than the half of a 3–6 start
#: call another core takes (on entry-P10's first six starts and the ring's three, in a
#: fresh process and in a long-lived one; docs/accuracy.md, thirty-second session).
MIN_STARTS_IN_PROCESSES = 2


@dataclass
class TensorSet:
    """The tensors of one camera's triplets, normalised by ``start``.

    Attributes:
        start: (fx0, fy0, cx0, cy0) of the normalisation, pixels.
        by_triplet: per selected triplet, its tensor (None where none was found).
        both_starts: per triplet, whether its tensor was refined from both starts.
    """

    start: np.ndarray
    by_triplet: list[TripletTensor | None]
    both_starts: np.ndarray

    @property
    def positions(self) -> list[int]:
        """Positions (among the triplets) of the tensors that exist."""
        return [p for p, t in enumerate(self.by_triplet) if t is not None]

    @property
    def tensors(self) -> list[TripletTensor]:
        """The tensors that exist, in triplet order (what the solve takes)."""
        return [t for t in self.by_triplet if t is not None]


@dataclass
class TensorEstimator:
    """Estimates one camera's tensors at a start K, reusing what it can.

    Attributes:
        tracks: the camera's triplets and tracks (pixels).
        camera_id: for messages.
        options: the tensor settings, workers, progress, ``tau``.
        seeds: one per triplet.
        starts_used: refinement starts run so far (the work done).
    """

    tracks: CameraTracks
    camera_id: int
    options: CalibrationOptions
    seeds: list[np.random.SeedSequence]
    starts_used: int = 0
    _cache: dict[tuple[Any, ...], TripletFit | None] = field(default_factory=dict, repr=False)

    @property
    def budget(self) -> int:
        """Refinement starts allowed in all (``MAX_STARTS_PER_TRIPLET`` per triplet)."""
        return MAX_STARTS_PER_TRIPLET * len(self.tracks.triplets)

    def can_afford(self, starts: int) -> bool:
        """Whether ``starts`` more refinement starts stay within the budget."""
        return self.starts_used + starts <= self.budget

    def charge(self, starts: int) -> None:
        """Count ``starts`` refinement starts run for this camera by another estimator
        (on the lens search's warped tracks) in this one's budget: one budget per camera."""
        self.starts_used += starts

    def at(self, start: np.ndarray, previous: TensorSet | None = None) -> TensorSet:
        """Tensors normalised by ``start``: those of ``previous`` that agree with
        ``start`` (whitened norm below τ there) carried over, the rest estimated.

        Raises:
            NoEstimate: no triplet gives a tensor.
        """
        count = len(self.tracks.triplets)
        by_triplet: list[TripletTensor | None] = [None] * count
        both = np.zeros(count, dtype=bool)
        todo = list(range(count))
        if previous is not None and previous.tensors:
            agree = self.agreeing(previous, start)
            K_old, K_new = intrinsics_matrix(previous.start), intrinsics_matrix(start)
            for position, ok in zip(previous.positions, agree, strict=True):
                if ok:
                    tensor = previous.by_triplet[position]
                    assert tensor is not None
                    by_triplet[position] = tensor.renormalised(K_old, K_new)
                    both[position] = previous.both_starts[position]
            todo = [p for p in todo if by_triplet[p] is None]
        for position, tensor in zip(
            todo, self._estimate(start, todo, second_start=False), strict=True
        ):
            by_triplet[position] = tensor
        found = sum(t is not None for t in by_triplet)
        logger.info("camera %d: %d of %d triplets gave a tensor", self.camera_id, found, count)
        if found == 0:
            raise NoEstimate(
                f"camera {self.camera_id}: no triplet gave a consistent trifocal tensor"
            )
        return TensorSet(np.asarray(start, float).copy(), by_triplet, both)

    def first(self, start: np.ndarray, count: int) -> TensorSet:
        """The tensors of the first ``count`` triplets alone at ``start`` (cached, so
        :meth:`at` from the same start reuses them)."""
        positions = list(range(min(count, len(self.tracks.triplets))))
        return TensorSet(
            np.asarray(start, float).copy(),
            self._estimate(start, positions, second_start=False),
            np.zeros(len(positions), dtype=bool),
        )

    def with_second_starts(self, tensors: TensorSet, disagree: np.ndarray) -> TensorSet | None:
        """``tensors`` with the disagreeing ones (bool per existing tensor) refined from
        both starts; None when that changes none of them (or the budget is spent)."""
        positions = [
            p
            for p, bad in zip(tensors.positions, disagree, strict=True)
            if bad and not tensors.both_starts[p]
        ]
        if not positions or not self.options.tensor.calibrated_start:
            return None
        if not self.can_afford(self._second_start_cost(tensors.start, positions)):
            logger.info("camera %d: tensor budget spent; no second starts", self.camera_id)
            return None
        by_triplet = list(tensors.by_triplet)
        both = tensors.both_starts.copy()
        changed = False
        for position, tensor in zip(
            positions, self._estimate(tensors.start, positions, second_start=True), strict=True
        ):
            both[position] = True
            if tensor is not None and not _same(tensor, by_triplet[position]):
                by_triplet[position] = tensor
                changed = True
        if not changed:
            return None
        return TensorSet(tensors.start, by_triplet, both)

    def agreeing(self, tensors: TensorSet, intrinsics: np.ndarray) -> np.ndarray:
        """(n,) bool per existing tensor: whitened constraint norm below τ at ``intrinsics``."""
        theta = intrinsics_to_theta(np.asarray(intrinsics, float), tensors.start)
        norms = ConstraintProblem.build(tensors.tensors, theta).norms(theta)
        return np.asarray(norms < self.options.tau)

    def _estimate(
        self, start: np.ndarray, positions: list[int], *, second_start: bool
    ) -> list[TripletTensor | None]:
        """The tensors of the triplets at ``positions`` from ``start`` (cached). A second
        start completes the first start's fit at the same K where there is one (its
        deferred start alone: one refinement start), else fits from scratch (two)."""
        key = self._key(start)
        missing = [p for p in positions if (key, p, second_start) not in self._cache]
        K0 = intrinsics_matrix(start)
        jobs: list[Callable[[], TripletFit | None]] = []
        starts = 0
        for p in missing:
            starts += self._starts(key, p, second_start=second_start)
            first = self._cache.get((key, p, False)) if second_start else None
            if first is not None:
                jobs.append(first.with_second_start)
            else:
                jobs.append(partial(self._fit, p, K0, second_start=second_start))
        self.starts_used += starts
        fits = map_jobs(
            _call,
            jobs,
            self.options.workers,
            f"camera {self.camera_id}: tensors",
            progress=self.options.progress,
            processes=starts >= MIN_STARTS_IN_PROCESSES,
        )
        for p, fit in zip(missing, fits, strict=True):
            self._cache[(key, p, second_start)] = fit
        return [_tensor(self._cache[(key, p, second_start)]) for p in positions]

    def _second_start_cost(self, start: np.ndarray, positions: list[int]) -> int:
        """Refinement starts that second starts at ``positions`` from ``start`` take."""
        key = self._key(start)
        return sum(self._starts(key, p, second_start=True) for p in positions)

    def _starts(self, key: tuple[Any, ...], position: int, *, second_start: bool) -> int:
        """Refinement starts one fit takes at the start of ``key``: a first start 1; a
        second start 1 where it completes the first start's fit (0 where that deferred
        nothing), 2 where it fits from scratch."""
        if not second_start:
            return 1
        first = self._cache.get((key, position, False))
        return 2 if first is None else int(first.deferred is not None)

    def _fit(self, position: int, K0: np.ndarray, *, second_start: bool) -> TripletFit | None:
        """One triplet's fit from K0; its own seed makes it independent of scheduling."""
        return fit_triplet(
            self.tracks.triplets[position].image_ids,
            self.tracks.tracks[position],
            K0,
            np.random.default_rng(self.seeds[position]),
            self.options.tensor,
            second_start=second_start,
        )

    @staticmethod
    def _key(start: np.ndarray) -> tuple[Any, ...]:
        """The cache key of a start K (fx, fy, cx, cy), to 1e-9 px."""
        return tuple(np.round(np.asarray(start, float), 9))


def _same(a: TripletTensor, b: TripletTensor | None) -> bool:
    """Whether two tensors are the same fit (identical cameras)."""
    return b is not None and np.array_equal(a.P2, b.P2) and np.array_equal(a.P3, b.P3)


def _call(job: Callable[[], TripletFit | None]) -> TripletFit | None:
    """Runs one job of :meth:`TensorEstimator._estimate`."""
    return job()


def _tensor(fit: TripletFit | None) -> TripletTensor | None:
    """A fit's tensor (None without a fit)."""
    return None if fit is None else fit.tensor
