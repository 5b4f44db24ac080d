"""turntable_node across processes: the real node drives the emulated servo; an rclpy action client in
this process rotates, watches feedback, cancels; joint states arrive; a bad port fails with one line."""

import math
import time

import pytest
from action_msgs.msg import GoalStatus
from helpers import wait_future
from sensor_msgs.msg import JointState

from n2d.launch_description import LaunchSpec, NodeSpec
from n2d.launcher import Launch
from n2d_common.ros import SENSOR_QOS, SafeActionClient, background_node, send_goal
from n2d_interfaces.action import Rotate


def _turntable_launch(port: str, logs: list) -> Launch:
    node = NodeSpec("n2d_capture", "turntable_node", "turntable",
                    parameters={"turntable.port": port, "turntable.velocity_limit_rad_s": 2.0,
                                "turntable.acceleration_rad_s2": 10.0, "turntable.settle_time_s": 0.1})
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


@pytest.mark.timeout(60)
def test_wrong_port_is_one_clear_fatal_line(tmp_path, ros_domain):
    logs = []
    with _turntable_launch(str(tmp_path / "ttyUSB9"), logs) as launch:
        assert launch.wait() == 2
    fatal = [line for line in logs if "FATAL" in line]
    assert len(fatal) == 1 and "cannot open serial port" in fatal[0] and "hint:" in fatal[0]
