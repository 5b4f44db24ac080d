"""The nodes' parameters are their user tier: at most 15 each (as `ros2 param list` shows them, through rclpy's
list_parameters service), read-only; the expert settings come from the `config_file` YAML, and an expert
setting given as a parameter is refused with a hint."""

import importlib
import threading
import typing

import pytest
import rclpy
import yaml
from helpers import list_parameters, wait_future
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor

from n2d_common.config import flat_fields
from n2d_common.errors import ConfigError
from n2d_common.ros import read_node_config, user_parameters
from n2d_reconstruct.nodes.reconstruct_node import ReconstructNodeConfig

MAX_PARAMETERS = 15
CONFIGS = {
    "turntable_node": ("n2d_capture.nodes.turntable_node", "TurntableNodeConfig"),
    "capture_node": ("n2d_capture.nodes.capture_node", "CaptureNodeConfig"),
    "reconstruct_node": ("n2d_reconstruct.nodes.reconstruct_node", "ReconstructNodeConfig"),
    "dataset_node": ("n2d_dataset.nodes.dataset_node", "DatasetNodeConfig"),
    "train_node": ("n2d_dope.nodes.train_node", "TrainNodeConfig"),
    "dope_node": ("n2d_dope.nodes.dope_node", "DopeNodeConfig"),
    "pipeline_node": ("n2d.nodes.pipeline_node", "PipelineNodeConfig"),
    "sim_camera_node": ("n2d_sim.nodes.sim_camera_node", "SimCameraNodeConfig"),
    "sim_turntable_node": ("n2d_sim.nodes.sim_turntable_node", "SimTurntableConfig"),
}
EXTRA = {"dope_node": ["models"]}
"""Parameters a node declares besides its config's user tier and config_file."""
IN_PROCESS = {"capture": ("n2d_capture.nodes.capture_node", "CaptureNode", "capture_node"),
              "reconstruct": ("n2d_reconstruct.nodes.reconstruct_node", "ReconstructNode", "reconstruct_node"),
              "dataset": ("n2d_dataset.nodes.dataset_node", "DatasetNode", "dataset_node"),
              "train": ("n2d_dope.nodes.train_node", "TrainNode", "train_node"),
              "pipeline": ("n2d.nodes.pipeline_node", "PipelineNode", "pipeline_node")}
"""Nodes that start without hardware, models or Blender (turntable, dope and sim_camera are listed where their
launch tests run them)."""


def expected_parameters(node: str) -> list[str]:
    """The parameters `node` must list: its config's user tier (without the mappings, which are no parameters),
    config_file and its extras."""
    module, cls = CONFIGS[node]
    config = getattr(importlib.import_module(module), cls)
    mappings = {name for name, tp, *_ in flat_fields(config) if typing.get_origin(tp) is dict or tp is dict}
    return sorted([n for n in user_parameters(config) if n not in mappings] + ["config_file"] + EXTRA.get(node, []))


@pytest.mark.parametrize("node", sorted(CONFIGS))
def test_user_tier_fits(node):
    names = expected_parameters(node)
    print(f"{node}: {len(names)} parameters")
    assert len(names) <= MAX_PARAMETERS, names


@pytest.fixture
def ros(ros_domain):
    """rclpy initialised and an executor spinning in a thread; yields (make, client node): `make(module, class)`
    constructs a node onto the executor."""
    rclpy.init()
    executor = SingleThreadedExecutor()
    nodes = []

    def make(module: str, cls: str):
        node = getattr(importlib.import_module(module), cls)()
        nodes.append(node)
        executor.add_node(node)
        return node

    client = rclpy.create_node("test_parameters")
    executor.add_node(client)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield make, client
    finally:
        executor.shutdown(timeout_sec=5.0)
        for node in [*nodes, client]:
            node.destroy_node()
        rclpy.shutdown()


def test_nodes_list_their_user_tier(ros):
    make, client = ros
    for name, (module, cls, config) in IN_PROCESS.items():
        make(module, cls)
        listed = list_parameters(client, f"/{name}")
        print(f"{name}: {len(listed)} parameters")
        assert listed == expected_parameters(config)
    # read-only: a value the node read at start-up cannot be changed under it
    set_client = client.create_client(SetParameters, "/dataset/set_parameters")
    assert set_client.wait_for_service(timeout_sec=10)
    value = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=7)
    future = set_client.call_async(SetParameters.Request(parameters=[Parameter(name="dataset.frames", value=value)]))
    assert not wait_future(future, 10).results[0].successful


@pytest.fixture
def expert_file(tmp_path):
    path = tmp_path / "reconstruct.yaml"
    path.write_text(yaml.safe_dump({"reconstruct": {"neus": {"steps": 7, "optim": {"lr": 0.002}},
                                                    "mesh": {"voxel_m": 0.004}, "texture.size_px": 512}}))
    return path


def test_config_file_sets_expert_values_and_parameters_win(tmp_path, expert_file, ros_domain):
    rclpy.init(args=["--ros-args", "-p", f"config_file:={expert_file}", "-p", "reconstruct.mesh.voxel_m:=0.003"])
    try:
        node = importlib.import_module("n2d_reconstruct.nodes.reconstruct_node").ReconstructNode()
        cfg = node.cfg.reconstruct
        assert (cfg.neus.steps, cfg.neus.optim.lr, cfg.texture.size_px) == (7, 0.002, 512)  # from the file
        assert cfg.mesh.voxel_m == 0.003  # the parameter overrides the file
        assert node.get_parameter("reconstruct.neus.steps").value == 7  # a user parameter shows the file's value
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_ros_parameters_file_is_a_config_file(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"reconstruct.neus.steps": 9,
                                                                "reconstruct.method": "neus"}}}))
    cfg = read_node_config(ReconstructNodeConfig, str(path)).reconstruct
    assert (cfg.neus.steps, cfg.method) == (9, "neus")


@pytest.mark.parametrize("text, words", [
    ("reconstruct: {neus: {stepz: 3}}", ["unknown key", "stepz"]),
    ("reconstruct: {neus: {steps: many}}", ["neus.steps", "many"]),
    ("reconstruct: {neus: {lr: 0.1}}", ["unknown key", "lr", "optim"]),  # a key of the flat layout
    ("reconstruct: [1, 2", ["not valid YAML"]),
])
def test_bad_config_file_says_what_and_where(tmp_path, text, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        read_node_config(ReconstructNodeConfig, str(path))
    assert all(w in str(info.value) for w in [str(path), *words]), str(info.value)
    with pytest.raises(ConfigError, match="cannot read"):
        read_node_config(ReconstructNodeConfig, str(tmp_path / "missing.yaml"))


def test_expert_setting_as_parameter_is_refused(ros_domain):
    rclpy.init(args=["--ros-args", "-p", "reconstruct.neus.optim.lr:=0.1"])
    try:
        with pytest.raises(ConfigError) as info:
            importlib.import_module("n2d_reconstruct.nodes.reconstruct_node").ReconstructNode()
        assert "reconstruct.neus.optim.lr" in info.value.message and "config_file" in info.value.hint
    finally:
        rclpy.shutdown()
