"""dataset_node: the `generate_dataset` action: model directories -> annotated, domain-randomised dataset.

The frames are rendered by worker processes (one bpy each); this node only forwards their progress as
action feedback (frames done, ETA) and their cancel; with the `cluster` parameter Ray actors on a cluster
render them instead (n2d_dataset/cluster.py). A cancelled or failed goal keeps every finished
frame; a later goal for the same dataset with `resume: true` renders only the missing ones. Parameters
are the fields of `DatasetConfig` (a goal's frames, workers, seed and config_yaml override them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from rclpy.node import Node

from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.progress import Progress
from n2d_common.ros import JobActionServer, declare_config, run_node
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_interfaces.action import GenerateDataset


@dataclass
class DatasetNodeConfig:
    """Parameters of dataset_node."""

    ROS_PARAMETERS = ("dataset.frames", "dataset.seed", "dataset.workers", "dataset.photoreal_frames",
                      "dataset.camera.width", "dataset.camera.height", "dataset.camera.focal_px",
                      "dataset.scene.distractors", "dataset.scene.in_hand", "dataset.render.engine",
                      "dataset.render.samples", "dataset.render.device", "dataset.render.threads", "cluster")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    """Defaults of every dataset."""
    cluster: str = ""
    """Render every goal's frames on this Ray cluster: ray://HEAD:10001, HEAD:6379, auto or local (empty: local
    worker processes); the frames are written on this machine."""


def _feedback(p: Progress) -> GenerateDataset.Feedback:
    return GenerateDataset.Feedback(progress=p.fraction, stage=p.stage, eta_s=p.eta_s,
                                    frames_done=int(p.info.get("frames_done", 0)),
                                    frames_total=int(p.info.get("frames_total", 0)))


class DatasetNode(Node):
    NAME = "dataset"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, DatasetNodeConfig)
        self.jobs = JobActionServer(self, GenerateDataset, "generate_dataset", self.run_goal,
                                    accept=lambda g: len(g.model_dirs) > 0 and bool(g.dataset_dir),
                                    feedback=_feedback)
        self.get_logger().info("dataset ready")

    def _goal_config(self, goal: GenerateDataset.Goal) -> DatasetConfig:
        data = to_dict(self.cfg.dataset)
        for name in ("frames", "workers", "seed"):
            if getattr(goal, name):
                data[name] = getattr(goal, name)
        return from_dict(DatasetConfig, merge(data, parse_mapping(goal.config_yaml, "goal config_yaml")))

    def run_goal(self, goal: GenerateDataset.Goal, result: GenerateDataset.Result, progress, cancel) -> None:
        # generate_dataset runs its render workers as processes; this thread only waits for them.
        result.dataset_dir = goal.dataset_dir
        summary = generate_dataset(list(goal.model_dirs), goal.dataset_dir, self._goal_config(goal),
                                   overwrite=not goal.resume, progress=progress, cancel=cancel,
                                   cluster=self.cfg.cluster or None)
        result.frames_done = summary["frames"]
        result.message = json.dumps(summary)

    def destroy_node(self) -> None:
        self.jobs.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(DatasetNode, args)


if __name__ == "__main__":
    main()
