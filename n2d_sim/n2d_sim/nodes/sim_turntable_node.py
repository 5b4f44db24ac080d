"""sim_turntable_node: the turntable's Dynamixel servo, emulated on a pseudo-terminal, plus its ground truth.

The real driver (`n2d_capture.turntable`, `dynamixel_sdk`) opens `port_link` as it would a U2D2
adapter. The node publishes the emulator's true plate angle on `sim/plate_state`
(sensor_msgs/JointState, joint `turntable_plate`), which the simulated camera renders from, and
serves fault injection (no reply, bad CRC, overload, disconnect) on `control_socket`.
"""

from __future__ import annotations

from dataclasses import dataclass

from rclpy.node import Node
from sensor_msgs.msg import JointState

from n2d_common.ros import PUBLISH_QOS, declare_config, run_node
from n2d_sim.servo import ControlServer, PtyServo, ServoEmulator


@dataclass
class SimTurntableConfig:
    """Parameters of sim_turntable_node."""

    port_link: str = "/tmp/n2d_sim/ttyDXL"
    """Path of the symlink to the emulated servo's pty: the driver's `port`."""
    control_socket: str = "/tmp/n2d_sim/servo.ctl"
    """Unix socket for fault injection and state queries; empty: none."""
    servo_id: int = 1
    """Dynamixel ID the emulated servo answers to."""
    rate_hz: float = 50.0
    """Rate of the ground-truth plate state."""

    def __post_init__(self):
        if not 0 <= self.servo_id <= 252:
            raise ValueError("servo_id must be in 0..252")
        if not 0 < self.rate_hz <= 1000:
            raise ValueError("rate_hz must be in (0, 1000]")


class SimTurntableNode(Node):
    NAME = "sim_turntable"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, SimTurntableConfig)
        self.servo = PtyServo(ServoEmulator(servo_id=self.cfg.servo_id), link=self.cfg.port_link).start()
        self.control = ControlServer(self.servo, self.cfg.control_socket).start() if self.cfg.control_socket else None
        self.state_pub = self.create_publisher(JointState, "sim/plate_state", PUBLISH_QOS)
        self.create_timer(1.0 / self.cfg.rate_hz, self.on_timer)
        self.get_logger().info(f"emulated XM430-W350 id {self.cfg.servo_id} on {self.cfg.port_link}")

    def on_timer(self) -> None:
        msg = JointState()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.name = ["turntable_plate"]
        msg.position = [self.servo.emulator.plate_angle_rad()]
        self.state_pub.publish(msg)

    def destroy_node(self) -> None:
        if self.control is not None:
            self.control.close()
        self.servo.stop()
        super().destroy_node()


def main(args=None) -> None:
    run_node(SimTurntableNode, args)


if __name__ == "__main__":
    main()
