"""The Capture action across processes, as a task planner calls it: `n2d launch capture` (simulated servo and
camera, turntable_node, capture_node), an rclpy client here: empty-plate sweep, object sweep, complete session;
a capture of two placements that waits for the object to be turned over, is cancelled while it waits, resumes at
the pause, continues on `capture/continue`, and stopped in its second sweep resumes there."""

import json
import threading
import time

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from helpers import wait_future
from std_srvs.srv import SetBool, Trigger

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d_capture.capture import TURN_OVER
from n2d_capture.masks import iou
from n2d_capture.sweep import read_sweep
from n2d_common.formats.session import read_session
from n2d_common.images import read_png
from n2d_common.ros import SafeActionClient, background_node, send_goal
from n2d_interfaces.action import Capture

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

VIEWS = 6
"""Enough for the turntable fit (as PLACED_VIEWS below); each view is a render, so more only makes the test slower."""


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


PLACED_VIEWS = 6
"""Views per placement of the two-placement capture: enough for each placement's turntable fit."""


@pytest.mark.timeout(600)
def test_capture_action_waits_for_the_object_turned_over(tmp_path, ros_domain):
    logs = []
    args = {"port": str(tmp_path / "ttyDXL"), "control": str(tmp_path / "servo.ctl")}
    session = tmp_path / "session"
    request = Capture.Goal(session_dir=str(session), views=PLACED_VIEWS,
                           config_yaml="placements: 2\nsweep: {frame_timeout_s: 60}")
    with Launch(load("capture"), args, log=logs.append) as launch, background_node("test_planner", ros_domain) as node:
        client = SafeActionClient(node, Capture, "/n2d/capture")
        turn = node.create_client(SetBool, "/n2d/sim/turn_over")
        resume = node.create_client(Trigger, "/n2d/capture/continue")
        assert client.wait_for_server(timeout_sec=60) and turn.wait_for_service(timeout_sec=60), logs[-20:]
        assert resume.wait_for_service(timeout_sec=10)
        assert not wait_future(resume.call_async(Trigger.Request()), 30).success  # nothing waits yet
        feedback, asked = [], threading.Event()

        def on_feedback(message):
            feedback.append(message.feedback.stage)
            if message.feedback.stage == TURN_OVER:
                asked.set()

        goal = send_goal(client, request, feedback_callback=on_feedback)
        assert goal.accepted and asked.wait(400), "\n".join(logs[-40:])
        first = read_sweep(session.with_name("session.partial"), "images")
        assert len(first) == PLACED_VIEWS and "rotating" in feedback
        # cancelled while it waits: the first placement's views are kept
        wait_future(goal.cancel_goal_async(), 30)
        assert wait_future(goal.get_result_async(), 60).status == GoalStatus.STATUS_CANCELED
        # sent again, it resumes at the pause: no view of the first placement is taken again
        feedback.clear()
        asked.clear()
        goal = send_goal(client, request, feedback_callback=on_feedback)
        assert goal.accepted and asked.wait(120)
        assert "rotating" not in feedback and read_sweep(session.with_name("session.partial"), "images") == first
        assert wait_future(turn.call_async(SetBool.Request(data=True)), 60).success
        assert wait_future(resume.call_async(Trigger.Request()), 30).success
        # stopped during the second sweep, it resumes there: the object is not asked for again
        partial = session.with_name("session.partial")
        deadline = time.monotonic() + 300
        while len(read_sweep(partial, "images2")) < 2:
            assert time.monotonic() < deadline, "\n".join(logs[-40:])
            time.sleep(0.2)
        wait_future(goal.cancel_goal_async(), 30)
        assert wait_future(goal.get_result_async(), 120).status == GoalStatus.STATUS_CANCELED
        kept = read_sweep(partial, "images2")
        feedback.clear()
        goal = send_goal(client, request, feedback_callback=on_feedback)
        assert goal.accepted
        result = wait_future(goal.get_result_async(), 400)
        assert TURN_OVER not in feedback and read_sweep(session, "images2")[:len(kept)] == kept
        assert result.status == GoalStatus.STATUS_SUCCEEDED, (result.result.message, "\n".join(logs[-40:]))
        assert result.result.views_captured == 2 * PLACED_VIEWS
        assert not launch.dead()
    s = read_session(session)
    assert s.placements == 2 and [v.placement for v in s.views] == [0] * PLACED_VIEWS + [1] * PLACED_VIEWS
    # one fixed camera: in each placement's turntable frame every view is at the same height
    assert np.ptp([v.T_turntable_cam[2, 3] for v in s.views]) < 0.002
    # the box lies on its side in the second sweep: at the same plate angles its silhouette differs
    masks = [read_png(v.mask) > 0 for v in s.views]
    overlap = [iou(a, b) for a, b in zip(masks[:PLACED_VIEWS], masks[PLACED_VIEWS:])]
    assert np.median(overlap) < 0.8, overlap
    info = json.loads((session / "capture.json").read_text())
    assert [p["views"] for p in info["placements"]] == [PLACED_VIEWS, PLACED_VIEWS]
