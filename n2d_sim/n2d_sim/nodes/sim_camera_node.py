"""sim_camera_node: the simulated turntable camera, publishing like a camera driver plus ground truth.

Publishes (under its namespace) `camera/image_raw` (rgb8, sensor noise), `camera/camera_info`
(REP 103 optical frame, exact K), and the ground truth of each frame with the same stamp:
`sim/object_pose` (PoseStamped, T_cam_obj) and `sim/object_mask` (mono8, 255 = object).
It renders (in a bpy worker process) whenever the true plate angle on `sim/plate_state` changes.
The service `sim/set_object_visible` (std_srvs/SetBool) lifts the object off the plate and puts it
back: what a person does for the empty-plate background sweep. The service `sim/turn_over` (std_srvs/SetBool)
turns the object over between the sweeps of a two-placement capture: true lays it as the session's second
placement (`n2d_sim.session.SECOND_PLACEMENT_DEG` of the object, on its side or upside down), false back as
`world.placement_deg` says; `sim/object_pose` follows.
While the plate stands still it republishes the last render with fresh noise at `rate_hz` (while anyone
subscribes), stamped now; while it moves it publishes each finished render stamped with the time of the
angle it shows, so the rate drops during motion rather than showing an old scene with a new stamp.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_srvs.srv import SetBool

from n2d_common.ros import (
    PUBLISH_QOS,
    SENSOR_QOS,
    camera_info_msg,
    declare_config,
    image_msg,
    pose_msg,
    run_node,
    stamp_msg,
)
from n2d_sim.camera import SimCamera, SimFrame
from n2d_sim.session import turned
from n2d_sim.world import SimWorldConfig


@dataclass
class SimCameraNodeConfig:
    """Parameters of sim_camera_node."""

    ROS_PARAMETERS = ("world.object", "world.width", "world.height", "world.focal_px", "world.camera_distance_m",
                      "world.camera_elevation_deg", "world.board_visible", "world.samples", "world.device",
                      "world.threads", "world.clutter", "rate_hz", "frame_id", "noise_seed")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    world: SimWorldConfig = field(default_factory=SimWorldConfig)
    """The rendered world: object, camera, board, lights, noise."""
    rate_hz: float = 10.0
    """Publishing rate while the plate stands still (Hz)."""
    frame_id: str = "sim_camera_optical_frame"
    """frame_id of the images (OpenCV optical frame: x right, y down, z forward)."""
    noise_seed: int = 0
    """Seed of the sensor noise."""
    angle_epsilon_rad: float = 1e-5
    """Plate angle change that triggers a new render."""

    def __post_init__(self):
        if not 0 < self.rate_hz <= 100:
            raise ValueError("rate_hz must be in (0, 100]")


class SimCameraNode(Node):
    NAME = "sim_camera"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, SimCameraNodeConfig)
        self.rng = np.random.default_rng(self.cfg.noise_seed)
        self.image_pub = self.create_publisher(Image, "camera/image_raw", PUBLISH_QOS)
        self.info_pub = self.create_publisher(CameraInfo, "camera/camera_info", PUBLISH_QOS)
        self.pose_pub = self.create_publisher(PoseStamped, "sim/object_pose", PUBLISH_QOS)
        self.mask_pub = self.create_publisher(Image, "sim/object_mask", PUBLISH_QOS)
        self.create_subscription(JointState, "sim/plate_state", self.on_plate_state, SENSOR_QOS)
        self.create_service(SetBool, "sim/set_object_visible", self.on_set_visible)
        self.create_service(SetBool, "sim/turn_over", self.on_turn_over)
        self._changed = threading.Condition()
        self._angle: tuple[float, float] | None = None  # (angle_rad, stamp_s) of the latest plate state
        self._frame: SimFrame | None = None
        self._visible = True
        self._placement = self._frame_placement = self.cfg.world.placement_deg
        self._running = True
        self.camera = SimCamera(self.cfg.world)
        self.camera.start()
        self._renderer = threading.Thread(target=self._render_loop, daemon=True)
        self._renderer.start()
        self.create_timer(1.0 / self.cfg.rate_hz, self.on_timer)
        self.get_logger().info(f"rendering {self.cfg.world.object} at {self.cfg.world.width}x{self.cfg.world.height};"
                               " waiting for sim/plate_state")

    def on_plate_state(self, msg: JointState) -> None:
        with self._changed:
            self._angle = (float(msg.position[0]), msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
            self._changed.notify()

    def on_set_visible(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        with self._changed:
            self._visible = request.data
            self._changed.notify()
        response.success = True
        response.message = "object on the plate" if request.data else "object lifted off the plate"
        return response

    def on_turn_over(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        placement = (turned(self.cfg.world) if request.data else self.cfg.world).placement_deg
        self.camera.place(placement)  # waits for a render in progress
        with self._changed:
            self._placement = placement
            self._changed.notify()
        response.success = True
        response.message = f"object placed at {list(placement)} deg (x, y, z)"
        return response

    def _current(self, frame: SimFrame | None, angle: tuple[float, float] | None) -> bool:
        """Whether `frame` shows the scene as it is now."""
        return (frame is not None and angle is not None and frame.object_visible == self._visible
                and self._frame_placement == self._placement
                and abs(angle[0] - frame.angle_rad) < self.cfg.angle_epsilon_rad)

    def on_timer(self) -> None:
        frame, angle = self._frame, self._angle
        # Republishing 640x480 with fresh noise costs a third of a core: only while someone listens.
        watched = any(p.get_subscription_count() for p in (self.image_pub, self.pose_pub, self.mask_pub))
        if watched and self._current(frame, angle):
            self.publish(frame, time.time())

    def _render_loop(self) -> None:
        while self._running:
            with self._changed:
                while self._running and (self._angle is None or self._current(self._frame, self._angle)):
                    self._changed.wait(0.5)
                if not self._running:
                    return
                (angle, stamp), visible, placement = self._angle, self._visible, self._placement
            frame = self.camera.render(angle, object_visible=visible)
            with self._changed:
                if placement != self._placement:  # turned over while it rendered: render again
                    continue
                self._frame, self._frame_placement = frame, placement
            self.publish(frame, stamp)

    def publish(self, frame: SimFrame, stamp_s: float) -> None:
        stamp = stamp_msg(stamp_s)
        fid = self.cfg.frame_id
        self.info_pub.publish(camera_info_msg(frame.K, frame.rgb.shape[1], frame.rgb.shape[0], stamp, fid))
        self.mask_pub.publish(image_msg(frame.mask.astype(np.uint8) * 255, "mono8", stamp, fid))
        pose = PoseStamped()
        pose.header.stamp, pose.header.frame_id = stamp, fid
        pose.pose = pose_msg(frame.T_cam_obj)
        self.pose_pub.publish(pose)
        self.image_pub.publish(image_msg(self.camera.noisy(frame.rgb, self.rng), "rgb8", stamp, fid))

    def destroy_node(self) -> None:
        self._running = False
        with self._changed:
            self._changed.notify_all()
        self.camera.close()
        super().destroy_node()


def main(args=None) -> None:
    run_node(SimCameraNode, args)


if __name__ == "__main__":
    main()
