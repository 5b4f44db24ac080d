"""dataset_node's `cluster` and train_node's `ddp` parameters reach their stage: a dataset_node started with
`cluster:=local` renders a goal's frames on a one-machine Ray cluster (loopback), and a train_node started with
`ddp:=2` trains on them in two processes from its worker process."""

import importlib
import json
import threading

import pytest
import rclpy

from n2d_common.contracts import read_manifest
from n2d_interfaces.action import GenerateDataset, Train
from n2d_sim.objects import sample_object_dir

pytestmark = pytest.mark.slow  # a Ray cluster, rendering and training: tens of seconds

TINY = ("{camera: {width: 320, height: 240, focal_px: 300}, render: {engine: raster}, workers: 1, "
        "scene: {distractors: [1, 2], boards: 0}}")


def _node(module: str, cls: str, parameter: str):
    """The node `cls` of `module`, started with the parameter `name:=value` as a launch file gives it."""
    rclpy.init(args=["--ros-args", "-p", parameter])
    return getattr(importlib.import_module(module), cls)()


def test_cluster_and_ddp_parameters_reach_their_stage(tmp_path, ros_domain):
    out = tmp_path / "ds"
    node = _node("n2d_dataset.nodes.dataset_node", "DatasetNode", "cluster:=local")
    try:
        assert node.get_parameter("cluster").value == "local"
        goal = GenerateDataset.Goal(model_dirs=[str(sample_object_dir("box"))], dataset_dir=str(out), frames=4,
                                    config_yaml=TINY, resume=True)
        result, seen = GenerateDataset.Result(), []
        node.run_goal(goal, result, seen.append, threading.Event())
    finally:
        node.destroy_node()
        rclpy.shutdown()
    summary = json.loads(result.message)
    assert summary["cluster"] == "local" and summary["frames"] == 4 and summary["resumed_frames"] == 0
    assert read_manifest(out)["complete"] and seen[-1].info["frames_done"] == 4

    (out / "models" / "box" / "mesh.obj").unlink()  # no refinement model after training: not what this tests
    node = _node("n2d_dope.nodes.train_node", "TrainNode", "ddp:=2")
    try:
        assert node.cfg.ddp == 2
        goal = Train.Goal(dataset_dir=str(out), model_dir=str(tmp_path / "dope"), preset="tiny", resume=True,
                          config_yaml="{epochs: 2, holdout: 0.0, int8: false}")
        result = Train.Result()
        node.run_goal(goal, result, lambda p: None, threading.Event())
    finally:
        node.destroy_node()
        rclpy.shutdown()
    summary = json.loads(result.summary_json)
    assert summary["processes"] == 2 and summary["steps"] == summary["planned_steps"]
    assert read_manifest(tmp_path / "dope")["complete"] and (tmp_path / "dope" / "model.onnx").is_file()
