"""A fast render worker: one process rendering its share of a dataset's frames with the CPU rasterizer.

The counterpart of `render_worker.py` (Cycles) with the same per-frame records, writers and annotations, so
the two paths write datasets of one format: per frame a random scene (`raster_scene.py`), cameras sampled until
the target is visible enough (checked on the label pass, which costs one rasterization), the shaded image
(`shading.py`), then the annotations and the frame's files, its record last. A frame's randomness comes only
from (seed, frame), so any worker renders it the same way, and a resumed run writes identical frames.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import torch

from n2d_common.config import from_dict
from n2d_common.frames import inv_T
from n2d_common.images import auto_exposure, to_srgb8
from n2d_common.progress import ProgressFn
from n2d_dataset import writer
from n2d_dataset.annotate import annotate
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import load_models
from n2d_dataset.poses import candidate_camera, sample_camera
from n2d_dataset.raster_scene import Placed, RasterSceneBuilder
from n2d_dataset.shading import Geometry, MergedMeshes, RasterScene, shade, trace


def _choose_camera(cfg: DatasetConfig, rng: np.random.Generator, scene: RasterScene, merged: MergedMeshes,
                   focus: Placed, in_hand: bool) -> tuple[np.ndarray, Geometry]:
    """Sample camera poses until the focus target is visible enough; returns (T_world_cam, its labels)."""
    c = cfg.camera
    K = c.K()
    best: tuple[float, np.ndarray | None, Geometry | None] = (-1.0, None, None)
    for _ in range(c.max_tries):
        T_world_cam = candidate_camera(rng, c, focus.model, focus.T_world_obj(), in_hand)
        if T_world_cam is None:
            continue
        g = trace(scene, K, T_world_cam, c.width, c.height, merged)
        a = annotate(focus.model, focus.label, inv_T(T_world_cam) @ focus.T_world_obj(), K, g.index, g.depth)
        if a.info["visib_fract"] > best[0]:
            best = (a.info["visib_fract"], T_world_cam, g)
        if best[0] >= c.min_visible_fraction:
            break
    if best[1] is None:  # never in view: look straight at it
        T_world_cam = sample_camera(rng, focus.T_world_obj()[:3, 3], c.distance_m, c.elevation_deg, 0.0, 0.0)
        return T_world_cam, trace(scene, K, T_world_cam, c.width, c.height, merged)
    return best[1], best[2]


def finish_image(linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """8-bit sRGB of a linear render as a camera would give it: auto exposure as the Cycles path, the optics' blur
    (which also stands in for anti-aliasing) and sensor noise."""
    linear = cv2.GaussianBlur(linear, (0, 0), float(rng.uniform(0.45, 1.0)))
    rgb = to_srgb8(linear, auto_exposure(linear, rng.uniform(0.1, 0.3))).astype(np.float32)
    rgb += rng.normal(0.0, rng.uniform(0.0, 3.0), rgb.shape).astype(np.float32)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def _render_frame(cfg: DatasetConfig, builder: RasterSceneBuilder, root: Path, frame: int) -> None:
    """Compose, render, annotate and write one frame (its record last)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng([cfg.seed, frame])
    scene, placed, focus, in_hand = builder.build(rng)
    merged = MergedMeshes(scene.bodies)
    t1 = time.perf_counter()
    T_world_cam, g = _choose_camera(cfg, rng, scene, merged, focus, in_hand)
    t2 = time.perf_counter()
    rgb = finish_image(shade(scene, g, merged), rng)
    t3 = time.perf_counter()
    record = {"frame": frame, "in_hand": in_hand, "renderer": "raster",
              "seconds": {"compose": t1 - t0, "labels": t2 - t1, "render": t3 - t2}}
    writer.write_annotated_frame(root, cfg, frame, rgb, record, [(p.model, p.label, p.T_world_obj()) for p in placed],
                                 T_world_cam, g.index, g.depth)


@contextmanager
def frame_renderer(model_dirs: list[str], config: dict, threads: int) -> Iterator[tuple[Callable, str]]:
    """Set up a rasterizer with `threads` CPU threads; yields (render_one(root, frame), device name)."""
    cfg = from_dict(DatasetConfig, config)
    torch.set_num_threads(threads)
    builder = RasterSceneBuilder(load_models(model_dirs), cfg)
    yield (lambda root, frame: _render_frame(cfg, builder, Path(root), frame)), "cpu (raster)"


def render_frames(model_dirs: list[str], root: str, config: dict, frames: list[int], progress: ProgressFn,
                  cancel: threading.Event) -> dict:
    """Render `frames` of the dataset being written in `root` (the stage's partial directory)."""
    return writer.render_shard(frame_renderer, "raster", model_dirs, root, config, frames, progress, cancel)
