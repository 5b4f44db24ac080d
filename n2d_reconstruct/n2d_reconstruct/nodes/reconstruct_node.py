"""reconstruct_node: the `reconstruct` action: capture session -> textured, metric model directory.

The job runs in a worker process (the node stays responsive, a crash cannot take it down); its
progress becomes the action feedback (phase, step, loss, ETA). Cancel makes the job save its state
and stop; a later goal with `resume: true` and the same config continues from there. Parameters are
the fields of `ReconstructConfig` (a goal's `method` and `config_yaml` override them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from rclpy.node import Node

from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.progress import Progress
from n2d_common.ros import JobActionServer, declare_config, run_node
from n2d_common.worker import run_in_worker
from n2d_interfaces.action import Reconstruct
from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct


@dataclass
class ReconstructNodeConfig:
    """Parameters of reconstruct_node."""

    ROS_PARAMETERS = ("reconstruct.method", "reconstruct.object_name", "reconstruct.holdout_every",
                      "reconstruct.symmetry", "reconstruct.min_views", "reconstruct.mesh.voxel_m",
                      "reconstruct.mesh.target_faces", "reconstruct.refine.enabled", "reconstruct.texture.size_px",
                      "reconstruct.neus.steps", "reconstruct.neus.device", "reconstruct.neus.seed")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    reconstruct: ReconstructConfig = field(default_factory=ReconstructConfig)
    """Defaults of every reconstruction."""


def _job(session_dir: str, model_dir: str, config: dict, overwrite: bool, progress, cancel) -> dict:
    return reconstruct(session_dir, model_dir, from_dict(ReconstructConfig, config), overwrite=overwrite,
                       progress=progress, cancel=cancel)


def _feedback(p: Progress) -> Reconstruct.Feedback:
    return Reconstruct.Feedback(progress=p.fraction, stage=p.stage, eta_s=p.eta_s, step=int(p.info.get("step", 0)),
                                steps_total=int(p.info.get("steps", 0)), loss=float(p.info.get("loss", 0.0)))


class ReconstructNode(Node):
    NAME = "reconstruct"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, ReconstructNodeConfig)
        self.jobs = JobActionServer(self, Reconstruct, "reconstruct", self.run_goal,
                                    accept=lambda g: bool(g.session_dir and g.model_dir), feedback=_feedback)
        self.get_logger().info("reconstruct ready")

    def _goal_config(self, goal: Reconstruct.Goal) -> ReconstructConfig:
        data = to_dict(self.cfg.reconstruct)
        if goal.method:
            data["method"] = goal.method
        return from_dict(ReconstructConfig, merge(data, parse_mapping(goal.config_yaml, "goal config_yaml")))

    def run_goal(self, goal: Reconstruct.Goal, result: Reconstruct.Result, progress, cancel) -> None:
        result.model_dir = goal.model_dir
        report = run_in_worker(_job, {"session_dir": goal.session_dir, "model_dir": goal.model_dir,
                                      "config": to_dict(self._goal_config(goal)), "overwrite": not goal.resume},
                               progress=progress, cancel=cancel)
        result.report_json = json.dumps(report)

    def destroy_node(self) -> None:
        self.jobs.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(ReconstructNode, args)


if __name__ == "__main__":
    main()
