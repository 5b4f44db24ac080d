"""The Reconstruct action across processes, as a task planner calls it: `n2d launch reconstruct`, an rclpy
client here; feedback, a complete model directory, cancel (the worker stops, the partial stays) and resume."""

import json

import pytest
from action_msgs.msg import GoalStatus
from helpers import send_and_cancel, wait_future

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d_common.contracts import read_manifest
from n2d_common.ros import SafeActionClient, background_node, send_goal
from n2d_interfaces.action import Reconstruct
from n2d_sim.session import render_session, small_world

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

SMALL = "{mesh: {voxel_m: 0.003, target_faces: 3000}, texture: {size_px: 128}}"



@pytest.mark.timeout(600)
def test_reconstruct_action(tmp_path, ros_domain):
    session = tmp_path / "session"
    render_session(session, small_world("box", 240, 180), 12)
    logs = []
    with Launch(load("reconstruct"), {}, log=logs.append) as launch:
        with background_node("test_planner", ros_domain) as node:
            client = SafeActionClient(node, Reconstruct, "/n2d/reconstruct")
            assert client.wait_for_server(timeout_sec=60), logs[-20:]

            # cancel as soon as the job reports: the worker stops, the partial directory stays for a resume
            cancelled = tmp_path / "cancelled"
            request = Reconstruct.Goal(session_dir=str(session), model_dir=str(cancelled), config_yaml=SMALL)
            goal, _ = send_and_cancel(client, request, lambda _: True)
            result = wait_future(goal.get_result_async(), 300)
            assert result.status == GoalStatus.STATUS_CANCELED, (result.result.message, logs[-20:])
            assert not cancelled.exists() and cancelled.with_name("cancelled.partial").is_dir(), logs[-20:]

            feedback = []
            model = tmp_path / "model"
            goal = send_goal(client, Reconstruct.Goal(session_dir=str(session), model_dir=str(model),
                                                      method="fast", config_yaml=SMALL),
                             feedback_callback=lambda f: feedback.append(f.feedback))
            result = wait_future(goal.get_result_async(), 300)
            assert result.status == GoalStatus.STATUS_SUCCEEDED, (result.result.message, logs[-20:])
            report = json.loads(result.result.report_json)
            assert report["model"]["watertight"] and report["heldout"]["mesh_psnr_db"] > 10
            assert read_manifest(model)["complete"]
            stages = [f.stage for f in feedback]
            assert {"load", "mesh", "texture", "report"} <= set(stages), stages
            assert all(a.progress <= b.progress + 1e-6 for a, b in zip(feedback, feedback[1:]))

            # bad input: aborted with the reason
            goal = send_goal(client, Reconstruct.Goal(session_dir=str(tmp_path / "nowhere"),
                                                      model_dir=str(tmp_path / "m3")))
            result = wait_future(goal.get_result_async(), 60)
            assert result.status == GoalStatus.STATUS_ABORTED and "nowhere" in result.result.message
            assert not launch.dead()
