"""turntable_node across processes: the real node drives the emulated servo; an rclpy action client in
this process rotates, watches feedback, cancels; joint states arrive; a bad port fails with one line. The
lifecycle: every transition through the lifecycle services, with the emulator's torque checked in each state;
a servo fault mid-motion and a pulled cable end in the error transition, and the node comes back; the plate
on /tf matches the joint state."""

import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from action_msgs.msg import GoalStatus
from helpers import list_parameters, wait_future
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import JointState
from tf2_msgs.msg import TFMessage

from n2d.launch_description import LaunchSpec, NodeSpec
from n2d.launcher import Launch
from n2d_capture.turntable_frame import TurntableFit
from n2d_common.frames import make_T, rot_z
from n2d_common.ros import SENSOR_QOS, TF_QOS, TF_STATIC_QOS, SafeActionClient, background_node, send_goal
from n2d_interfaces.action import Rotate


def _turntable_launch(port: str, logs: list, expert: dict | None = None, **parameters) -> Launch:
    """turntable_node on `port` with the user `parameters`; the `expert` settings (and a quick motion profile)
    go through its config file, as they do for a user."""
    settings = {"turntable.acceleration_rad_s2": 10.0, "turntable.settle_time_s": 0.1, **(expert or {})}
    config = Path(tempfile.mkdtemp(prefix="n2d-turntable-")) / "turntable.yaml"
    config.write_text(yaml.safe_dump(settings))
    node = NodeSpec("n2d_capture", "turntable_node", "turntable",
                    parameters={"turntable.port": port, "turntable.velocity_limit_rad_s": 2.0,
                                "config_file": str(config), **parameters})
    return Launch(LaunchSpec("turntable", "", {}, [node]), log=logs.append)


@pytest.fixture
def client_node(ros_domain):
    with background_node("test_turntable_client", ros_domain) as node:
        yield node



@pytest.mark.timeout(120)
def test_rotate_action_feedback_cancel_and_joint_states(sim, client_node):
    logs = []
    with _turntable_launch(sim.link, logs) as launch:
        states = []
        client_node.create_subscription(JointState, "/n2d/turntable/joint_states", states.append, SENSOR_QOS)
        client = SafeActionClient(client_node, Rotate, "/n2d/turntable/rotate")
        assert client.wait_for_server(timeout_sec=30), logs
        from test_node_parameters import expected_parameters

        assert list_parameters(client_node, "/n2d/turntable") == expected_parameters("turntable_node")

        feedback = []
        goal = send_goal(client, Rotate.Goal(angle_rad=math.pi / 2), feedback_callback=feedback.append)
        assert goal.accepted
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_SUCCEEDED and result.result.success
        assert abs(result.result.angle_rad - math.pi / 2) < 0.005
        assert abs(sim.control.state()["plate_rad"] - math.pi / 2) < 0.005
        assert feedback and feedback[-1].feedback.progress == pytest.approx(1.0)
        assert {f.feedback.stage for f in feedback} <= {"moving", "settling"}

        # a long move, cancelled half way: the plate stops short of the goal
        goal = send_goal(client, Rotate.Goal(angle_rad=4 * math.pi))
        time.sleep(0.8)
        busy = send_goal(client, Rotate.Goal(angle_rad=0.0))
        assert not busy.accepted  # one rotation at a time
        wait_future(goal.cancel_goal_async())
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_CANCELED
        deadline = time.monotonic() + 10
        while sim.control.state()["moving"]:  # braking with the profile deceleration
            assert time.monotonic() < deadline, "the plate does not stop"
            time.sleep(0.05)
        stopped = sim.control.state()["plate_rad"]
        assert math.pi / 2 < stopped < 4 * math.pi - 1.0
        deadline = time.monotonic() + 10
        while not states or abs(states[-1].position[0] - stopped) > 0.01:
            assert time.monotonic() < deadline, f"joint states do not follow the plate: {stopped} {states[-1:]}"
            time.sleep(0.05)
        assert states[-1].name == ["turntable_plate"]
        assert not launch.dead()


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_wrong_port_is_one_clear_fatal_line(tmp_path, ros_domain):
    logs = []
    with _turntable_launch(str(tmp_path / "ttyUSB9"), logs) as launch:
        assert launch.wait() == 2
    fatal = [line for line in logs if "FATAL" in line]
    assert len(fatal) == 1 and "cannot open serial port" in fatal[0] and "hint:" in fatal[0]


class Lifecycle:
    """Client of turntable_node's lifecycle services (lifecycle_msgs ChangeState, GetState)."""

    def __init__(self, node, name: str = "/n2d/turntable"):
        self.change = node.create_client(ChangeState, f"{name}/change_state")
        self.get = node.create_client(GetState, f"{name}/get_state")
        assert self.change.wait_for_service(timeout_sec=30) and self.get.wait_for_service(timeout_sec=30)
        self.state()  # both directions of the service matched before the first transition is requested

    def state(self) -> int:
        """The node's lifecycle state id; a GetState request lost right after discovery is sent again."""
        for _ in range(5):
            future = self.get.call_async(GetState.Request())
            deadline = time.monotonic() + 10
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.01)
            if future.done():
                return future.result().current_state.id
        raise AssertionError("get_state does not answer")

    def set(self, transition: int) -> bool:
        """Request `transition` (a Transition.TRANSITION_* id); whether it succeeded."""
        return wait_future(self.change.call_async(ChangeState.Request(transition=Transition(id=transition))),
                           60).success

    def wait_for(self, state: int, timeout_s: float = 30) -> None:
        deadline = time.monotonic() + timeout_s
        while (now := self.state()) != state:
            assert time.monotonic() < deadline, f"the node stays in state {now}, not {state}"
            time.sleep(0.1)


def _wait(condition, timeout_s: float = 20, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def _torque(sim) -> bool:
    return sim.control.state()["torque"]


def _port_quiet(sim, for_s: float = 0.6) -> bool:
    """Whether the driver leaves the servo alone (no packet for `for_s`): its port is closed."""
    before = sim.control.state()["rx_packets"]
    time.sleep(for_s)
    return sim.control.state()["rx_packets"] == before


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_lifecycle_transitions_torque_goals_and_plate_tf(sim, client_node, tmp_path):
    logs = []
    T_cam_turntable = make_T(Rotation.from_rotvec([2.0, 0.3, -0.4]).as_matrix(), [0.1, -0.05, 0.6])
    fit = TurntableFit(np.eye(4), T_cam_turntable, 0, np.zeros(1), np.zeros(1), np.zeros(1), np.ones(1, bool),
                       servo_offset_rad=0.3, servo_scale=1.0, servo_residual_deg=np.zeros(1), board_tilt_deg=0.0)
    (tmp_path / "capture.json").write_text(json.dumps({"turntable_fit": fit.to_dict()}))
    with _turntable_launch(sim.link, logs, autostart=False, camera_session=str(tmp_path)) as launch:
        states, tf, tf_static = [], [], []
        client_node.create_subscription(JointState, "/n2d/turntable/joint_states", states.append, SENSOR_QOS)
        client_node.create_subscription(TFMessage, "/tf", tf.append, TF_QOS)
        client_node.create_subscription(TFMessage, "/tf_static", tf_static.append, TF_STATIC_QOS)
        client = SafeActionClient(client_node, Rotate, "/n2d/turntable/rotate")
        assert client.wait_for_server(timeout_sec=30), logs
        lifecycle = Lifecycle(client_node)
        assert lifecycle.state() == State.PRIMARY_STATE_UNCONFIGURED
        assert not _torque(sim) and _port_quiet(sim)
        # latched on /tf_static from start-up on: where the capture session's turntable sits in the camera
        _wait(lambda: tf_static, what="nothing on /tf_static")
        t = tf_static[0].transforms[0]
        assert (t.header.frame_id, t.child_frame_id) == ("camera_optical_frame", "turntable_base")
        expected = T_cam_turntable @ rot_z(-0.3)
        v, q = t.transform.translation, t.transform.rotation
        np.testing.assert_allclose([v.x, v.y, v.z], expected[:3, 3], atol=1e-9)
        np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), expected[:3, :3], atol=1e-9)

        assert lifecycle.set(Transition.TRANSITION_CONFIGURE), logs
        assert lifecycle.state() == State.PRIMARY_STATE_INACTIVE
        assert not _torque(sim)  # configured: port open, joint states, torque off
        _wait(lambda: states, what="no joint states while inactive")
        assert not send_goal(client, Rotate.Goal(angle_rad=1.0)).accepted

        assert lifecycle.set(Transition.TRANSITION_ACTIVATE)
        assert lifecycle.state() == State.PRIMARY_STATE_ACTIVE and _torque(sim)
        goal = send_goal(client, Rotate.Goal(angle_rad=math.pi / 2))
        assert goal.accepted
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_SUCCEEDED, result.result.message

        # the plate on /tf: turntable_base to turntable_plate, turned about +z by the joint state's angle
        def matched():
            angles = {(m.header.stamp.sec, m.header.stamp.nanosec): m.position[0] for m in list(states)}
            for message in list(tf):
                for t in message.transforms:
                    key = (t.header.stamp.sec, t.header.stamp.nanosec)
                    if (t.header.frame_id, t.child_frame_id) == ("turntable_base", "turntable_plate") \
                            and key in angles and abs(angles[key] - math.pi / 2) < 0.01:
                        return t, angles[key]
            return None
        _wait(matched, what=f"no plate transform matching a joint state: {tf[-1:]}")
        t, angle = matched()
        q = t.transform.rotation
        assert (q.x, q.y) == (0.0, 0.0) and abs(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2 - 1) < 1e-9
        assert abs(math.remainder(2 * math.atan2(q.z, q.w) - angle, 2 * math.pi)) < 1e-6
        assert (t.transform.translation.x, t.transform.translation.y, t.transform.translation.z) == (0, 0, 0)

        assert lifecycle.set(Transition.TRANSITION_DEACTIVATE)
        assert lifecycle.state() == State.PRIMARY_STATE_INACTIVE and not _torque(sim)
        assert not send_goal(client, Rotate.Goal(angle_rad=0.0)).accepted

        # deactivating mid-motion cancels the rotation (aborted, not succeeded) and then releases the servo
        assert lifecycle.set(Transition.TRANSITION_ACTIVATE) and _torque(sim)
        goal = send_goal(client, Rotate.Goal(angle_rad=4 * math.pi))
        assert goal.accepted
        _wait(lambda: sim.control.state()["moving"], what="the plate does not move")
        assert lifecycle.set(Transition.TRANSITION_DEACTIVATE)
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_ABORTED and "deactivated" in result.result.message
        assert not _torque(sim) and sim.control.state()["plate_rad"] < 4 * math.pi - 1.0

        assert lifecycle.set(Transition.TRANSITION_CLEANUP)
        assert lifecycle.state() == State.PRIMARY_STATE_UNCONFIGURED and _port_quiet(sim)
        assert lifecycle.set(Transition.TRANSITION_CONFIGURE)
        assert lifecycle.state() == State.PRIMARY_STATE_INACTIVE and not _port_quiet(sim)
        assert lifecycle.set(Transition.TRANSITION_INACTIVE_SHUTDOWN)
        assert lifecycle.state() == State.PRIMARY_STATE_FINALIZED
        assert not _torque(sim) and _port_quiet(sim)
        assert not lifecycle.set(Transition.TRANSITION_CONFIGURE)  # finalized is final
        assert not launch.dead()


@pytest.mark.timeout(180)
def test_servo_fault_mid_motion_is_the_error_transition_and_configure_recovers(sim, client_node):
    logs = []
    with _turntable_launch(sim.link, logs) as launch:  # autostart: configured and active at start-up
        client = SafeActionClient(client_node, Rotate, "/n2d/turntable/rotate")
        assert client.wait_for_server(timeout_sec=30), logs
        lifecycle = Lifecycle(client_node)
        assert lifecycle.state() == State.PRIMARY_STATE_ACTIVE and _torque(sim)

        goal = send_goal(client, Rotate.Goal(angle_rad=4 * math.pi))
        assert goal.accepted
        _wait(lambda: sim.control.state()["moving"], what="the plate does not move")
        sim.control.fault("overload")
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_ABORTED and "overload" in result.result.message
        lifecycle.wait_for(State.PRIMARY_STATE_UNCONFIGURED)
        assert any("now unconfigured" in line and "overload" in line for line in logs), logs[-10:]
        assert not launch.dead() and not _torque(sim)

        # configure again: the node reboots the servo, which clears the overload; torque comes back on activate
        assert lifecycle.set(Transition.TRANSITION_CONFIGURE), logs[-10:]
        assert sim.control.state()["hardware_error"] == 0 and not _torque(sim)
        assert lifecycle.set(Transition.TRANSITION_ACTIVATE) and _torque(sim)
        goal = send_goal(client, Rotate.Goal(angle_rad=1.0))
        assert goal.accepted
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_SUCCEEDED, result.result.message
        assert abs(sim.control.state()["plate_rad"] - 1.0) < 0.005
        assert not launch.dead()


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_pulled_cable_is_the_error_transition_and_autostart_comes_back(sim, client_node):
    logs = []
    with _turntable_launch(sim.link, logs, {"turntable.reconnect_attempts": 2}) as launch:
        client = SafeActionClient(client_node, Rotate, "/n2d/turntable/rotate")
        assert client.wait_for_server(timeout_sec=30), logs
        lifecycle = Lifecycle(client_node)
        assert lifecycle.state() == State.PRIMARY_STATE_ACTIVE
        sim.control.disconnect()
        lifecycle.wait_for(State.PRIMARY_STATE_UNCONFIGURED)
        assert not send_goal(client, Rotate.Goal(angle_rad=1.0)).accepted
        sim.control.reconnect()
        lifecycle.wait_for(State.PRIMARY_STATE_ACTIVE)
        assert _torque(sim)
        goal = send_goal(client, Rotate.Goal(angle_rad=1.0))
        assert goal.accepted
        assert wait_future(goal.get_result_async()).status == GoalStatus.STATUS_SUCCEEDED
        assert not launch.dead()


@pytest.mark.timeout(60)
def test_a_configure_request_without_a_servo_fails_and_the_node_waits(tmp_path, client_node):
    logs = []
    with _turntable_launch(str(tmp_path / "ttyUSB9"), logs, {"connect_timeout_s": 0.5}, autostart=False) as launch:
        lifecycle = Lifecycle(client_node)
        assert not lifecycle.set(Transition.TRANSITION_CONFIGURE)
        assert lifecycle.state() == State.PRIMARY_STATE_UNCONFIGURED
        _wait(lambda: any("configure failed: cannot open serial port" in line for line in logs), what=logs[-5:])
        assert not launch.dead()
