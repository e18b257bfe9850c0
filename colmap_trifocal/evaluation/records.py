"""One evaluated calibration (a method on one run), as stored in ``--json`` and the CSV."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

PARAMETER_NAMES = ("fx", "fy", "cx", "cy")


def mean_relative_error_percent(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Mean of |estimate / truth − 1| over (fx, fy, cx, cy), in percent (the paper's metric)."""
    return float(np.mean(np.abs(np.asarray(estimate) / np.asarray(truth) - 1.0)) * 100.0)


@dataclass
class RunRecord:
    """The outcome of one method on one run.

    Intrinsics are (fx, fy, cx, cy) in pixels, COLMAP pixel convention.
    """

    experiment: str  # "synthetic" or the dataset kind ("strecha", "blendedmvs", ...)
    scene: str
    method: str
    run: int
    seed: int
    num_images: int
    perturbation: str  # prior perturbation range in percent, e.g. "0-5"
    truth: list[float]
    prior: list[float]
    estimate: list[float] | None = None  # None when the method failed
    std: list[float | None] | None = None  # reported standard deviations, where available
    error_percent: float | None = None  # mean relative error of the estimate, percent
    seconds: float = 0.0
    noise_px: float | None = None  # synthetic keypoint noise (half-width, pixels)
    message: str = ""  # why the method failed
    extra: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.estimate is not None and self.error_percent is not None

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def finished(
        cls, estimate: np.ndarray | None, truth: np.ndarray, prior: np.ndarray, **fields
    ) -> RunRecord:
        """A record with the error computed (``estimate`` None: a failed run)."""
        return cls(
            truth=[float(v) for v in truth],
            prior=[float(v) for v in prior],
            estimate=None if estimate is None else [float(v) for v in estimate],
            error_percent=None
            if estimate is None
            else mean_relative_error_percent(estimate, truth),
            **fields,
        )
