"""train_node: the `train` action: annotated dataset -> trained DOPE network exported to ONNX (a DOPE model directory).

Training runs in a worker process (torch takes the cores; the node stays responsive, a crash cannot take it
down); its progress becomes the action feedback (stage, step, loss, ETA). With the `ddp` parameter the worker
trains in that many processes (n2d_dope/distributed.py). Cancel makes the job save its checkpoint and stop; a
later goal with `resume: true` and the same config continues at the exact batch.
Parameters are the fields of `TrainConfig` (a goal's `preset` replaces them as the base, keeping the node's
device and threads; its `config_yaml` overrides them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from rclpy.node import Node

from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.progress import Progress
from n2d_common.ros import JobActionServer, declare_config, run_node
from n2d_common.worker import run_in_worker
from n2d_dope.config import TrainConfig
from n2d_dope.train import train
from n2d_interfaces.action import Train

MACHINE_FIELDS = ("device", "threads")
"""TrainConfig fields that describe this machine, not the training: a goal's preset keeps the node's values."""


@dataclass
class TrainNodeConfig:
    """Parameters of train_node."""

    ROS_PARAMETERS = ("train.backbone", "train.input_size", "train.init_model", "train.epochs", "train.max_minutes",
                      "train.batch_size", "train.lr", "train.symmetry_aware", "train.holdout", "train.device",
                      "train.threads", "train.seed", "train.int8", "ddp")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    train: TrainConfig = field(default_factory=TrainConfig)
    """Defaults of every training run."""
    ddp: int = 0
    """Train data-parallel in this many processes of this machine (torch.distributed: gloo on CPUs, NCCL on GPUs;
    0 or 1: one process)."""

    def __post_init__(self):
        if self.ddp < 0:
            raise ValueError("ddp must be >= 0")


def _job(dataset_dir: str, model_dir: str, config: dict, object_name: str | None, overwrite: bool, ddp: int,
         progress, cancel) -> dict:
    return train(dataset_dir, model_dir, from_dict(TrainConfig, config), object_name=object_name,
                 overwrite=overwrite, progress=progress, cancel=cancel, ddp=ddp)


def _feedback(p: Progress) -> Train.Feedback:
    return Train.Feedback(progress=p.fraction, stage=p.stage, eta_s=p.eta_s,
                          step=int(p.info.get("step", 0)), steps_total=int(p.info.get("steps", 0)),
                          loss=float(p.info.get("loss", 0.0)))


class TrainNode(Node):
    NAME = "train"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, TrainNodeConfig)
        self.jobs = JobActionServer(self, Train, "train", self.run_goal,
                                    accept=lambda g: bool(g.dataset_dir and g.model_dir), feedback=_feedback)
        self.get_logger().info("train ready")

    def _goal_config(self, goal: Train.Goal) -> TrainConfig:
        data = to_dict(self.cfg.train)
        if goal.preset:
            data = {**to_dict(TrainConfig.preset(goal.preset)), **{k: data[k] for k in MACHINE_FIELDS}}
        return from_dict(TrainConfig, merge(data, parse_mapping(goal.config_yaml, "goal config_yaml")))

    def run_goal(self, goal: Train.Goal, result: Train.Result, progress, cancel) -> None:
        result.model_dir = goal.model_dir
        summary = run_in_worker(_job, {"dataset_dir": goal.dataset_dir, "model_dir": goal.model_dir,
                                       "config": to_dict(self._goal_config(goal)),
                                       "object_name": goal.object_name or None, "overwrite": not goal.resume,
                                       "ddp": self.cfg.ddp},
                                progress=progress, cancel=cancel, children=self.cfg.ddp > 1)
        result.summary_json = json.dumps(summary)

    def destroy_node(self) -> None:
        self.jobs.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(TrainNode, args)


if __name__ == "__main__":
    main()
