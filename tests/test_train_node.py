"""The Train action across processes, as a task planner calls it: `n2d launch train`, an rclpy client here;
a tiny-preset goal cancelled at its first training step (checkpoint kept, no model), resumed to a complete DOPE
model directory with step feedback, and a bad goal aborted with the reason while the node keeps serving."""

import json

import pytest
from action_msgs.msg import GoalStatus
from helpers import send_and_cancel, wait_future

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d_common.config import load_config
from n2d_common.contracts import open_stage
from n2d_common.ros import SafeActionClient, background_node, send_goal
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_interfaces.action import Train
from n2d_sim.objects import sample_object_dir

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

EPOCHS = 30
"""Training steps of the goals (two frames, batch 4: one step per epoch); a cancel lands within a few."""


@pytest.mark.timeout(300)
def test_train_action(tmp_path, ros_domain):
    dataset = tmp_path / "ds"
    cfg = load_config(DatasetConfig, overrides=["frames=2", "camera.width=160", "camera.height=120",
                                                "camera.focal_px=150", "render.samples=2"])
    generate_dataset([sample_object_dir("box")], dataset, cfg)
    model = tmp_path / "dope"
    logs = []
    # one torch thread: with the default (one per core) this test ran several times slower on 2 busy cores
    with Launch(load("train"), {"device": "cpu", "threads": "1"}, log=logs.append) as launch:
        with background_node("test_planner", ros_domain) as node:
            client = SafeActionClient(node, Train, "/n2d/train")
            assert client.wait_for_server(timeout_sec=60), logs[-20:]

            # an incomplete goal is refused
            refused = send_goal(client, Train.Goal(dataset_dir=str(dataset)))
            assert not refused.accepted

            # cancel at the first training step: the goal ends canceled, the checkpoint stays for a resume
            request = Train.Goal(dataset_dir=str(dataset), model_dir=str(model), preset="tiny",
                                 config_yaml=f"{{epochs: {EPOCHS}}}")
            goal, first = send_and_cancel(client, request, lambda f: f.stage == "training")
            result = wait_future(goal.get_result_async(), 120)
            assert result.status == GoalStatus.STATUS_CANCELED, (result.result.message, logs[-20:])
            assert first.steps_total == EPOCHS and first.step >= 1 and first.loss > 0
            assert not model.exists() and (tmp_path / "dope.partial" / "checkpoint.pt").is_file()

            # resume: training continues after the saved step and ends in a complete model directory
            feedback = []
            request.resume = True
            goal = send_goal(client, request, feedback_callback=lambda f: feedback.append(f.feedback))
            assert goal.accepted
            result = wait_future(goal.get_result_async(), 180)
            assert result.status == GoalStatus.STATUS_SUCCEEDED, (result.result.message, logs[-20:])
            assert result.result.success and result.result.model_dir == str(model)
            summary = json.loads(result.result.summary_json)
            assert summary["steps"] == summary["planned_steps"] == EPOCHS and summary["object"] == "box"
            assert summary["device"] == "cpu"  # the launch's device, kept under the goal's preset
            training = [f for f in feedback if f.stage == "training"]
            assert training and training[0].step > 1, [f.step for f in training[:3]]  # resumed, not restarted
            assert all(f.steps_total == EPOCHS for f in training) and training[-1].step == EPOCHS
            assert all(a.step <= b.step for a, b in zip(training, training[1:]))
            assert {"exporting", "done"} <= {f.stage for f in feedback}
            assert open_stage(model, "dope_model")["kind"] == "dope_model"
            assert (model / "model.onnx").is_file()
            config = json.loads((model / "config.json").read_text())
            assert config["object"] == "box" and config["stages"] == 1  # the tiny preset, not the node's 3 stages

            # bad input: aborted with the reason, the node keeps serving
            bad = Train.Goal(dataset_dir=str(tmp_path / "nowhere"), model_dir=str(tmp_path / "m2"), preset="tiny")
            goal = send_goal(client, bad)
            result = wait_future(goal.get_result_async(), 60)
            assert result.status == GoalStatus.STATUS_ABORTED and "nowhere" in result.result.message
            assert not (tmp_path / "m2").exists()
            assert not launch.dead()
