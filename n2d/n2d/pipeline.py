"""The whole pipeline as one resumable run: capture -> reconstruct -> dataset -> train -> evaluate.

A run directory holds every stage's output under a fixed name (`RunLayout`), the run's manifest
(`n2d.json`, kind "run", complete only once every stage has finished) and `run.json`, rewritten after
each stage: what ran, for how long, where its output is, and the evaluation. A stage whose output is
complete is skipped and an unfinished one resumes (every stage writes through `stage_output`, so its
partial work survives a kill): the same call after Ctrl-C, a cancel or a crash continues where it stopped.

The stages run through a `StageRunner`; `pipeline_node` and `n2d demo` use the stage nodes' actions
(`n2d.stage_clients.ActionStages`). The evaluation runs here: ADD / ADD-S of the DOPE model on the
held-out synthetic frames and on the board-posed test sweep (a real-world test set: captured at angles
between the object sweep's, with ground truth from the ChArUco board).

    capture       object sweep(s)                  -> capture/       (capture session)
    test_capture  sweep half a step off the first  -> capture_test/  (capture session)
    reconstruct   capture/                         -> model/         (textured metric mesh)
    dataset       model/                           -> dataset/       (BOP + DOPE, seed)
    test_dataset  model/                           -> dataset_test/  (seed + 1)
    train         dataset/                         -> dope/          (ONNX model)
    evaluate      dope/, dataset_test/, capture_test/ -> dope/eval.json, run.json

`empty_plate` is a stage run only when asked for: the empty-plate sweep into `capture/` (the background
reference of the masks), for a caller who has cleared the plate; the `capture` stage then completes it.
With `placements: 2` the test sweep runs before the object sweeps (`PLACED_STAGES`): the capture stage waits for
the object to be turned over between its two sweeps and leaves it so.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, read_manifest, write_manifest
from n2d_common.errors import Cancelled, ConfigError, ContractError, N2DError
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_dope.config import TIMED_EPOCHS

STAGES = ("capture", "test_capture", "reconstruct", "dataset", "test_dataset", "train", "evaluate")
"""The stages of a run, in order."""
PLACED_STAGES = ("test_capture", "capture", *STAGES[2:])
"""The order of a run of two placements: the test sweep first, while the object stands as it first stood (the model's
frame), since the capture leaves it turned over."""
EMPTY_PLATE = "empty_plate"
"""The optional stage before `capture` (see the module doc)."""
OUTPUTS = {EMPTY_PLATE: "capture", "capture": "capture", "test_capture": "capture_test", "reconstruct": "model",
           "dataset": "dataset", "test_dataset": "dataset_test", "train": "dope"}
"""Output directory of each stage inside the run directory."""
NEEDS = {"capture": (), "test_capture": (), "reconstruct": ("capture",), "dataset": ("reconstruct",),
         "test_dataset": ("reconstruct",), "train": ("dataset",), "evaluate": ("train",)}
"""The stages whose output each stage reads."""
CAPTURE_STAGES = (EMPTY_PLATE, "capture", "test_capture")
"""The stages that drive the turntable and the camera (the rest run anywhere, e.g. on a cluster)."""
RECONSTRUCT_SUMMARY = ("model", "heldout", "geometry", "timings_s", "placements")
"""What run.json keeps of a reconstruction's report."""
TRAIN_SUMMARY = ("backbone", "parameters", "steps", "train_frames", "train_seconds", "held_out_loss", "device")
"""What run.json keeps of a training's summary."""
WEIGHTS = {EMPTY_PLATE: 2.0, "capture": 3.0, "test_capture": 1.0, "reconstruct": 4.0, "dataset": 10.0,
           "test_dataset": 1.0, "train": 10.0, "evaluate": 0.5}
"""Typical share of a run's time (the default demo on 2 cores), for the overall progress."""


FAST_DATASET = {"render": {"engine": "raster"}, "camera": {"width": 320, "height": 320, "focal_px": 900.0}}
"""The training set a run renders by default: the fast rasterizer, frames of 320 x 320 pixels at the focal length
the network learns at (900 px: the lite preset's 1.5 x zoom of a 600 px camera), so every rendered pixel is one a
240 x 240 training window can use and none is upsampled (docs/dope.md)."""
FAST_TRAIN = {"crop": True, "zoom": 2 / 3, "input_size": [160, 160], "stages": 1, "frozen_blocks": 6}
"""Training overrides that go with FAST_DATASET: windows of 160 x 160 cut from the frames at two thirds of their
scale (the 240 x 240 pixels of context a window at the frames' own scale sees, at 600 px: the camera's focal
length, so detection runs on camera images as they are), and the cheaper network that learns most per CPU-minute
(one belief/affinity stage, the trunk's first six blocks fixed). On 2 cores it makes about 3.5 steps of 16
windows a second; chosen on a validation set against windows at the frames' scale and at half of it
(docs/experiments.md)."""


@dataclass
class PipelineConfig:
    """One run of the pipeline. The stage nodes' own parameters are the defaults of everything not set here."""

    views: int = 36
    """Stops of the object sweep (the views the reconstruction uses)."""
    placements: int = 1
    """Sweeps of the object: 2 turns it over after the first (the capture waits for that, stage `turn_over`, and
    continues on capture_node's `capture/continue`) and sweeps it again, so the model is closed, its underside
    reconstructed too (1 or 2)."""
    test_views: int = 12
    """Stops of the test sweep, half a step off the object sweep's (the board-posed test set; 0: none)."""
    require_empty_plate: bool = True
    """Refuse the object sweep until the empty-plate sweep is recorded: without that reference the masks
    segment the object far worse (benchmarks/masks.py measures both)."""
    method: Literal["fast", "neus"] = "fast"
    """Reconstruction method."""
    frames: int = 3000
    """Frames of the training dataset (rendered by the fast path, `dataset` below; `dataset.photoreal_frames` of
    them by Cycles)."""
    test_frames: int = 40
    """Frames of the held-out synthetic test set (rendered with seed + 1; 0: none)."""
    seed: int = 0
    """Seed of the training dataset."""
    preset: Literal["lite", "vgg", "tiny"] = "lite"
    """DOPE training preset (lite: CPU, vgg: DOPE as published, GPU; tiny: tests)."""
    train_minutes: float = 13.0
    """Minutes of training (the learning rate anneals over them; the preset's epochs do not stop it, an epochs
    value in `train` does); 0: the preset's epochs."""
    precisions: list[str] = field(default_factory=lambda: ["fp32", "int8"])
    """ONNX models to evaluate (int8 only where the training exported one)."""
    evaluate_refined: bool = True
    """Score each precision's poses refined against the images too (what dope_node publishes with its default
    `refine`), under `<precision> refined`; the network's own poses are scored either way."""
    capture: dict = field(default_factory=dict)
    """Overrides of capture_node's config for both sweeps (a mapping, like a Capture goal's config_yaml)."""
    reconstruct: dict = field(default_factory=dict)
    """Overrides of reconstruct_node's config."""
    dataset: dict = field(default_factory=lambda: json.loads(json.dumps(FAST_DATASET)))
    """Overrides of dataset_node's config for the training dataset (default: `FAST_DATASET`)."""
    test_dataset: dict = field(default_factory=dict)
    """Overrides of dataset_node's config for the held-out synthetic test set."""
    train: dict = field(default_factory=lambda: dict(FAST_TRAIN))
    """Overrides of the training preset (default: `FAST_TRAIN`)."""

    def __post_init__(self):
        if self.views < 1 or self.test_views < 0:
            raise ValueError("views must be >= 1 and test_views >= 0")
        if self.placements not in (1, 2):
            raise ValueError(f"placements is 1 or 2, got {self.placements}")
        if self.frames < 1 or self.test_frames < 0:
            raise ValueError("frames must be >= 1 and test_frames >= 0")
        if self.train_minutes < 0:
            raise ValueError("train_minutes must be >= 0")
        unknown = set(self.precisions) - {"fp32", "int8"}
        if unknown or not self.precisions:
            raise ValueError(f"precisions are fp32 and/or int8, got {self.precisions}")

    def stages(self) -> list[str]:
        """The stages this config runs (the test stages only when they have views / frames)."""
        skip = {"test_capture"} if self.test_views == 0 else set()
        skip |= {"test_dataset"} if self.test_frames == 0 else set()
        return [s for s in (PLACED_STAGES if self.placements > 1 else STAGES) if s not in skip]

    def capture_overrides(self, test: bool) -> dict:
        """Capture config of the object sweep, or of the test sweep half a step off it."""
        sweep = {"views": self.test_views if test else self.views}
        if test:
            sweep["start_angle_rad"] = math.pi / self.views
        # the test sweep is of the object as it first stood (the model's frame): one placement
        placements = {"placements": 1 if test else self.placements} if self.placements > 1 else {}
        return {**self.capture, **placements, "sweep": {**self.capture.get("sweep", {}), **sweep}}

    def train_overrides(self) -> dict:
        if not self.train_minutes:
            return dict(self.train)
        return {"epochs": TIMED_EPOCHS, **self.train, "max_minutes": self.train_minutes}


class StageRunner(Protocol):
    """Runs one stage's job into its output directory, resuming unfinished work there; returns its summary.

    Each method reports the stage's own progress (0..1) to `progress` and stops with Cancelled when `cancel`
    is set. Failures raise N2DError with the stage's message.
    """

    def capture(self, session_dir: Path, overrides: dict, *, empty_plate: bool, progress: ProgressFn,
                cancel: threading.Event) -> dict: ...

    def reconstruct(self, session_dir: Path, model_dir: Path, overrides: dict, *, progress: ProgressFn,
                    cancel: threading.Event) -> dict: ...

    def dataset(self, model_dir: Path, dataset_dir: Path, frames: int, seed: int, overrides: dict, *,
                progress: ProgressFn, cancel: threading.Event) -> dict: ...

    def train(self, dataset_dir: Path, dope_dir: Path, object_name: str, preset: str, overrides: dict, *,
              progress: ProgressFn, cancel: threading.Event) -> dict: ...

    def evaluate(self, dope_dir: Path, tests: dict, precisions: list[str], refined: bool, *, progress: ProgressFn,
                 cancel: threading.Event) -> dict: ...


@dataclass
class RunLayout:
    """Where a run keeps what."""

    root: Path

    def output(self, stage: str) -> Path:
        return self.root / OUTPUTS[stage]

    @property
    def status_file(self) -> Path:
        return self.root / "run.json"

    def done(self, stage: str, status: dict) -> bool:
        """Whether `stage` has finished (its output is complete; the evaluation is recorded in run.json)."""
        if stage == "evaluate":
            return "evaluate" in status.get("stages", {})
        if stage == EMPTY_PLATE:
            return self.done("capture", status) or (self.root / "capture.partial" / "empty.json").is_file()
        manifest = read_manifest(self.output(stage)) if self.output(stage).is_dir() else None
        return bool(manifest and manifest.get("complete"))


_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")


def run_config(object_name: str, cfg: PipelineConfig) -> dict:
    """What a run's manifest records, and what a later call must repeat to continue it."""
    return {"object_name": object_name, **to_dict(cfg)}


def check_object_name(name: str) -> str:
    """An object name usable in topics and file names, or ConfigError."""
    if not _NAME.match(name or ""):
        raise ConfigError(f"object name {name!r} is not usable",
                          "use letters, digits, '_' and '-' (up to 64), starting with a letter or digit")
    return name


def check_run_dir(root: Path, object_name: str, cfg: PipelineConfig, overwrite: bool = False) -> dict | None:
    """Check that `root` is free, or a run of the same object and config (any run with `overwrite`); returns
    its manifest (None when there is none yet). ContractError otherwise: a file, a foreign directory, another
    kind of n2d directory, a run of another object or config."""
    check_object_name(object_name)
    if not root.exists():
        return None
    manifest = read_manifest(root) if root.is_dir() else None
    if manifest is None and (not root.is_dir() or any(root.iterdir())):
        raise ContractError(f"{root} exists and is not an n2d run directory", "choose another run directory")
    if manifest is not None and manifest["kind"] != "run":
        raise ContractError(f"{root} holds a {manifest['kind'].replace('_', ' ')}", "choose another run directory")
    if manifest is not None and not overwrite and manifest.get("config") != run_config(object_name, cfg):
        raise ContractError(f"{root} holds a run of another object or config",
                            "use the same object and config to resume it, another run directory, or overwrite")
    return manifest


def read_status(layout: RunLayout, object_name: str, fresh: bool) -> dict:
    """The run's run.json, or an empty status for a new run (or one about to be overwritten)."""
    if layout.status_file.is_file() and not fresh:
        return json.loads(layout.status_file.read_text())
    return {"object_name": object_name, "stages": {}}


def stage_order(requested: list[str] | None, cfg: PipelineConfig) -> list[str]:
    """The stages to run, in pipeline order; ConfigError for unknown names."""
    if not requested:
        return cfg.stages()
    known = (EMPTY_PLATE, *(PLACED_STAGES if cfg.placements > 1 else STAGES))
    unknown = [s for s in requested if s not in known]
    if unknown:
        raise ConfigError(f"unknown stage(s) {', '.join(unknown)}", f"stages are {', '.join(known)}")
    if EMPTY_PLATE in requested and "capture" in requested:
        raise ConfigError("empty_plate and capture cannot run in one call",
                          "the object must be placed on the plate in between: run empty_plate, place it, then the rest")
    return [s for s in known if s in requested]


def needs(stage: str, cfg: PipelineConfig) -> tuple[str, ...]:
    """The stages whose output `stage` reads under `cfg` (the evaluation: also the test sets `cfg` has)."""
    if stage == "evaluate":
        return NEEDS[stage] + tuple(s for s in ("test_dataset", "test_capture") if s in cfg.stages())
    return NEEDS.get(stage, ())


def check_stages(layout: RunLayout, cfg: PipelineConfig, order: list[str], status: dict,
                 given: tuple[str, ...] = ()) -> None:
    """ContractError when a stage of `order` that is to run reads an output that neither runs before it nor is
    finished (nor is among `given`, outputs that will be put in place before the run), or when the object sweep
    lacks its empty-plate sweep. A stage already finished, or given, does not run: its inputs are not needed."""
    for stage in order:
        if stage in given or layout.done(stage, status):
            continue
        missing = [need for need in needs(stage, cfg)
                   if need not in order and need not in given and not layout.done(need, status)]
        if missing:
            raise ContractError(f"stage {stage} needs the output of {', '.join(missing)}, which is not finished",
                                f"run {', '.join(missing)} first (or the whole pipeline)"
                                + ("; for no turntable test set, set test_views: 0" if "test_capture" in missing
                                   else ""))
    if ("capture" in order and cfg.require_empty_plate and not layout.done("capture", status)
            and not layout.done(EMPTY_PLATE, status)):
        raise ContractError("no empty-plate sweep is recorded for this run (the masks' background reference)",
                            "clear the plate and run the empty_plate stage first, or set require_empty_plate: false")


def run_pipeline(run_dir: str | Path, object_name: str, cfg: PipelineConfig, runner: StageRunner, *,
                 stages: list[str] | None = None, overwrite: bool = False, progress: ProgressFn = no_progress,
                 cancel: threading.Event | None = None) -> dict:
    """Run the pipeline (or the given `stages`) into `run_dir` and return its status (also run.json).

    Finished stages are skipped, the others resume. Progress reports carry the stage name and the stage's own
    progress line; `info` holds stage_index, stages_total and stage_progress. Raises Cancelled, N2DError.
    """
    cancel = cancel or threading.Event()
    layout = RunLayout(Path(run_dir).absolute())
    order = stage_order(stages, cfg)
    manifest = check_run_dir(layout.root, object_name, cfg, overwrite)
    status = read_status(layout, object_name, fresh=overwrite)
    # every check before anything is written: a refused call leaves the run directory as it was
    check_stages(layout, cfg, order, status)
    if manifest is not None and overwrite:
        shutil.rmtree(layout.root)
    layout.root.mkdir(parents=True, exist_ok=True)
    if read_manifest(layout.root) is None:
        write_manifest(layout.root, "run", config=run_config(object_name, cfg), complete=False)
    total = sum(WEIGHTS[s] for s in order)
    before = 0.0
    for index, stage in enumerate(order, 1):
        if cancel.is_set():
            raise Cancelled("the pipeline was cancelled", "run it again to continue")
        base = before / total

        def stage_progress(p: Progress, stage=stage, index=index, base=base) -> None:
            line = " ".join(x for x in (p.stage, p.message) if x)
            progress(Progress(base + WEIGHTS[stage] / total * min(max(p.fraction, 0.0), 1.0), stage, p.eta_s, line,
                              {"stage_index": index, "stages_total": len(order), "stage_progress": p.fraction}))

        if layout.done(stage, status):
            stage_progress(Progress(1.0, "done", 0.0, "finished earlier"))
        else:
            stage_progress(Progress(0.0, "starting"))
            t0 = time.monotonic()
            try:
                summary = _run_stage(stage, layout, object_name, cfg, runner, stage_progress, cancel)
            except Cancelled:
                raise
            except N2DError as exc:
                raise type(exc)(f"stage {stage}: {exc.message}", exc.hint) from None
            status["stages"][stage] = {"seconds": round(time.monotonic() - t0, 1), "summary": summary,
                                       **({"output": str(layout.output(stage))} if stage in OUTPUTS else {})}
            atomic_write_json(layout.status_file, status)
        before += WEIGHTS[stage]
    if all(layout.done(s, status) for s in cfg.stages()):
        write_manifest(layout.root, "run", config=run_config(object_name, cfg),
                       extra={"seconds": {s: v["seconds"] for s, v in status["stages"].items()},
                              "evaluation": status["stages"].get("evaluate", {}).get("summary", {})})
    return status


def _run_stage(stage: str, layout: RunLayout, object_name: str, cfg: PipelineConfig, runner: StageRunner,
               progress: ProgressFn, cancel: threading.Event) -> dict:
    out = layout.output
    if stage in (EMPTY_PLATE, "capture", "test_capture"):
        return runner.capture(out(stage), cfg.capture_overrides(test=stage == "test_capture"),
                              empty_plate=stage == EMPTY_PLATE, progress=progress, cancel=cancel)
    if stage == "reconstruct":
        return runner.reconstruct(out("capture"), out(stage),
                                  {**cfg.reconstruct, "method": cfg.method, "object_name": object_name},
                                  progress=progress, cancel=cancel)
    if stage in ("dataset", "test_dataset"):
        test = stage == "test_dataset"
        return runner.dataset(out("reconstruct"), out(stage), cfg.test_frames if test else cfg.frames,
                              cfg.seed + 1 if test else cfg.seed, cfg.test_dataset if test else cfg.dataset,
                              progress=progress, cancel=cancel)
    if stage == "train":
        return runner.train(out("dataset"), out(stage), object_name, cfg.preset, cfg.train_overrides(),
                            progress=progress, cancel=cancel)
    tests = {name: out(s) for name, s in (("synthetic", "test_dataset"), ("turntable", "test_capture"))
             if s in cfg.stages()}
    return runner.evaluate(out("train"), tests, cfg.precisions, cfg.evaluate_refined, progress=progress, cancel=cancel)


def evaluate_run(dope_dir: str | Path, tests: dict, precisions: list[str], refined: bool = False, *,
                 progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> dict:
    """The evaluate stage: the DOPE model on each test set (`synthetic`: a dataset, `turntable`: a board-posed
    capture session) in each precision it has, and with `refined` its poses refined against the images too
    (dope_node's default refinement, under `<precision> refined`); returns {test: {precision: headline numbers}}."""
    from n2d_dope.evaluate import evaluate, evaluate_session
    from n2d_dope.pose_refine import RefineConfig

    dope_dir = Path(dope_dir)
    jobs = [(name, path, precision, refine) for name, path in tests.items() for precision in precisions
            for refine in ([None, RefineConfig()] if refined else [None])
            if precision == "fp32" or (dope_dir / "model_int8.onnx").is_file()]
    results: dict = {}
    for i, (name, path, precision, refine) in enumerate(jobs):
        if cancel is not None and cancel.is_set():
            raise Cancelled("evaluation cancelled", "run it again to continue")
        key = precision if refine is None else f"{precision} refined"

        def sub(p: Progress, i=i, what=f"{name} {key}") -> None:
            progress(Progress((i + p.fraction) / len(jobs), what, -1.0, p.message))

        run = evaluate_session if name == "turntable" else evaluate
        r = run(dope_dir, path, name=name if refine is None else f"{name}_refined", precision=precision,
                refine=refine, progress=sub)
        results.setdefault(name, {})[key] = {
            k: r[k] for k in ("images", "instances", "detected", "adds_accuracy_10pct", "add_accuracy_10pct",
                              "adds_auc_10cm", "add_auc_10cm", "adds_median_mm", "add_median_mm", "diameter_mm")
            if k in r}
    progress(Progress(1.0, "done", 0.0))
    return results
