"""Wall-clock seconds per stage of a calibration, for the report and ``-v``."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

#: The stages of one camera's calibration, in the order they run.
STAGES = (
    "read",
    "tracks",
    "focal_search",
    "tensors",
    "solve",
    "lens_search",
    "polish",
    "assessment",
)


class StageClock:
    """Accumulates wall seconds (``time.perf_counter``) per stage name.

    A stage entered several times (the tensors of a second start) adds up. ``total``
    is the sum of the stages; :meth:`as_dict` lists every stage of ``STAGES`` (0 for
    one that did not run) and then ``total``.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        """Time the block as ``stage``."""
        begin = time.perf_counter()
        try:
            yield
        finally:
            self.add(stage, time.perf_counter() - begin)

    def add(self, stage: str, seconds: float) -> None:
        """Add ``seconds`` to ``stage``."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds

    @property
    def total(self) -> float:
        """Seconds over all stages."""
        return float(sum(self.seconds.values()))

    def as_dict(self) -> dict[str, float]:
        """``{stage: seconds, ..., "total": seconds}`` (rounded to 0.1 ms)."""
        names = [*STAGES, *sorted(set(self.seconds) - set(STAGES))]
        data = {name: round(self.seconds.get(name, 0.0), 4) for name in names}
        data["total"] = round(self.total, 4)
        return data

    def summary(self) -> str:
        """One line: ``tracks 0.12 s, focal_search 0.30 s, ...`` (stages that ran)."""
        return ", ".join(
            f"{name} {seconds:.2f} s" for name, seconds in self.seconds.items() if seconds > 0
        )
