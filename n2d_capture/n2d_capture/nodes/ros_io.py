"""ROS adapters of the capture sweep: frames from any Image + CameraInfo pair, rotation via the Rotate action.

`RosFrameSource` keeps the newest few frames of an image topic (best-effort, keep-last: a live
stream is never queued) and hands out the first one exposed after a given time. `RosRotator`
turns the plate through `turntable/rotate`, so the capture node never touches the serial port.
Both block the calling (worker) thread, never an executor thread.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from n2d_common.camera import Frame
from n2d_common.errors import Cancelled, DeviceError, N2DError
from n2d_common.ros import LiveSubscription, SafeActionClient, call_action, image_rgb, stamp_seconds
from n2d_interfaces.action import Rotate


class RosFrameSource:
    """Frames of `image_topic`; K and distortion from `camera_info_topic`."""

    def __init__(self, node: Node, image_topic: str, camera_info_topic: str, use_header_stamp: bool = True):
        self._frames: deque[tuple[float, Image]] = deque(maxlen=4)
        self._info: CameraInfo | None = None
        self._cond = threading.Condition()
        self._use_header = use_header_stamp
        self.topic = node.resolve_topic_name(image_topic)
        self._subs = [LiveSubscription(node, Image, image_topic, self._on_image),
                      LiveSubscription(node, CameraInfo, camera_info_topic, self._on_info)]

    def close(self) -> None:
        """Unsubscribe (a node that only needs frames during a sweep stops receiving them)."""
        for sub in self._subs:
            sub.destroy()
        self._subs = []

    def _on_image(self, msg: Image) -> None:
        stamp = stamp_seconds(msg.header.stamp) if self._use_header else time.time()
        with self._cond:
            self._frames.append((stamp, msg))
            self._cond.notify_all()

    def _on_info(self, msg: CameraInfo) -> None:
        self._info = msg

    def grab(self, after_s: float, timeout_s: float) -> Frame:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                for stamp, msg in self._frames:
                    if stamp >= after_s:
                        info = self._info
                        K = None if info is None else np.array(info.k, dtype=float).reshape(3, 3)
                        dist = None if info is None else np.array(info.d, dtype=float)
                        return Frame(image_rgb(msg), stamp, K, dist)
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = f"last frame {time.time() - self._frames[-1][0]:.1f} s ago" if self._frames else "no frame"
                    raise DeviceError(f"no fresh image on {self.topic} within {timeout_s:.0f} s ({seen})",
                                      "check that the camera driver publishes (ros2 topic hz) and its clock")
                self._cond.wait(min(left, 0.5))


class RosRotator:
    """Turns the plate through the `Rotate` action of turntable_node."""

    def __init__(self, node: Node, action: str, cancel: threading.Event | None = None,
                 server_timeout_s: float = 20.0, move_timeout_s: float = 120.0):
        self.client = SafeActionClient(node, Rotate, action)
        self.cancel = cancel
        self.server_timeout_s = server_timeout_s
        self.move_timeout_s = move_timeout_s

    def rotate_to(self, angle_rad: float) -> float:
        try:
            result = call_action(self.client, Rotate.Goal(angle_rad=angle_rad), what="turntable", cancel=self.cancel,
                                 server_timeout_s=self.server_timeout_s, timeout_s=self.move_timeout_s)
        except Cancelled:
            raise Cancelled("capture cancelled while the plate was turning", "run it again to resume") from None
        except DeviceError:
            raise
        except N2DError as exc:  # the turntable refused or failed the rotation: a device fault for the sweep
            raise DeviceError(exc.message, exc.hint) from None
        return result.angle_rad
