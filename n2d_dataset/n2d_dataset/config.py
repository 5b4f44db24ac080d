"""The dataset config: what a scene holds, how the camera and lights are sampled, how frames are rendered.

Plain dataclasses (no bpy), read by the CLI, the ROS node and the render workers alike. Every random
choice of a frame is drawn from a generator seeded by (seed, frame index), so a frame looks the same
whichever worker renders it and however often a run was interrupted.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Literal

import numpy as np


@dataclass
class CameraConfig:
    """The pinhole camera (fixed per dataset) and how its pose is sampled around the targets."""

    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    focal_px: float = 600.0
    """Focal length, pixels (fx = fy); the principal point is the image centre ((W-1)/2, (H-1)/2)."""
    distance_m: tuple[float, float] = (0.35, 0.9)
    """Range of the distance from the camera to the point it looks at, metres."""
    elevation_deg: tuple[float, float] = (15.0, 80.0)
    """Range of the camera's elevation above the floor seen from that point, degrees."""
    look_at_jitter_m: float = 0.05
    """The point looked at is a target's centre moved by up to this in each axis, metres."""
    roll_deg: float = 20.0
    """In-plane roll of the camera, uniform in +-this, degrees."""
    min_visible_fraction: float = 0.3
    """Each sampled view must show the chosen target with at least this visible fraction of its silhouette."""
    max_tries: int = 20
    """Camera poses tried per frame before the frame settles for the best one."""

    def __post_init__(self):
        if self.width < 16 or self.height < 16:
            raise ValueError("camera width and height must be >= 16 pixels")
        if self.focal_px <= 0:
            raise ValueError("camera.focal_px must be > 0")
        for name in ("distance_m", "elevation_deg"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"camera.{name} must be a range [lo, hi] with 0 <= lo <= hi")
        if not 0 <= self.min_visible_fraction <= 1:
            raise ValueError("camera.min_visible_fraction must be in [0, 1]")

    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix, OpenCV pixel-centre convention."""
        return np.array([[self.focal_px, 0.0, (self.width - 1) / 2],
                         [0.0, self.focal_px, (self.height - 1) / 2],
                         [0.0, 0.0, 1.0]])


@dataclass
class SceneConfig:
    """What a frame's scene holds and how it is laid out."""

    instances_per_model: tuple[int, int] = (1, 2)
    """Range of the number of copies of each model in a scene."""
    distractors: tuple[int, int] = (3, 8)
    """Range of the number of distractors (procedural primitives with random materials)."""
    distractor_size_m: tuple[float, float] = (0.03, 0.15)
    """Range of a distractor's largest dimension, metres."""
    spread_m: float = 0.25
    """Objects are dropped over a square of this half size around the origin, metres."""
    walls: float = 0.5
    """Probability of walls behind the floor (a room corner) instead of an open horizon."""
    boards: float = 0.3
    """Probability that a frame has a printed fiducial sheet (a ChArUco board or an ArUco marker grid, as
    labs calibrate and capture on) lying flat under one of the targets: without it the network mistakes
    a board's black squares and markers for the object's corners."""
    in_hand: float = 0.0
    """Probability that a frame shows one target held by a gripper proxy in the air (the paper validates
    in-hand) instead of resting on the floor."""
    lights: tuple[int, int] = (1, 4)
    """Range of the number of lights (point, spot, area, sun; colour temperatures 2700-7500 K)."""
    light_power_w: tuple[float, float] = (20.0, 300.0)
    """Range of a point/spot/area light's power, watts (suns get a strength derived from it)."""
    world_strength: tuple[float, float] = (0.1, 1.0)
    """Range of the strength of the gradient sky that lights the scene from all around."""
    physics: bool = True
    """Cycles path: drop the objects with rigid-body physics so they rest naturally (else they float where placed).
    The fast path has no physics: it places models in their resting poses, or floating when turned at random."""
    upright: float = 0.35
    """Probability that a model stands as it was captured (its Z up, as it stood on the turntable: a stable pose
    the capture saw), about a random yaw."""
    resting: float = 0.35
    """Probability that a model lies in one of its other resting poses (the stable faces of its convex hull, drawn
    by how likely a drop ends in each). The rest get a uniformly random rotation."""

    def __post_init__(self):
        for name in ("instances_per_model", "distractors", "lights"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"scene.{name} must be a range [lo, hi] with 0 <= lo <= hi")
        if self.instances_per_model[1] < 1:
            raise ValueError("scene.instances_per_model must allow at least one copy")
        if self.upright + self.resting > 1 + 1e-9:
            raise ValueError(f"scene.upright + scene.resting is a probability, at most 1 (got {self.upright} + "
                             f"{self.resting})")
        for name in ("walls", "boards", "in_hand", "upright", "resting"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"scene.{name} is a probability, in [0, 1]")


@dataclass
class RenderConfig:
    """How frames are rendered: the photoreal Cycles path or the fast rasterizer, and their settings."""

    engine: Literal["cycles", "raster"] = "cycles"
    """cycles: Blender's path tracer (photoreal: soft light, bounces, glossy reflections); raster: n2d's CPU
    rasterizer with per-pixel shading and shadow maps (no bpy), an order of magnitude faster per annotated frame,
    for the bulk of a training set. Both write the same exact labels."""
    samples: int = 16
    """Cycles samples per pixel of the RGB image (cycles only)."""
    denoiser: Literal["none", "oidn"] = "oidn"
    """Denoiser: none, or OpenImageDenoise guided by albedo and normal passes."""
    max_bounces: int = 3
    """Light bounces (diffuse and glossy alike)."""
    device: Literal["auto", "cpu", "gpu"] = "auto"
    """Cycles device: auto uses a GPU (OptiX, CUDA, HIP, oneAPI, Metal) when one is present."""
    threads: int = 0
    """CPU render threads per worker (0: the cores divided among the workers)."""
    rgb_format: Literal["jpg", "png"] = "jpg"
    """Image format of rgb/ (BOP's train_pbr uses JPEG)."""
    jpeg_quality: int = 95
    """JPEG quality of rgb/ images."""

    def __post_init__(self):
        if self.samples < 1:
            raise ValueError("render.samples must be >= 1")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError("render.jpeg_quality must be in [1, 100]")


@dataclass
class DatasetConfig:
    """Models to an annotated, domain-randomised dataset (BOP train_pbr layout + DOPE JSON)."""

    frames: int = 100
    """Number of frames to render."""
    seed: int = 0
    """Seed of every random choice (frame i uses (seed, i): reproducible whatever the worker count)."""
    workers: int = 0
    """Render worker processes. 0: automatic, what is fastest on a CPU: for Cycles one worker (one bpy) using all
    cores, for the rasterizer one single-threaded worker per core."""
    chunk_size: int = 1000
    """Frames per BOP chunk directory (train_pbr/000000, 000001, ...)."""
    photoreal_frames: int = 0
    """With `render.engine=raster`: this many of the frames (the first ones) are rendered with Cycles instead, the
    photoreal part of a mixed training set (DOPE's best results came from domain randomisation mixed with
    photoreal frames); training draws from the two parts by `photoreal_mix` (TrainConfig)."""
    annotate: bool = True
    """Write annotations (masks, depth, poses). False renders bare RGB (only to measure the overhead)."""
    camera: CameraConfig = field(default_factory=CameraConfig)
    """Camera intrinsics and pose sampling."""
    scene: SceneConfig = field(default_factory=SceneConfig)
    """Scene composition."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """Rendering."""

    def worker_count(self, engine: str | None = None) -> int:
        """The number of render worker processes this config runs for `engine` (default: the configured one):
        `workers`, or the automatic choice."""
        if self.workers:
            return self.workers
        return max(1, len(os.sched_getaffinity(0))) if (engine or self.render.engine) == "raster" else 1

    def photoreal(self) -> range:
        """The frames rendered with Cycles."""
        return range(self.frames if self.render.engine == "cycles" else self.photoreal_frames)

    def __post_init__(self):
        if self.frames < 1:
            raise ValueError("frames must be >= 1")
        if self.workers < 0:
            raise ValueError("workers must be >= 0 (0: automatic)")
        if not 0 <= self.photoreal_frames <= self.frames:
            raise ValueError(f"photoreal_frames must be in 0..frames ({self.frames}), got {self.photoreal_frames}")
        if self.photoreal_frames and self.render.engine == "cycles":
            raise ValueError("photoreal_frames is for render.engine=raster (with cycles every frame is photoreal)")
        if self.chunk_size < 1:
            raise ValueError("chunk_size must be >= 1")
