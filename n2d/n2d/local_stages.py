"""The pipeline's stages as library calls in this process: the `StageRunner` of `n2d pipeline`.

`ActionStages` (stage_clients.py) sends each stage to its node; `LibraryStages` calls the same library functions
those nodes call (reconstruct, generate_dataset, train, the evaluation), with the defaults of their configs under
the run's overrides, and with resume: an unfinished output continues. It needs no ROS, so it runs wherever n2d is
installed, e.g. in a task on a Ray cluster node (n2d/objects.py). The capture stages drive the turntable and are
refused here: objects are captured beforehand (`n2d capture`, the Pipeline action) and their runs continue here.
"""

from __future__ import annotations

import threading
from pathlib import Path

from n2d.pipeline import RECONSTRUCT_SUMMARY, TRAIN_SUMMARY, evaluate_run
from n2d_common.config import from_dict, merge, to_dict
from n2d_common.errors import ConfigError
from n2d_common.progress import ProgressFn


class LibraryStages:
    """Runs each stage by calling its library function in this process (see the module doc)."""

    def capture(self, session_dir: Path, overrides: dict, *, empty_plate: bool, progress: ProgressFn,
                cancel: threading.Event) -> dict:
        raise ConfigError(f"capturing {session_dir} needs the turntable, which n2d pipeline does not drive",
                          "capture the object first (n2d capture, or the Pipeline action with stages empty_plate, "
                          "capture, test_capture), then run the remaining stages here")

    def reconstruct(self, session_dir: Path, model_dir: Path, overrides: dict, *, progress: ProgressFn,
                    cancel: threading.Event) -> dict:
        from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct

        cfg = from_dict(ReconstructConfig, merge(to_dict(ReconstructConfig()), overrides))
        report = reconstruct(session_dir, model_dir, cfg, progress=progress, cancel=cancel)
        return {k: report[k] for k in RECONSTRUCT_SUMMARY if k in report}

    def dataset(self, model_dir: Path, dataset_dir: Path, frames: int, seed: int, overrides: dict, *,
                progress: ProgressFn, cancel: threading.Event) -> dict:
        from n2d_dataset.config import DatasetConfig
        from n2d_dataset.generate import generate_dataset

        cfg = from_dict(DatasetConfig, merge(to_dict(DatasetConfig()), {**overrides, "frames": frames, "seed": seed}))
        return generate_dataset([model_dir], dataset_dir, cfg, progress=progress, cancel=cancel)

    def train(self, dataset_dir: Path, dope_dir: Path, object_name: str, preset: str, overrides: dict, *,
              progress: ProgressFn, cancel: threading.Event) -> dict:
        from n2d_dope.config import TrainConfig
        from n2d_dope.train import train

        cfg = from_dict(TrainConfig, merge(to_dict(TrainConfig.preset(preset)), overrides))
        summary = train(dataset_dir, dope_dir, cfg, object_name=object_name, progress=progress, cancel=cancel)
        return {k: summary[k] for k in TRAIN_SUMMARY if k in summary}

    def evaluate(self, dope_dir: Path, tests: dict, precisions: list[str], refined: bool, *, progress: ProgressFn,
                 cancel: threading.Event) -> dict:
        return evaluate_run(dope_dir, tests, precisions, refined, progress=progress, cancel=cancel)
