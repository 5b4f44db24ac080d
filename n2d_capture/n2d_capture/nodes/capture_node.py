"""capture_node: the `capture` action: sweep the turntable, write a posed, masked capture session.

Turns the plate through turntable_node's `turntable/rotate` action and takes frames from any camera
driver's `image` + `camera_info` topics (remap them). A goal with `empty_plate: true` records the
empty-plate background sweep and leaves the session unfinished; place the object and send the
normal goal, which records (or resumes) the object sweep, computes poses and masks and publishes
the session. One goal at a time; cancel stops after the current view and keeps what was taken.
With `placements: 2` (in the goal's config_yaml) the goal sweeps the object, then publishes feedback with
stage `turn_over` (repeated every `turn_over_feedback_s`) and waits for the object to be turned over: the
service `capture/continue` (std_srvs/Trigger) resumes it, and it sweeps placement 2 into the same session.
Cancel works while it waits; a goal sent again after a cancel or a crash resumes in the right placement.
Parameters are the fields of `CaptureConfig` (sweep, board, masks, intrinsics) plus the topics.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_srvs.srv import Trigger

from n2d_capture.capture import TURN_OVER, CaptureConfig, capture
from n2d_capture.nodes.ros_io import RosFrameSource, RosRotator
from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.errors import Cancelled
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
    turn_over_feedback_s: float = 2.0
    """While a goal waits for the object to be turned over, its `turn_over` feedback is repeated this often (s)."""

    def __post_init__(self):
        if self.turn_over_feedback_s <= 0:
            raise ValueError("turn_over_feedback_s must be > 0")


class CaptureNode(Node):
    NAME = "capture"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, CaptureNodeConfig)
        self.jobs = JobActionServer(self, Capture, "capture", self.run_goal, accept=lambda g: bool(g.session_dir),
                                    feedback=self._feedback)
        self.rotator = RosRotator(self, self.cfg.rotate_action, self.jobs.cancel)
        self._turned = threading.Event()
        self.create_service(Trigger, "capture/continue", self.on_continue, callback_group=ReentrantCallbackGroup())
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

    def on_continue(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """capture/continue: the object was turned over; the waiting goal sweeps its next placement."""
        waiting = self.jobs.state == "running" and getattr(self.jobs.progress, "stage", "") == TURN_OVER
        response.success = waiting
        response.message = ("continuing with the next placement" if waiting
                            else "no capture is waiting for the object to be turned over")
        if waiting:
            self._turned.set()
        return response

    def _wait_turned_over(self, placement: int, progress, cancel: threading.Event) -> None:
        """Until capture/continue is called (the `turn_over` feedback repeated meanwhile), or Cancelled."""
        ask = self.jobs.progress
        self.get_logger().info(f"{ask.message}: ros2 service call {self.resolve_service_name('capture/continue')} "
                               "std_srvs/srv/Trigger")
        while not self._turned.wait(self.cfg.turn_over_feedback_s):
            if cancel.is_set():
                raise Cancelled(f"capture cancelled while waiting for placement {placement + 1}",
                                "send the goal again to resume: it waits for the object to be turned over again")
            progress(ask)
        self._turned.clear()

    def run_goal(self, goal: Capture.Goal, result: Capture.Result, progress, cancel) -> None:
        result.session_dir = goal.session_dir
        cfg = self._goal_config(goal)
        self._turned.clear()
        # Subscribed only while a sweep runs: an idle node costs the camera driver and this machine nothing.
        camera = RosFrameSource(self, self.cfg.image_topic, self.cfg.camera_info_topic, self.cfg.use_header_stamp)
        try:
            summary = capture(goal.session_dir, cfg, self.rotator, camera, empty_plate=goal.empty_plate,
                              overwrite=goal.overwrite, progress=progress, cancel=cancel,
                              turn_over=lambda placement: self._wait_turned_over(placement, progress, cancel))
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
