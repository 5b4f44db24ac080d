"""Small helpers shared by the test files (import as `from helpers import ...`)."""

import time

import cv2


def wait_future(future, timeout_s: float = 30.0, poll_s: float = 0.01):
    """The result of an rclpy future that a background executor completes; fails the test after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not future.done():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(poll_s)
    return future.result()


def write_photos(folder, images, suffix):
    """Save RGB images as a camera would name them: IMG_0000<suffix>, ... (JPEG at quality 95)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, rgb in enumerate(images):
        assert cv2.imwrite(str(folder / f"IMG_{i:04d}{suffix}"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, 95])
    return folder
