"""Progress of long jobs: one small record that the CLI shows as a bar and the ROS nodes send as feedback."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class Progress:
    """Where a job stands."""

    fraction: float
    """Done so far, 0..1."""
    stage: str
    """Short phase name, e.g. "rotating", "rendering"."""
    eta_s: float = -1.0
    """Seconds left, -1 when unknown."""
    message: str = ""
    """One human line about the current step."""
    info: dict = field(default_factory=dict)
    """Stage-specific numbers (view index, loss, ...)."""

    def __post_init__(self):
        # ROS feedback fields are float32: a whole number here (eta -1) would kill the node that sends it.
        self.fraction, self.eta_s = float(self.fraction), float(self.eta_s)


ProgressFn = Callable[[Progress], None]


def no_progress(_: Progress) -> None:
    """A ProgressFn that ignores reports."""


class Eta:
    """Estimate seconds left from the fraction done, by linear extrapolation since the first report."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()
        self._f0: float | None = None

    def __call__(self, fraction: float) -> float:
        now = time.monotonic()
        if self._f0 is None:
            self._t0, self._f0 = now, fraction
            return -1.0
        done = fraction - self._f0
        if done <= 1e-9:
            return -1.0
        return max(0.0, (now - self._t0) / done * (1.0 - fraction))
