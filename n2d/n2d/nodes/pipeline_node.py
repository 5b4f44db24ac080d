"""pipeline_node: the `pipeline` action: an object on the turntable -> a trained, evaluated DOPE model.

A task planner sends one goal (object name, run directory); the node runs the stages of `n2d.pipeline`
through the stage nodes' actions (capture_node, reconstruct_node, dataset_node, train_node), forwards
their progress as feedback and returns the output paths and the evaluation. Planners that only speak
services use `pipeline/start`, `pipeline/status` and `pipeline/cancel` instead. Parameters are the fields
of `PipelineConfig` (a goal's `config_yaml` overrides them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from rclpy.node import Node
from std_srvs.srv import Trigger

from n2d.pipeline import PipelineConfig, RunLayout, check_object_name, run_pipeline
from n2d.stage_clients import ActionStages
from n2d_common.config import from_dict, merge, parse_mapping, to_dict
from n2d_common.progress import Progress
from n2d_common.ros import JobActionServer, declare_config, run_node
from n2d_interfaces.action import Pipeline
from n2d_interfaces.srv import PipelineStatus, StartPipeline


@dataclass
class PipelineNodeConfig:
    """Parameters of pipeline_node."""

    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    """Defaults of every run."""


def _feedback(p: Progress) -> Pipeline.Feedback:
    return Pipeline.Feedback(stage=p.stage, stage_index=int(p.info.get("stage_index", 0)),
                             stages_total=int(p.info.get("stages_total", 0)),
                             stage_progress=float(p.info.get("stage_progress", 0.0)), progress=p.fraction,
                             eta_s=p.eta_s, message=p.message)


class PipelineNode(Node):
    NAME = "pipeline"

    def __init__(self):
        super().__init__(self.NAME)
        self.cfg = declare_config(self, PipelineNodeConfig)
        self.stages = ActionStages(self)
        self.run_dir = ""
        """The run directory of the current or last run."""
        self.jobs = JobActionServer(self, Pipeline, "pipeline", self.run_goal,
                                    accept=lambda g: bool(g.object_name and g.run_dir), feedback=_feedback)
        self.create_service(StartPipeline, "pipeline/start", self.on_start)
        self.create_service(PipelineStatus, "pipeline/status", self.on_status)
        self.create_service(Trigger, "pipeline/cancel", self.on_cancel)
        self.get_logger().info("pipeline ready")

    def _goal_config(self, goal) -> PipelineConfig:
        return from_dict(PipelineConfig, merge(to_dict(self.cfg.pipeline),
                                               parse_mapping(goal.config_yaml, "goal config_yaml")))

    def run_goal(self, goal, result: Pipeline.Result, progress, cancel) -> None:
        name = check_object_name(goal.object_name)
        layout = RunLayout(Path(goal.run_dir).absolute())
        result.run_dir = self.run_dir = str(layout.root)
        status = run_pipeline(layout.root, name, self._goal_config(goal), self.stages, stages=list(goal.stages),
                              overwrite=goal.overwrite, progress=progress, cancel=cancel)
        result.session_dir, result.model_dir = str(layout.output("capture")), str(layout.output("reconstruct"))
        result.dataset_dir, result.dope_model_dir = str(layout.output("dataset")), str(layout.output("train"))
        result.summary_json = json.dumps(status)
        self.get_logger().info(f"pipeline: {name} finished in {result.run_dir}")

    def on_start(self, request: StartPipeline.Request, response: StartPipeline.Response):
        goal = Pipeline.Goal(object_name=request.object_name, run_dir=request.run_dir,
                             config_yaml=request.config_yaml, stages=list(request.stages), overwrite=request.overwrite)
        response.message = self.jobs.start(goal)
        response.accepted = not response.message
        return response

    def on_status(self, _request, response: PipelineStatus.Response):
        jobs, p, result = self.jobs, self.jobs.progress, self.jobs.result
        response.state, response.run_dir = jobs.state, self.run_dir
        if p is not None:
            feedback = _feedback(p)
            response.stage, response.stage_index, response.stages_total = (feedback.stage, feedback.stage_index,
                                                                           feedback.stages_total)
            response.progress, response.eta_s, response.message = feedback.progress, feedback.eta_s, feedback.message
        if result is not None:
            response.summary_json = result.summary_json
            response.message = result.message or response.message
        return response

    def on_cancel(self, _request, response: Trigger.Response):
        response.success = self.jobs.state == "running"
        response.message = "cancelling" if response.success else "no run in progress"
        if response.success:
            self.jobs.cancel.set()
        return response

    def destroy_node(self) -> None:
        self.jobs.destroy()
        super().destroy_node()


def main(args=None) -> None:
    run_node(PipelineNode, args)


if __name__ == "__main__":
    main()
