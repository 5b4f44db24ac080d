"""A camera image as the capture and the simulator hand it around: pixels, exposure time and, when the source
knows them, the intrinsics."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    """One camera image."""

    rgb: np.ndarray
    """HxWx3 uint8."""
    stamp_s: float
    """When it was exposed (seconds, the clock of `time.time()`)."""
    K: np.ndarray | None = None
    """3x3 intrinsics when the source knows them (CameraInfo), else None."""
    dist: np.ndarray | None = None
    """Distortion coefficients (OpenCV order) when known."""
