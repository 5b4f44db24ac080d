"""Client side of the simulated camera: grab the next fresh frame together with its ground truth.

The sim camera publishes `camera/image_raw`, `sim/object_mask` and `sim/object_pose` with one shared
stamp per frame; `SimCameraClient.next_frame(after_s)` waits for the first complete set stamped at
or after `after_s` (e.g. the moment the plate settled), so a caller never gets a stale frame.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from n2d_common.errors import DeviceError
from n2d_common.frames import R_from_quat, make_T
from n2d_common.ros import SENSOR_QOS, LiveSubscription, image_rgb, stamp_seconds


@dataclass
class SimObservation:
    """One camera frame of the simulator with its ground truth."""

    stamp_s: float
    """Header stamp (seconds): when the scene looked like this."""
    rgb: np.ndarray
    """HxWx3 uint8 image as published (with sensor noise)."""
    mask: np.ndarray
    """HxW bool exact object mask."""
    T_cam_obj: np.ndarray
    """4x4 object model frame -> camera optical frame (metres)."""
    K: np.ndarray
    """3x3 intrinsics from camera_info."""


class SimCameraClient:
    """Subscribes (on `node`) to the sim camera topics under `namespace` and pairs them by stamp."""

    def __init__(self, node: Node, namespace: str = "/n2d", keep: int = 8):
        self._lock = threading.Condition()
        self._parts: OrderedDict[int, dict] = OrderedDict()
        self._keep = keep
        self.K: np.ndarray | None = None
        ns = namespace.rstrip("/")
        self._subs = [
            LiveSubscription(node, Image, f"{ns}/camera/image_raw", lambda m: self._add(m.header.stamp, "rgb", m)),
            LiveSubscription(node, Image, f"{ns}/sim/object_mask", lambda m: self._add(m.header.stamp, "mask", m)),
            LiveSubscription(node, CameraInfo, f"{ns}/camera/camera_info", self._on_info),
        ]
        node.create_subscription(PoseStamped, f"{ns}/sim/object_pose",
                                 lambda m: self._add(m.header.stamp, "pose", m), SENSOR_QOS)

    def _on_info(self, msg: CameraInfo) -> None:
        self.K = np.array(msg.k, dtype=float).reshape(3, 3)

    def _add(self, stamp, part: str, msg) -> None:
        key = stamp.sec * 1_000_000_000 + stamp.nanosec
        with self._lock:
            self._parts.setdefault(key, {})[part] = msg
            while len(self._parts) > self._keep:
                self._parts.popitem(last=False)
            self._lock.notify_all()

    def next_frame(self, after_s: float, timeout_s: float = 30.0) -> SimObservation:
        """The first complete frame stamped at or after `after_s`; DeviceError if none comes in time."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                for key, parts in self._parts.items():
                    if key * 1e-9 >= after_s and len(parts) == 3 and self.K is not None:
                        return self._observation(parts)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceError(f"no simulated camera frame after t={after_s:.3f} within {timeout_s:.0f} s",
                                      "is the sim camera running (n2d sim) on this ROS_DOMAIN_ID?")
                self._lock.wait(min(left, 0.5))

    def _observation(self, parts: dict) -> SimObservation:
        pose = parts["pose"].pose
        T = make_T(R_from_quat([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]),
                   [pose.position.x, pose.position.y, pose.position.z])
        mask_msg = parts["mask"]
        mask = np.frombuffer(mask_msg.data, np.uint8).reshape(mask_msg.height, mask_msg.step)[:, :mask_msg.width]
        return SimObservation(stamp_seconds(parts["rgb"].header.stamp), image_rgb(parts["rgb"]), mask > 0, T,
                              self.K.copy())
