"""turntable_node: the Dynamixel turntable on ROS 2 (a real servo or the emulated one, unchanged), a managed node.

A lifecycle node, as ros2_control hardware interfaces are: configure opens the port, activate turns the
servo's torque on and lets goals in, deactivate cancels a running rotation and turns the torque off, cleanup
closes the port, shutdown does what is left from any state. A servo fault (a hardware error, a lost port, a
servo that stops answering) goes through the error transition to unconfigured; the process stays up. With
`autostart` (the default) the node configures and activates itself at start-up, and again after a
communication fault.

From configured on it publishes `turntable/joint_states` (sensor_msgs/JointState, joint `turntable_plate`,
plate angle in rad, multi-turn) and `/tf` (`base_frame` to `plate_frame`, a rotation about +z by the plate
angle) at `joint_state_rate_hz`; with `camera_session`, the camera to the base on `/tf_static`. While active
it serves the `turntable/rotate` action (n2d_interfaces/Rotate: feedback with angle, progress, stage and ETA;
cancel brakes the plate); goals are refused otherwise. One goal at a time: a second goal while the plate moves
is rejected. Its ROS parameters are the user tier of `TurntableNodeConfig` (port, baud, servo_id, protocol,
gear_ratio, velocity_limit_rad_s, ...); the expert settings come from `config_file`.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import rclpy
from geometry_msgs.msg import Quaternion, Transform, TransformStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from n2d_capture.turntable import (
    ServoCommError,
    ServoDisconnected,
    ServoHardwareError,
    Turntable,
    TurntableConfig,
)
from n2d_capture.turntable_frame import T_cam_base, TurntableFit
from n2d_common.errors import Cancelled, ConfigError, DeviceError, N2DError
from n2d_common.ros import (
    PUBLISH_QOS,
    TF_QOS,
    TF_STATIC_QOS,
    declare_config,
    refuse_invalid_transitions,
    run_node,
    transform_msg,
)
from n2d_interfaces.action import Rotate

FAULTS = (ServoHardwareError, ServoCommError, ServoDisconnected)
"""Errors after which the servo cannot be commanded: they go through the error transition."""
COMM_FAULTS = (ServoCommError, ServoDisconnected)
"""Faults that `autostart` recovers from by itself (a hardware error waits for a configure request)."""
RECOVER_PERIOD_S = 2.0
"""With autostart, try to bring the node up again this often after a communication fault [s]."""
SUCCESS, FAILURE, ERROR = (TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE,
                           TransitionCallbackReturn.ERROR)


@dataclass
class TurntableNodeConfig:
    """Parameters of turntable_node."""

    ROS_PARAMETERS = ("turntable.port", "turntable.baud", "turntable.servo_id", "turntable.protocol",
                      "turntable.gear_ratio", "turntable.velocity_limit_rad_s", "turntable.zero_offset_rad",
                      "turntable.retries", "autostart", "publish_tf", "base_frame", "plate_frame", "camera_session",
                      "camera_frame")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    turntable: TurntableConfig = field(default_factory=TurntableConfig)
    """The servo and its motion profile."""
    joint_state_rate_hz: float = 20.0
    """Rate of turntable/joint_states."""
    joint_name: str = "turntable_plate"
    """Joint name in the JointState messages."""
    connect_timeout_s: float = 5.0
    """Keep trying to open the servo this long when configuring (the adapter or simulator may come up later)."""
    autostart: bool = True
    """Configure and activate at start-up (a configure error ends the node), and again after a communication
    fault; false: the node waits unconfigured for a lifecycle manager or `ros2 lifecycle set`."""
    reboot_after_fault: bool = True
    """After the error transition for a servo hardware error (overload, overheating), the next configure
    reboots the servo, which clears the error; its torque stays off until activate. False: power-cycle it."""
    publish_tf: bool = True
    """Broadcast the plate's transform on /tf (base_frame to plate_frame) with each joint state."""
    base_frame: str = "turntable_base"
    """TF frame of the turntable's base: origin on the plate's axis, on its top face, z up."""
    plate_frame: str = "turntable_plate"
    """TF frame of the plate: base_frame turned about +z by the plate angle."""
    camera_session: str = ""
    """A capture session directory: publish where its fitted turntable sits in the camera, camera_frame to
    base_frame on /tf_static (the camera and the servo's zero as in that capture); empty: none."""
    camera_frame: str = "camera_optical_frame"
    """The camera's optical frame (OpenCV axes) for camera_session."""

    def __post_init__(self):
        if not 0 < self.joint_state_rate_hz <= 200:
            raise ValueError("joint_state_rate_hz must be in (0, 200]")
        if self.publish_tf and not (self.base_frame and self.plate_frame and self.base_frame != self.plate_frame):
            raise ValueError("base_frame and plate_frame must be two different, non-empty frame names")
        if self.camera_session and not self.camera_frame:
            raise ValueError("camera_frame must not be empty with camera_session")


def plate_transform(angle_rad: float, header: Header, child_frame: str) -> TransformStamped:
    """The plate frame as a TF transform: header.frame_id (the base) to `child_frame`, turned about +z."""
    rotation = Quaternion(x=0.0, y=0.0, z=math.sin(angle_rad / 2), w=math.cos(angle_rad / 2))
    return TransformStamped(header=header, child_frame_id=child_frame, transform=Transform(rotation=rotation))


class TurntableNode(LifecycleNode):
    NAME = "turntable"

    def __init__(self):
        super().__init__(self.NAME)
        refuse_invalid_transitions(self)
        self.cfg = declare_config(self, TurntableNodeConfig)
        self.turntable: Turntable | None = None
        """The open driver, from configure to cleanup (None when unconfigured)."""
        self.active = False
        self.last_error: N2DError | None = None
        """Why the last transition failed, or the fault that ended in the error transition."""
        self._fault: N2DError | None = None
        self._busy = threading.Lock()
        self._cancel: threading.Event | None = None
        self._recover_at: float | None = None
        self._reboot_next = False
        self._quiet = False
        self._connect_wait_s = self.cfg.connect_timeout_s
        self.state_pub = self.create_publisher(JointState, "turntable/joint_states", PUBLISH_QOS)
        self.tf_pub = self.create_publisher(TFMessage, "/tf", TF_QOS) if self.cfg.publish_tf else None
        self.tf_static_pub = self._publish_camera_base() if self.cfg.camera_session else None
        # In the default (mutually exclusive) group, with the lifecycle services: a fault's transition from the
        # timer never runs alongside a requested one.
        self.create_timer(1.0 / self.cfg.joint_state_rate_hz, self.on_timer)
        self.rotate_server = ActionServer(self, Rotate, "turntable/rotate", execute_callback=self.execute_rotate,
                                          goal_callback=self.on_goal, cancel_callback=self.on_cancel,
                                          callback_group=ReentrantCallbackGroup())
        if self.cfg.autostart and not self._bring_up(self.cfg.connect_timeout_s):
            self._release()
            raise self.last_error or DeviceError("turntable: the lifecycle transitions at start-up failed")

    def _publish_camera_base(self):
        """camera_frame to base_frame from the session's turntable fit, once, latched on /tf_static."""
        path = Path(self.cfg.camera_session) / "capture.json"
        try:
            fit = TurntableFit.from_dict(json.loads(path.read_text())["turntable_fit"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"camera_session: cannot read the turntable fit from {path}: {exc}",
                              "give a capture session directory (it holds capture.json)") from None
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=self.cfg.camera_frame)
        transform = TransformStamped(header=header, child_frame_id=self.cfg.base_frame,
                                     transform=transform_msg(T_cam_base(fit)))
        publisher = self.create_publisher(TFMessage, "/tf_static", TF_STATIC_QOS)
        publisher.publish(TFMessage(transforms=[transform]))
        return publisher

    # ---------------------------------------------------------------- transitions
    def _bring_up(self, timeout_s: float) -> bool:
        """Configure and activate; whether the node is active. Failures are kept in `last_error`, not logged."""
        self._quiet, self._connect_wait_s = True, timeout_s
        try:
            return self.trigger_configure() == SUCCESS and self.trigger_activate() == SUCCESS
        finally:
            self._quiet, self._connect_wait_s = False, self.cfg.connect_timeout_s

    def _failed(self, exc: N2DError, what: str) -> TransitionCallbackReturn:
        self.last_error = exc
        if not self._quiet:
            self.get_logger().error(f"{what} failed: {exc}")
        return ERROR if isinstance(exc, FAULTS) and self.turntable is not None else FAILURE

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        turntable = Turntable(self.cfg.turntable)
        try:
            self._open(turntable, self._connect_wait_s)
        except ServoHardwareError as exc:
            if not (self.cfg.reboot_after_fault and self._reboot_next and not self._quiet):
                return self._failed(exc, "configure")
            self.get_logger().warning(f"{exc}; rebooting the servo to clear it")
            try:
                turntable.reboot()  # keeps the torque off, as open(torque=False) asked
            except N2DError as exc:
                turntable.close()
                return self._failed(exc, "configure (rebooting the servo)")
        except N2DError as exc:
            return self._failed(exc, "configure")
        self.turntable = turntable
        self.last_error, self._fault, self._recover_at, self._reboot_next = None, None, None, False
        self.get_logger().info(f"turntable servo {turntable.model_number} id {self.cfg.turntable.servo_id} "
                               f"on {self.cfg.turntable.port} at {math.degrees(turntable.angle()):.1f} deg, "
                               "torque off")
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.turntable.set_torque(True)
        except N2DError as exc:
            return self._failed(exc, "activate")
        self.active = True
        self.get_logger().info("turntable active: torque on, accepting goals")
        return SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        if self._fault is not None:
            return ERROR  # a fault: on_error releases the servo
        self._stop_rotation()
        try:
            self.turntable.set_torque(False)
        except N2DError as exc:
            return self._failed(exc, "deactivate")
        self.get_logger().info("turntable inactive: torque off")
        return SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._fault is not None:
            return ERROR
        self._release()
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        fault, self._fault = self._fault or self.last_error, None
        self.last_error = fault
        self._release()
        self._reboot_next = isinstance(fault, ServoHardwareError)
        recover = self.cfg.autostart and isinstance(fault, COMM_FAULTS)
        self._recover_at = time.monotonic() + RECOVER_PERIOD_S if recover else None
        then = ("trying again every few seconds" if recover else
                "configure again" + (" (it reboots the servo)" if isinstance(fault, ServoHardwareError)
                                     and self.cfg.reboot_after_fault else ""))
        self.get_logger().error(f"turntable fault, now unconfigured: {fault}; {then}")
        return SUCCESS

    @staticmethod
    def _open(turntable: Turntable, timeout_s: float) -> None:
        """Open with the torque off, trying again for `timeout_s` (the adapter or simulator may come up later)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                turntable.open(torque=False)
                return
            except DeviceError as exc:
                if time.monotonic() > deadline or isinstance(exc, ServoHardwareError):
                    raise
                time.sleep(0.25)

    def _stop_rotation(self, timeout_s: float = 15.0) -> None:
        """Cancel a running rotation and wait until it has braked (or `timeout_s` passed)."""
        cancel = self._cancel
        if cancel is not None:
            cancel.set()
        if self._busy.acquire(timeout=timeout_s):
            self._busy.release()

    def _release(self) -> None:
        """Stop a rotation, turn the torque off and close the port (from any state)."""
        self.active = False
        self._stop_rotation()
        turntable, self.turntable = self.turntable, None
        if turntable is not None:
            turntable.close()

    def _enter_error(self, exc: N2DError) -> None:
        """A fault (from the timer, in the lifecycle services' callback group): through on_error to unconfigured."""
        self._fault = exc
        if self.active:
            self.trigger_deactivate()
        elif self.turntable is not None:
            self.trigger_cleanup()
        self._fault = None

    # ---------------------------------------------------------------- state
    def on_timer(self) -> None:
        if self._fault is not None:
            self._enter_error(self._fault)
        if self.turntable is None:
            if self._recover_at is not None and time.monotonic() >= self._recover_at:
                self._recover_at = None
                if (not self._bring_up(0.0) and self.turntable is None and self._recover_at is None
                        and not isinstance(self.last_error, ServoHardwareError)):
                    self._recover_at = time.monotonic() + RECOVER_PERIOD_S
            return
        try:
            angle = self.turntable.angle(check_alert=self.active)
        except FAULTS as exc:
            self._enter_error(exc)
            return
        except N2DError as exc:
            self.get_logger().error(str(exc), throttle_duration_sec=5.0)
            return
        stamp = self.get_clock().now().to_msg()
        self.state_pub.publish(JointState(header=Header(stamp=stamp), name=[self.cfg.joint_name], position=[angle]))
        if self.tf_pub is not None:
            header = Header(stamp=stamp, frame_id=self.cfg.base_frame)
            self.tf_pub.publish(TFMessage(transforms=[plate_transform(angle, header, self.cfg.plate_frame)]))

    # ---------------------------------------------------------------- rotate action
    def on_goal(self, goal: Rotate.Goal) -> GoalResponse:
        if not self.active or not math.isfinite(goal.angle_rad) or goal.velocity_rad_s < 0 or self._busy.locked():
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
        turntable = self.turntable

        def feedback(angle: float, fraction: float, stage: str, eta_s: float) -> None:
            goal_handle.publish_feedback(Rotate.Feedback(angle_rad=angle, progress=fraction, stage=stage,
                                                         eta_s=eta_s))

        try:
            if not self.active or turntable is None:
                raise DeviceError("the turntable is not active", "activate it (ros2 lifecycle set) first")
            target = goal.angle_rad + (turntable.angle() if goal.relative else 0.0)
            result.angle_rad = turntable.rotate_to(target, goal.velocity_rad_s or None, feedback, self._cancel)
            result.success = True
            goal_handle.succeed()
        except Cancelled as exc:
            result.message, result.angle_rad = str(exc), turntable.angle()
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:  # stopped by deactivate or shutdown, not by the client
                result.message = f"the turntable was deactivated: {exc}"
                goal_handle.abort()
        except N2DError as exc:
            result.message = str(exc)
            self.get_logger().error(result.message)
            if isinstance(exc, FAULTS):
                self._fault = exc  # the timer takes it through the error transition
            goal_handle.abort()
        finally:
            self._cancel = None
            self._busy.release()
        return result

    def destroy_node(self) -> None:
        if self.turntable is not None and rclpy.ok(context=self.context):
            self.trigger_shutdown()  # through on_shutdown while the context still publishes the transition
        self._release()  # after Ctrl-C the context is gone: release the servo without the state machine
        self.rotate_server.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(TurntableNode, args)


if __name__ == "__main__":
    main()
