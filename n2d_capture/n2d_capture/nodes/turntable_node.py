"""turntable_node: the Dynamixel turntable on ROS 2 (a real servo or the emulated one, unchanged).

Publishes `turntable/joint_states` (sensor_msgs/JointState, joint `turntable_plate`, plate angle in
rad, multi-turn) at `joint_state_rate_hz` and serves the `turntable/rotate` action
(n2d_interfaces/Rotate: feedback with angle, progress, stage and ETA; cancel brakes the plate).
One goal at a time: a second goal while the plate moves is rejected. Parameters are the fields of
`TurntableConfig` (port, baud, servo_id, protocol, gear_ratio, velocity_limit_rad_s, ...).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import JointState

from n2d_capture.turntable import Turntable, TurntableConfig
from n2d_common.errors import Cancelled, DeviceError, N2DError
from n2d_common.ros import PUBLISH_QOS, declare_config, run_node
from n2d_interfaces.action import Rotate


@dataclass
class TurntableNodeConfig:
    """Parameters of turntable_node."""

    ROS_PARAMETERS = ("turntable.port", "turntable.baud", "turntable.servo_id", "turntable.protocol",
                      "turntable.gear_ratio", "turntable.velocity_limit_rad_s", "turntable.acceleration_rad_s2",
                      "turntable.zero_offset_rad", "turntable.retries", "joint_state_rate_hz", "joint_name")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    turntable: TurntableConfig = field(default_factory=TurntableConfig)
    """The servo and its motion profile."""
    joint_state_rate_hz: float = 20.0
    """Rate of turntable/joint_states."""
    joint_name: str = "turntable_plate"
    """Joint name in the JointState messages."""
    connect_timeout_s: float = 5.0
    """Keep trying to open the servo this long at start-up (the adapter or simulator may come up later)."""

    def __post_init__(self):
        if not 0 < self.joint_state_rate_hz <= 200:
            raise ValueError("joint_state_rate_hz must be in (0, 200]")


class TurntableNode(Node):
    NAME = "turntable"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, TurntableNodeConfig)
        self.turntable = self._connect()
        self._busy = threading.Lock()
        self._cancel: threading.Event | None = None
        self.state_pub = self.create_publisher(JointState, "turntable/joint_states", PUBLISH_QOS)
        self.create_timer(1.0 / self.cfg.joint_state_rate_hz, self.on_timer,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.rotate_server = ActionServer(self, Rotate, "turntable/rotate", execute_callback=self.execute_rotate,
                                          goal_callback=self.on_goal, cancel_callback=self.on_cancel,
                                          callback_group=ReentrantCallbackGroup())
        self.get_logger().info(f"turntable servo {self.turntable.model_number} id {self.cfg.turntable.servo_id} "
                               f"on {self.cfg.turntable.port} at {math.degrees(self.turntable.angle()):.1f} deg")

    def _connect(self) -> Turntable:
        deadline = time.monotonic() + self.cfg.connect_timeout_s
        while True:
            try:
                return Turntable(self.cfg.turntable).open()
            except DeviceError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.25)

    def on_timer(self) -> None:
        try:
            angle = self.turntable.angle()
        except N2DError as exc:
            self.get_logger().error(str(exc), throttle_duration_sec=5.0)
            return
        msg = JointState()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.name = [self.cfg.joint_name]
        msg.position = [angle]
        self.state_pub.publish(msg)

    def on_goal(self, goal: Rotate.Goal) -> GoalResponse:
        if not math.isfinite(goal.angle_rad) or goal.velocity_rad_s < 0 or self._busy.locked():
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def on_cancel(self, _goal_handle) -> CancelResponse:
        if self._cancel is not None:
            self._cancel.set()
        return CancelResponse.ACCEPT

    def execute_rotate(self, goal_handle) -> Rotate.Result:
        goal = goal_handle.request
        result = Rotate.Result()
        if not self._busy.acquire(blocking=False):  # two goals accepted at once: the second does not move
            goal_handle.abort()
            result.message = "another rotation is running"
            return result
        self._cancel = threading.Event()

        def feedback(angle: float, fraction: float, stage: str, eta_s: float) -> None:
            goal_handle.publish_feedback(Rotate.Feedback(angle_rad=angle, progress=fraction, stage=stage,
                                                         eta_s=eta_s))

        try:
            target = goal.angle_rad + (self.turntable.angle() if goal.relative else 0.0)
            result.angle_rad = self.turntable.rotate_to(target, goal.velocity_rad_s or None, feedback, self._cancel)
            result.success = True
            goal_handle.succeed()
        except Cancelled as exc:
            result.message, result.angle_rad = str(exc), self.turntable.angle()
            goal_handle.canceled()
        except N2DError as exc:
            result.message = str(exc)
            self.get_logger().error(result.message)
            goal_handle.abort()
        finally:
            self._cancel = None
            self._busy.release()
        return result

    def destroy_node(self) -> None:
        self.rotate_server.destroy()
        self.turntable.close()
        super().destroy_node()


def main(args=None) -> None:
    run_node(TurntableNode, args)


if __name__ == "__main__":
    main()
