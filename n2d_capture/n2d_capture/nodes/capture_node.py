"""capture_node: the `capture` action: sweep the turntable, write a posed, masked capture session.

Turns the plate through turntable_node's `turntable/rotate` action and takes frames from any camera
driver's `image` + `camera_info` topics (remap them). A goal with `empty_plate: true` records the
empty-plate background sweep and leaves the session unfinished; place the object and send the
normal goal, which records (or resumes) the object sweep, computes poses and masks and publishes
the session. One goal at a time; cancel stops after the current view and keeps what was taken.
Parameters are the fields of `CaptureConfig` (sweep, board, masks, intrinsics) plus the topics.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
from rclpy.node import Node

from n2d_capture.capture import CaptureConfig, capture
from n2d_capture.nodes.ros_io import RosFrameSource, RosRotator
from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.progress import Progress
from n2d_common.ros import JobActionServer, declare_config, image_msg, run_node, stamp_msg
from n2d_interfaces.action import Capture


@dataclass
class CaptureNodeConfig:
    """Parameters of capture_node."""

    ROS_PARAMETERS = ("capture.sweep.views", "capture.board.squares_x", "capture.board.squares_y",
                      "capture.board.square_m", "capture.board.marker_m", "capture.board.dictionary",
                      "capture.intrinsics", "capture.pose_from", "image_topic", "camera_info_topic", "rotate_action",
                      "use_header_stamp", "preview_width")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    capture: CaptureConfig = field(default_factory=CaptureConfig)
    """Defaults of every capture (a goal's `views` and `config_yaml` override them)."""
    image_topic: str = "camera/image_raw"
    """Camera images (any encoding image_rgb reads: rgb8, bgr8, mono8, ...)."""
    camera_info_topic: str = "camera/camera_info"
    """Camera intrinsics."""
    rotate_action: str = "turntable/rotate"
    """turntable_node's Rotate action."""
    use_header_stamp: bool = True
    """Judge freshness by the image header stamp (false: by arrival time, for drivers with another clock)."""
    preview_width: int = 160
    """Width of the last-image preview in the feedback (px)."""


class CaptureNode(Node):
    NAME = "capture"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, CaptureNodeConfig)
        self.jobs = JobActionServer(self, Capture, "capture", self.run_goal, accept=lambda g: bool(g.session_dir),
                                    feedback=self._feedback)
        self.rotator = RosRotator(self, self.cfg.rotate_action, self.jobs.cancel)
        self.get_logger().info(f"capture ready: images from {self.resolve_topic_name(self.cfg.image_topic)}")

    def _goal_config(self, goal: Capture.Goal) -> CaptureConfig:
        data = to_dict(self.cfg.capture)
        if goal.views:
            data["sweep"]["views"] = goal.views
        return from_dict(CaptureConfig, merge(data, parse_mapping(goal.config_yaml, "goal config_yaml")))

    def _feedback(self, p: Progress) -> Capture.Feedback:
        fb = Capture.Feedback(progress=p.fraction, stage=p.stage, eta_s=p.eta_s, view=p.info.get("view", 0),
                              views_total=p.info.get("views", 0))
        if "image" in p.info:
            rgb = p.info["image"]
            h = round(rgb.shape[0] * self.cfg.preview_width / rgb.shape[1])
            small = cv2.resize(rgb, (self.cfg.preview_width, h), interpolation=cv2.INTER_AREA)
            fb.last_image = image_msg(small, "rgb8", stamp_msg(0.0), "")
        return fb

    def run_goal(self, goal: Capture.Goal, result: Capture.Result, progress, cancel) -> None:
        result.session_dir = goal.session_dir
        cfg = self._goal_config(goal)
        # Subscribed only while a sweep runs: an idle node costs the camera driver and this machine nothing.
        camera = RosFrameSource(self, self.cfg.image_topic, self.cfg.camera_info_topic, self.cfg.use_header_stamp)
        try:
            summary = capture(goal.session_dir, cfg, self.rotator, camera, empty_plate=goal.empty_plate,
                              overwrite=goal.overwrite, progress=progress, cancel=cancel)
        finally:
            camera.close()
        result.views_captured = summary["views"]
        result.message = summary.get("message", "")

    def destroy_node(self) -> None:
        self.jobs.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(CaptureNode, args)


if __name__ == "__main__":
    main()
