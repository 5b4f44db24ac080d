"""The pipeline's stages through the stage nodes' actions: capture_node, reconstruct_node, dataset_node, train_node.

`ActionStages` is the `StageRunner` of `pipeline_node` (and so of `n2d demo`): each stage is one goal to
its node, sent with `resume` (the node continues unfinished work in the output directory), its feedback
turned into Progress, a cancel forwarded as a goal cancel. The evaluation runs in a worker process of
the calling node. Action names are relative to the node's namespace (`/n2d` in the launch files).
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import yaml
from rclpy.node import Node

from n2d.pipeline import RECONSTRUCT_SUMMARY, TRAIN_SUMMARY, evaluate_run
from n2d_common.progress import Progress, ProgressFn
from n2d_common.ros import SafeActionClient, call_action
from n2d_common.worker import run_in_worker
from n2d_interfaces.action import Capture, GenerateDataset, Reconstruct, Train


def feedback_progress(fb) -> Progress:
    """Progress of a stage action's feedback (all have progress, stage and eta_s; the rest varies)."""
    parts = []
    if getattr(fb, "views_total", 0):
        parts.append(f"view {min(fb.view + 1, fb.views_total)}/{fb.views_total}")
    if getattr(fb, "frames_total", 0):
        parts.append(f"frame {fb.frames_done}/{fb.frames_total}")
    if getattr(fb, "steps_total", 0):
        parts.append(f"step {fb.step}/{fb.steps_total}")
    if getattr(fb, "loss", 0.0):
        parts.append(f"loss {fb.loss:.4g}")
    return Progress(float(fb.progress), fb.stage, float(fb.eta_s), ", ".join(parts))


def _yaml(overrides: dict) -> str:
    return yaml.safe_dump(overrides) if overrides else ""


class ActionStages:
    """Runs each stage as a goal of its node's action (see the module doc)."""

    def __init__(self, node: Node, server_timeout_s: float = 60.0):
        self.capture_client = SafeActionClient(node, Capture, "capture")
        self.reconstruct_client = SafeActionClient(node, Reconstruct, "reconstruct")
        self.dataset_client = SafeActionClient(node, GenerateDataset, "generate_dataset")
        self.train_client = SafeActionClient(node, Train, "train")
        self.server_timeout_s = server_timeout_s

    def _call(self, client, goal, what: str, progress: ProgressFn, cancel: threading.Event):
        return call_action(client, goal, what=what, feedback=lambda fb: progress(feedback_progress(fb)),
                           cancel=cancel, server_timeout_s=self.server_timeout_s)

    def capture(self, session_dir: Path, overrides: dict, *, empty_plate: bool, progress: ProgressFn,
                cancel: threading.Event) -> dict:
        goal = Capture.Goal(session_dir=str(session_dir), views=int(overrides["sweep"]["views"]),
                            empty_plate=empty_plate, config_yaml=_yaml(overrides))
        result = self._call(self.capture_client, goal, "capture_node", progress, cancel)
        return {"views": result.views_captured}

    def reconstruct(self, session_dir: Path, model_dir: Path, overrides: dict, *, progress: ProgressFn,
                    cancel: threading.Event) -> dict:
        goal = Reconstruct.Goal(session_dir=str(session_dir), model_dir=str(model_dir),
                                method=overrides.get("method", ""), config_yaml=_yaml(overrides), resume=True)
        report = json.loads(self._call(self.reconstruct_client, goal, "reconstruct_node", progress, cancel).report_json)
        return {k: report[k] for k in RECONSTRUCT_SUMMARY if k in report}

    def dataset(self, model_dir: Path, dataset_dir: Path, frames: int, seed: int, overrides: dict, *,
                progress: ProgressFn, cancel: threading.Event) -> dict:
        goal = GenerateDataset.Goal(model_dirs=[str(model_dir)], dataset_dir=str(dataset_dir), frames=frames,
                                    config_yaml=_yaml({**overrides, "seed": seed}), resume=True)
        return json.loads(self._call(self.dataset_client, goal, "dataset_node", progress, cancel).message)

    def train(self, dataset_dir: Path, dope_dir: Path, object_name: str, preset: str, overrides: dict, *,
              progress: ProgressFn, cancel: threading.Event) -> dict:
        goal = Train.Goal(dataset_dir=str(dataset_dir), model_dir=str(dope_dir), object_name=object_name,
                          preset=preset, config_yaml=_yaml(overrides), resume=True)
        summary = json.loads(self._call(self.train_client, goal, "train_node", progress, cancel).summary_json)
        return {k: summary[k] for k in TRAIN_SUMMARY if k in summary}

    def evaluate(self, dope_dir: Path, tests: dict, precisions: list[str], refined: bool, *, progress: ProgressFn,
                 cancel: threading.Event) -> dict:
        return run_in_worker(evaluate_run, {"dope_dir": str(dope_dir), "tests": {k: str(v) for k, v in tests.items()},
                                            "precisions": precisions, "refined": refined},
                             progress=progress, cancel=cancel)
