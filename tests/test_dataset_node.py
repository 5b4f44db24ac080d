"""The GenerateDataset action across processes, as a task planner calls it: `n2d launch dataset`, an rclpy
client here; feedback with frame counts, cancel (finished frames stay), resume, and a refused bad goal."""

import json

import pytest
from action_msgs.msg import GoalStatus
from helpers import send_and_cancel, wait_future

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d_common.contracts import read_manifest
from n2d_common.ros import SafeActionClient, background_node, send_goal
from n2d_interfaces.action import GenerateDataset
from n2d_sim.objects import sample_object_dir

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

TINY = ("{camera: {width: 160, height: 120, focal_px: 150}, render: {samples: 2}, "
        "scene: {distractors: [0, 2], instances_per_model: [1, 1]}}")


@pytest.mark.timeout(600)
def test_generate_dataset_action(tmp_path, ros_domain):
    models = [str(sample_object_dir("box"))]
    out = tmp_path / "ds"
    logs = []
    with Launch(load("dataset"), {}, log=logs.append) as launch:
        with background_node("test_planner", ros_domain) as node:
            client = SafeActionClient(node, GenerateDataset, "/n2d/generate_dataset")
            assert client.wait_for_server(timeout_sec=60), logs[-20:]

            # cancel once the first frame is done: the goal ends canceled, finished frames stay for a resume
            request = GenerateDataset.Goal(model_dirs=models, dataset_dir=str(out), frames=4, config_yaml=TINY)
            goal, _ = send_and_cancel(client, request, lambda f: f.frames_done >= 1)
            result = wait_future(goal.get_result_async(), 300)
            assert result.status == GoalStatus.STATUS_CANCELED, (result.result.message, logs[-20:])
            assert not out.exists() and out.with_name("ds.partial").is_dir()

            feedback = []
            request.resume = True
            goal = send_goal(client, request, feedback_callback=lambda f: feedback.append(f.feedback))
            result = wait_future(goal.get_result_async(), 300)
            assert result.status == GoalStatus.STATUS_SUCCEEDED, (result.result.message, logs[-20:])
            summary = json.loads(result.result.message)
            assert result.result.frames_done == 4 and summary["resumed_frames"] >= 1
            assert read_manifest(out)["complete"] and (out / "contact_sheet.png").is_file()
            assert feedback and feedback[-1].frames_total == 4
            assert all(a.frames_done <= b.frames_done for a, b in zip(feedback, feedback[1:]))

            # bad input: aborted with the reason, nothing written
            bad = GenerateDataset.Goal(model_dirs=[str(tmp_path / "nowhere")], dataset_dir=str(tmp_path / "ds2"),
                                       frames=1)
            goal = send_goal(client, bad)
            result = wait_future(goal.get_result_async(), 60)
            assert result.status == GoalStatus.STATUS_ABORTED and "nowhere" in result.result.message
            assert not (tmp_path / "ds2").exists()
            assert not launch.dead()
