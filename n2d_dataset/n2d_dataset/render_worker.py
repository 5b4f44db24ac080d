"""A render worker: one bpy process rendering its share of a dataset's frames into the dataset directory.

`render_frames` runs in its own process (through `n2d_common.worker.run_in_worker`): it loads the models
into Blender once, then per frame builds a random scene, samples a camera until the target is visible
enough (checked on the label render), renders the image, annotates and writes the frame. A frame's
randomness comes only from (seed, frame), so any worker renders it the same way.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import bpy
import numpy as np

from n2d_blender import renderer
from n2d_blender.camera import set_pose
from n2d_common.config import from_dict
from n2d_common.frames import inv_T
from n2d_common.images import auto_exposure, to_srgb8
from n2d_common.progress import ProgressFn
from n2d_dataset import writer
from n2d_dataset.annotate import annotate
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import load_models
from n2d_dataset.poses import candidate_camera, sample_camera
from n2d_dataset.scene import Instance, SceneBuilder


def _choose_camera(cfg: DatasetConfig, rng: np.random.Generator, cam: bpy.types.Object, focus: Instance,
                   in_hand: bool) -> tuple:
    """Sample camera poses until the focus target is visible enough; returns (T_world_cam, labels or None)."""
    c = cfg.camera
    best = (-1.0, None, None)
    for _ in range(c.max_tries):
        T_world_cam = candidate_camera(rng, c, focus.model, focus.T_world_obj(), in_hand)
        if T_world_cam is None:
            continue
        set_pose(cam, T_world_cam)
        if not cfg.annotate:
            return T_world_cam, None
        with renderer.LabelRender():
            labels = renderer.render()
        a = annotate(focus.model, focus.index, inv_T(T_world_cam) @ focus.T_world_obj(), c.K(), labels["index"],
                     labels["depth"])
        if a.info["visib_fract"] > best[0]:
            best = (a.info["visib_fract"], T_world_cam, labels)
        if best[0] >= c.min_visible_fraction:
            break
    if best[1] is None:  # never in view: fall back to looking straight at it
        T_world_cam = sample_camera(rng, focus.T_world_obj()[:3, 3], c.distance_m, c.elevation_deg, 0.0, 0.0)
        set_pose(cam, T_world_cam)
        return T_world_cam, None
    set_pose(cam, best[1])
    return best[1], best[2]


def _render_frame(cfg: DatasetConfig, builder: SceneBuilder, root: Path, frame: int) -> None:
    """Build, render, annotate and write one frame (its record last)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([cfg.seed, frame])
    instances, focus, in_hand = builder.build(rng)
    bpy.context.scene.cycles.seed = int(rng.integers(2 ** 31))
    t1 = time.perf_counter()
    T_world_cam, labels = _choose_camera(cfg, rng, builder.camera, focus, in_hand)
    if cfg.annotate and labels is None:
        with renderer.LabelRender():
            labels = renderer.render()
    t2 = time.perf_counter()
    linear = renderer.render()["linear"]
    rgb = to_srgb8(linear, auto_exposure(linear, rng.uniform(0.1, 0.3)))
    t3 = time.perf_counter()
    record = {"frame": frame, "in_hand": in_hand, "renderer": "cycles",
              "seconds": {"compose": t1 - t0, "labels": t2 - t1, "render": t3 - t2}}
    index, depth = (labels["index"], labels["depth"]) if cfg.annotate else (None, None)
    targets = [(i.model, i.index, i.T_world_obj()) for i in instances]
    writer.write_annotated_frame(root, cfg, frame, rgb, record, targets, T_world_cam, index, depth)


@contextmanager
def frame_renderer(model_dirs: list[str], config: dict, threads: int) -> Iterator[tuple[Callable, str]]:
    """Load the models into Blender and set up Cycles with `threads` CPU threads; yields (render_one(root, frame),
    the device Cycles renders on)."""
    cfg = from_dict(DatasetConfig, config)
    builder = SceneBuilder(load_models(model_dirs), cfg)
    shm = "/dev/shm" if Path("/dev/shm").is_dir() else None  # the EXRs never need to touch a disk
    with tempfile.TemporaryDirectory(prefix="n2d_dataset_", dir=shm) as tmp:
        r = cfg.render
        device = renderer.setup(Path(tmp) / "frame.exr", r.samples, r.denoiser, r.max_bounces, r.device, threads)
        yield (lambda root, frame: _render_frame(cfg, builder, Path(root), frame)), device


def render_frames(model_dirs: list[str], root: str, config: dict, frames: list[int], progress: ProgressFn,
                  cancel: threading.Event) -> dict:
    """Render `frames` of the dataset being written in `root` (the stage's partial directory)."""
    return writer.render_shard(frame_renderer, "cycles", model_dirs, root, config, frames, progress, cancel)
