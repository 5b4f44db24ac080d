"""dataset_node: the `generate_dataset` action: model directories -> annotated, domain-randomised dataset.

The frames are rendered by worker processes (one bpy each); this node only forwards their progress as
action feedback (frames done, ETA) and their cancel. A cancelled or failed goal keeps every finished
frame; a later goal for the same dataset with `resume: true` renders only the missing ones. Parameters
are the fields of `DatasetConfig` (a goal's frames, workers, seed and config_yaml override them).
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.progress import Progress
from n2d_common.ros import declare_config, run_goal, run_node
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_interfaces.action import GenerateDataset


@dataclass
class DatasetNodeConfig:
    """Parameters of dataset_node."""

    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    """Defaults of every dataset."""


class DatasetNode(Node):
    NAME = "dataset"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, DatasetNodeConfig)
        self._busy = threading.Lock()
        self._cancel = threading.Event()
        self.server = ActionServer(self, GenerateDataset, "generate_dataset", execute_callback=self.execute,
                                   goal_callback=self.on_goal, cancel_callback=self.on_cancel,
                                   callback_group=ReentrantCallbackGroup())
        self.get_logger().info("dataset ready")

    def on_goal(self, goal: GenerateDataset.Goal) -> GoalResponse:
        ok = len(goal.model_dirs) > 0 and goal.dataset_dir and not self._busy.locked()
        return GoalResponse.ACCEPT if ok else GoalResponse.REJECT

    def on_cancel(self, _goal_handle) -> CancelResponse:
        self._cancel.set()
        return CancelResponse.ACCEPT

    def _goal_config(self, goal: GenerateDataset.Goal) -> DatasetConfig:
        data = to_dict(self.cfg.dataset)
        for name in ("frames", "workers", "seed"):
            if getattr(goal, name):
                data[name] = getattr(goal, name)
        return from_dict(DatasetConfig, merge(data, parse_mapping(goal.config_yaml, "goal config_yaml")))

    def execute(self, goal_handle) -> GenerateDataset.Result:
        goal = goal_handle.request
        result = GenerateDataset.Result(dataset_dir=goal.dataset_dir)
        with self._busy:
            self._cancel.clear()

            def feedback(p: Progress) -> None:
                goal_handle.publish_feedback(GenerateDataset.Feedback(
                    progress=p.fraction, stage=p.stage, eta_s=p.eta_s,
                    frames_done=int(p.info.get("frames_done", 0)), frames_total=int(p.info.get("frames_total", 0))))

            def job() -> None:
                # generate_dataset runs its render workers as processes; this thread only waits for them.
                summary = generate_dataset(list(goal.model_dirs), goal.dataset_dir, self._goal_config(goal),
                                           overwrite=not goal.resume, progress=feedback, cancel=self._cancel)
                result.frames_done = summary["frames"]
                result.message = json.dumps(summary)

            return run_goal(goal_handle, result, job, self.get_logger())

    def destroy_node(self) -> None:
        self._cancel.set()
        self.server.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(DatasetNode, args)


if __name__ == "__main__":
    main()
