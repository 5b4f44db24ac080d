"""The Capture action across processes, as a task planner calls it: `n2d launch capture` (simulated servo and
camera, turntable_node, capture_node), an rclpy client here: empty-plate sweep, object sweep, complete session."""


import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from helpers import wait_future
from std_srvs.srv import SetBool

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d_common.formats.session import read_session
from n2d_common.ros import SafeActionClient, background_node, send_goal
from n2d_interfaces.action import Capture

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

VIEWS = 12
"""Enough for the turntable fit; each view is a render, so more only makes the test slower."""


@pytest.mark.timeout(900)
def test_capture_action_writes_a_complete_session(tmp_path, ros_domain):
    logs = []
    args = {"port": str(tmp_path / "ttyDXL"), "control": str(tmp_path / "servo.ctl")}
    with Launch(load("capture"), args, log=logs.append) as launch:
        with background_node("test_planner", ros_domain) as node:
            client = SafeActionClient(node, Capture, "/n2d/capture")
            lift = node.create_client(SetBool, "/n2d/sim/set_object_visible")
            assert client.wait_for_server(timeout_sec=60) and lift.wait_for_service(timeout_sec=60), logs[-20:]
            session = str(tmp_path / "session")
            results = []
            for empty in (True, False):
                assert wait_future(lift.call_async(SetBool.Request(data=not empty)), 120).success
                feedback = []
                request = Capture.Goal(session_dir=session, views=VIEWS, empty_plate=empty,
                                       config_yaml="sweep: {frame_timeout_s: 60}")
                goal = send_goal(client, request, feedback_callback=feedback.append)
                assert goal.accepted
                result = wait_future(goal.get_result_async(), 800)
                assert result.status == GoalStatus.STATUS_SUCCEEDED, (result.result.message, "\n".join(logs[-40:]))
                assert result.result.views_captured == VIEWS
                assert any(f.feedback.last_image.width for f in feedback)
                results.append(result.result)
            assert "place the object" in results[0].message
            assert not launch.dead()
    s = read_session(session)
    assert len(s.views) == VIEWS and s.width == 640
    assert all(v.mask is not None and v.mask.is_file() for v in s.views)
    # the camera is fixed and the plate turns: in the plate's frame every view is at the same height
    heights = [v.T_turntable_cam[2, 3] for v in s.views]
    assert np.ptp(heights) < 0.002
