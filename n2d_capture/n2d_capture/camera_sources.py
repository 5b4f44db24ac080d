"""Frame sources without ROS: an OpenCV camera device or a video file, for `n2d capture --camera cv:...`."""

from __future__ import annotations

import time

import cv2

from n2d_common.camera import Frame
from n2d_common.errors import DeviceError

BUFFERED_READ_S = 0.005
"""A device read that returns faster than this came from the driver's buffer: an old frame."""


class OpenCVSource:
    """`grab()` returns the first frame read after `after_s`; buffered (stale) device frames are dropped.

    A video file has no clock: each grab returns its next frame. No intrinsics are known here
    (capture with `intrinsics: calibrate`, or import a calibration).
    """

    def __init__(self, device: str):
        self.device = device
        self.is_file = not device.isdigit()
        self.cap = cv2.VideoCapture(device if self.is_file else int(device))
        if not self.cap.isOpened():
            raise DeviceError(f"cannot open camera {device!r}",
                              "give a device index (cv:0) or a video file path that exists and is readable")

    def _read(self):
        ok, bgr = self.cap.read()
        if not ok:
            raise DeviceError(f"camera {self.device!r} returned no frame (end of the video, or unplugged)")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def grab(self, after_s: float, timeout_s: float) -> Frame:
        if self.is_file:
            return Frame(self._read(), time.time())
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            t0 = time.monotonic()
            rgb = self._read()
            now = time.time()
            if time.monotonic() - t0 > BUFFERED_READ_S and now >= after_s:
                return Frame(rgb, now)
        raise DeviceError(f"no fresh frame from camera {self.device!r} within {timeout_s:.0f} s")

    def close(self) -> None:
        self.cap.release()
