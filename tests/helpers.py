"""Small helpers shared by the test files (import as `from helpers import ...`)."""

import time


def wait_future(future, timeout_s: float = 30.0, poll_s: float = 0.01):
    """The result of an rclpy future that a background executor completes; fails the test after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not future.done():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(poll_s)
    return future.result()
