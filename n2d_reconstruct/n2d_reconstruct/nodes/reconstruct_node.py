"""reconstruct_node: the `reconstruct` action: capture session -> textured, metric model directory.

The job runs in a worker process (the node stays responsive, a crash cannot take it down); its
progress becomes the action feedback (phase, step, loss, ETA). Cancel makes the job save its state
and stop; a later goal with `resume: true` and the same config continues from there. Parameters are
the fields of `ReconstructConfig` (a goal's `method` and `config_yaml` override them).
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
from n2d_common.worker import run_in_worker
from n2d_interfaces.action import Reconstruct
from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct


@dataclass
class ReconstructNodeConfig:
    """Parameters of reconstruct_node."""

    reconstruct: ReconstructConfig = field(default_factory=ReconstructConfig)
    """Defaults of every reconstruction."""


def _job(session_dir: str, model_dir: str, config: dict, overwrite: bool, progress, cancel) -> dict:
    return reconstruct(session_dir, model_dir, from_dict(ReconstructConfig, config), overwrite=overwrite,
                       progress=progress, cancel=cancel)


class ReconstructNode(Node):
    NAME = "reconstruct"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, ReconstructNodeConfig)
        self._busy = threading.Lock()
        self._cancel = threading.Event()
        self.server = ActionServer(self, Reconstruct, "reconstruct", execute_callback=self.execute_reconstruct,
                                   goal_callback=self.on_goal, cancel_callback=self.on_cancel,
                                   callback_group=ReentrantCallbackGroup())
        self.get_logger().info("reconstruct ready")

    def on_goal(self, goal: Reconstruct.Goal) -> GoalResponse:
        ok = goal.session_dir and goal.model_dir and not self._busy.locked()
        return GoalResponse.ACCEPT if ok else GoalResponse.REJECT

    def on_cancel(self, _goal_handle) -> CancelResponse:
        self._cancel.set()
        return CancelResponse.ACCEPT

    def _goal_config(self, goal: Reconstruct.Goal) -> ReconstructConfig:
        data = to_dict(self.cfg.reconstruct)
        if goal.method:
            data["method"] = goal.method
        return from_dict(ReconstructConfig, merge(data, parse_mapping(goal.config_yaml, "goal config_yaml")))

    def execute_reconstruct(self, goal_handle) -> Reconstruct.Result:
        goal = goal_handle.request
        result = Reconstruct.Result(model_dir=goal.model_dir)
        with self._busy:
            self._cancel.clear()

            def feedback(p: Progress) -> None:
                goal_handle.publish_feedback(Reconstruct.Feedback(
                    progress=p.fraction, stage=p.stage, eta_s=p.eta_s,
                    step=int(p.info.get("step", 0)), steps_total=int(p.info.get("steps", 0)),
                    loss=float(p.info.get("loss", 0.0))))

            def job() -> None:
                report = run_in_worker(_job, {"session_dir": goal.session_dir, "model_dir": goal.model_dir,
                                              "config": to_dict(self._goal_config(goal)),
                                              "overwrite": not goal.resume},
                                       progress=feedback, cancel=self._cancel)
                result.report_json = json.dumps(report)

            return run_goal(goal_handle, result, job, self.get_logger())

    def destroy_node(self) -> None:
        self._cancel.set()
        self.server.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(ReconstructNode, args)


if __name__ == "__main__":
    main()
