"""The simulated camera as an in-process `FrameSource`, for capture sweeps and benchmarks without ROS.

It renders the scene at the plate's true angle, read from the servo emulator when the frame is
grabbed, so a sweep driven through the real Dynamixel driver sees exactly what the servo did.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from n2d_common.camera import Frame
from n2d_sim.camera import SimCamera, SimFrame


class SimFrameSource:
    """`grab()` waits until `after_s`, reads the true plate angle, renders, adds sensor noise."""

    def __init__(self, camera: SimCamera, plate_angle: Callable[[], float], seed: int = 0):
        self.camera = camera
        self.plate_angle = plate_angle
        self.rng = np.random.default_rng(seed)
        self.object_visible = True
        self.last: SimFrame | None = None
        """Ground truth of the last grabbed frame."""

    def grab(self, after_s: float, timeout_s: float) -> Frame:
        while time.time() < after_s:
            time.sleep(0.001)
        stamp = time.time()
        self.last = self.camera.render(self.plate_angle(), object_visible=self.object_visible)
        return Frame(self.camera.noisy(self.last.rgb, self.rng), stamp, self.last.K, np.zeros(5))
