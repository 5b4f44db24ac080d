"""The pipeline's run directory rules and bad input (no stage runs), and pipeline_node's services across
processes as a planner that only speaks services uses them: start, status, cancel, a resumed start, a refused
second start and a run that fails with a clear message. The whole pipeline through the action: test_demo.py."""

import json
import math
import time

import pytest
from std_srvs.srv import Trigger

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d.pipeline import FAST_TRAIN, PipelineConfig, run_pipeline
from n2d_capture.capture import CaptureConfig
from n2d_common.config import to_dict
from n2d_common.contracts import open_stage, write_manifest
from n2d_common.errors import ConfigError, ContractError
from n2d_common.formats.session import read_session
from n2d_common.ros import background_node, wait_future
from n2d_dope.config import TIMED_EPOCHS
from n2d_interfaces.srv import PipelineStatus, StartPipeline

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more


class NoStages:
    """A StageRunner that fails the test when any stage is asked to run: these checks come first."""

    def __getattr__(self, stage):
        raise AssertionError(f"stage {stage} ran")


def test_config_checks_and_test_sweep_angles():
    for bad in ({"views": 0}, {"frames": 0}, {"test_views": -1}, {"train_minutes": -1.0}, {"precisions": ["fp16"]},
                {"precisions": []}):
        with pytest.raises(ValueError):
            PipelineConfig(**bad)
    cfg = PipelineConfig(views=24, test_views=8, test_frames=0, capture={"sweep": {"frame_timeout_s": 30.0}})
    assert cfg.stages() == ["capture", "test_capture", "reconstruct", "dataset", "train", "evaluate"]
    assert cfg.capture_overrides(test=False)["sweep"] == {"frame_timeout_s": 30.0, "views": 24}
    test = cfg.capture_overrides(test=True)["sweep"]
    assert test["views"] == 8 and math.isclose(test["start_angle_rad"], math.pi / 24)  # between the object views
    # train_minutes is how long training runs: the preset's epochs do not cut it short, given epochs still do
    assert PipelineConfig(train_minutes=0.0, train={}).train_overrides() == {}
    assert PipelineConfig().train_overrides() == {"epochs": TIMED_EPOCHS, **FAST_TRAIN,
                                                  "max_minutes": PipelineConfig().train_minutes}
    assert PipelineConfig(train_minutes=8.0, train={}).train_overrides() == {"epochs": TIMED_EPOCHS, "max_minutes": 8.0}
    assert PipelineConfig(train_minutes=8.0, train={"epochs": 300}).train_overrides()["epochs"] == 300


def test_two_placements_sweep_the_test_set_first_and_capture_twice():
    with pytest.raises(ValueError, match="placements"):
        PipelineConfig(placements=3)
    cfg = PipelineConfig(placements=2, test_frames=0)
    # the capture leaves the object turned over: the test sweep comes first, while it stands as the model's frame
    assert cfg.stages() == ["test_capture", "capture", "reconstruct", "dataset", "train", "evaluate"]
    assert CaptureConfig(**{k: v for k, v in cfg.capture_overrides(test=False).items() if k != "sweep"}).placements == 2
    assert cfg.capture_overrides(test=True)["placements"] == 1
    assert "placements" not in PipelineConfig().capture_overrides(test=False)  # one-placement configs as before


def test_bad_input_is_refused_before_any_stage_runs(tmp_path):
    cfg = PipelineConfig()
    with pytest.raises(ConfigError, match="not usable"):
        run_pipeline(tmp_path / "a", "my mug!", cfg, NoStages())
    with pytest.raises(ConfigError, match="unknown stage"):
        run_pipeline(tmp_path / "a", "mug", cfg, NoStages(), stages=["capture", "paint"])
    with pytest.raises(ConfigError, match="place"):
        run_pipeline(tmp_path / "a", "mug", cfg, NoStages(), stages=["empty_plate", "capture"])
    with pytest.raises(ContractError, match="empty-plate sweep"):
        run_pipeline(tmp_path / "a", "mug", cfg, NoStages())
    with pytest.raises(ContractError, match="needs the output of dataset"):
        run_pipeline(tmp_path / "a", "mug", cfg, NoStages(), stages=["train"])
    assert not (tmp_path / "a").exists()  # a refused call writes nothing

    # a run of the mug with the default config (its manifest, as the first stage of a run writes it)
    write_manifest(tmp_path / "a", "run", config={"object_name": "mug", **to_dict(cfg)}, complete=False)
    with pytest.raises(ContractError, match="needs the output of dataset"):
        run_pipeline(tmp_path / "a", "mug", cfg, NoStages(), stages=["train"])
    with pytest.raises(ContractError, match="another object or config"):
        run_pipeline(tmp_path / "a", "mug", PipelineConfig(frames=10), NoStages(), stages=["train"])
    with pytest.raises(ContractError, match="another object or config"):
        run_pipeline(tmp_path / "a", "bowl", cfg, NoStages(), stages=["train"])
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "IMG_0001.jpg").write_bytes(b"")
    with pytest.raises(ContractError, match="not an n2d run"):
        run_pipeline(foreign, "mug", cfg, NoStages())
    assert (foreign / "IMG_0001.jpg").is_file()


def _status(client) -> PipelineStatus.Response:
    return wait_future(client.call_async(PipelineStatus.Request()), 30, "status")


def _wait_state(client, states: set[str], timeout_s: float, logs: list[str]) -> PipelineStatus.Response:
    deadline = time.monotonic() + timeout_s
    while (status := _status(client)).state not in states:
        assert time.monotonic() < deadline, (status, "\n".join(logs[-30:]))
        time.sleep(0.5)
    return status


@pytest.mark.timeout(600)
def test_pipeline_services(tmp_path, ros_domain):
    logs: list[str] = []
    args = {"port": str(tmp_path / "ttyDXL"), "control": str(tmp_path / "servo.ctl")}
    run_dir = tmp_path / "run"
    config = "views: 6\ntest_views: 0\nrequire_empty_plate: false\ncapture: {sweep: {frame_timeout_s: 60.0}}\n"
    request = StartPipeline.Request(object_name="box", run_dir=str(run_dir), config_yaml=config, stages=["capture"])
    with Launch(load("pipeline"), args, log=logs.append) as launch, background_node("test_planner", ros_domain) as node:
        start = node.create_client(StartPipeline, "/n2d/pipeline/start")
        status = node.create_client(PipelineStatus, "/n2d/pipeline/status")
        cancel = node.create_client(Trigger, "/n2d/pipeline/cancel")
        for client in (start, status, cancel):
            assert client.wait_for_service(timeout_sec=120), logs[-20:]
        assert _status(status).state == "idle"
        assert not wait_future(cancel.call_async(Trigger.Request()), 30, "cancel").success  # nothing to cancel

        # start, see it run the capture stage, cancel it: the views taken so far stay for the next start
        assert wait_future(start.call_async(request), 30, "start").accepted
        busy = wait_future(start.call_async(request), 30, "start")
        assert not busy.accepted and "running" in busy.message
        deadline = time.monotonic() + 300
        while not ((s := _status(status)).stage == "capture" and "view" in s.message):
            assert s.state == "running" and time.monotonic() < deadline, (s, "\n".join(logs[-30:]))
            time.sleep(0.2)
        assert s.run_dir == str(run_dir) and s.stages_total == 1
        assert wait_future(cancel.call_async(Trigger.Request()), 30, "cancel").success
        assert _wait_state(status, {"cancelled", "failed", "succeeded"}, 180, logs).state == "cancelled"
        assert (run_dir / "capture.partial").is_dir() and not (run_dir / "capture").exists()

        # started again, it resumes the sweep and finishes the stage
        assert wait_future(start.call_async(request), 30, "start").accepted
        done = _wait_state(status, {"cancelled", "failed", "succeeded"}, 300, logs)
        assert done.state == "succeeded", (done.message, "\n".join(logs[-30:]))
        assert "capture" in json.loads(done.summary_json)["stages"]
        assert open_stage(run_dir / "capture", "capture_session")["complete"]
        assert len(read_session(run_dir / "capture").views) == 6

        # a stage whose input is missing fails with a message that says what to run
        request.stages = ["train"]
        assert wait_future(start.call_async(request), 30, "start").accepted
        failed = _wait_state(status, {"cancelled", "failed", "succeeded"}, 60, logs)
        assert failed.state == "failed" and "needs the output of dataset" in failed.message
        assert not launch.dead(), logs[-20:]
