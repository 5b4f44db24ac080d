"""Validation sequences for tracking: a video of one scene of the fast renderer, with the truth of every frame.

- `tabletop`: one instance of the object among distractors on a table (the dataset's scene sampling, without
  hands), the camera circling it at `speed_deg_s` at a slowly bobbing height, so distractors pass in front of it;
- `in_hand`: the object held by the gripper proxy in front of a still camera, turning at `speed_deg_s` about an
  axis that itself swings, so that every side, the underside included, comes into view; the fingers occlude it.

Frames are rendered on demand (`Sequence.frame(i)`: the image, the object's true pose in the camera and its
visible fraction), from (seed, scene): the same config always gives the same video. Metres, OpenCV camera.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from n2d_common.frames import inv_T, make_T
from n2d_dataset.annotate import annotate
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import load_models
from n2d_dataset.poses import look_at
from n2d_dataset.raster_scene import RasterSceneBuilder
from n2d_dataset.raster_worker import finish_image
from n2d_dataset.shading import MergedMeshes, shade, trace


@dataclass
class SequenceConfig:
    """A validation sequence."""

    scene: Literal["tabletop", "in_hand"] = "tabletop"
    frames: int = 90
    fps: float = 30.0
    speed_deg_s: float = 30.0
    """Tabletop: the camera's angular speed about the object; in hand: the object's turning speed."""
    distance_m: float = 0.5
    """Camera to object."""
    elevation_deg: float = 35.0
    """Tabletop: the camera's mean elevation above the table."""
    width: int = 640
    height: int = 480
    focal_px: float = 600.0
    seed: int = 0

    def __post_init__(self):
        if self.frames < 1 or self.fps <= 0 or self.distance_m <= 0:
            raise ValueError("frames must be >= 1, fps and distance_m > 0")
        if self.scene not in ("tabletop", "in_hand"):
            raise ValueError(f"scene must be tabletop or in_hand, got {self.scene!r}")

    def K(self) -> np.ndarray:
        return np.array([[self.focal_px, 0.0, (self.width - 1) / 2], [0.0, self.focal_px, (self.height - 1) / 2],
                         [0.0, 0.0, 1.0]])


@dataclass
class Frame:
    """One frame of a sequence."""

    rgb: np.ndarray
    """H x W x 3 uint8."""
    stamp: float
    """Seconds from the first frame."""
    T_cam_obj: np.ndarray
    """4 x 4 true pose of the object: object frame -> camera, metres."""
    visible: float
    """Visible fraction of the object (BOP's visib_fract)."""


class Sequence:
    """A rendered validation sequence of one model."""

    def __init__(self, model_dir: str | Path, cfg: SequenceConfig | None = None):
        self.cfg = cfg or SequenceConfig()
        c = self.cfg
        in_hand = c.scene == "in_hand"
        dataset = DatasetConfig(seed=c.seed)
        dataset.scene = replace(dataset.scene, instances_per_model=(1, 1), in_hand=1.0 if in_hand else 0.0,
                                boards=0.0, distractors=(4, 8))
        self.model = load_models([model_dir])[0]
        builder = RasterSceneBuilder([self.model], dataset)
        rng = np.random.default_rng([c.seed, 1 if in_hand else 0])
        self.scene, placed, self.focus, _ = builder.build(rng)
        self.K = c.K()
        self._rng_seed = c.seed
        centre = self.focus.T_world_obj()[:3, 3].copy()
        self._centre = centre
        self._start = rng.uniform(0, 2 * np.pi)
        if in_hand:  # the object and the gripper turn together about the object's centre; the camera stays
            self._moving = [self.focus.body] + self.scene.bodies[-4:]  # the gripper's parts come last
            self._rest = {id(b): b.T_world.copy() for b in self._moving}
            side = np.array([np.cos(self._start), np.sin(self._start), 0.0])
            self._T_world_cam = look_at(centre + c.distance_m * side, centre)
        self.frames = c.frames

    def __len__(self) -> int:
        return self.cfg.frames

    def camera(self, t: float) -> np.ndarray:
        """T_world_cam at time t."""
        c = self.cfg
        if c.scene == "in_hand":
            return self._T_world_cam
        az = self._start + np.radians(c.speed_deg_s) * t
        el = np.radians(c.elevation_deg + 10.0 * np.sin(2 * np.pi * t / 6.0))
        eye = self._centre + c.distance_m * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return look_at(eye, self._centre)

    def _hand_motion(self, t: float) -> np.ndarray:
        """World motion of the held object at time t: a turn about its centre, its axis swinging slowly."""
        c = self.cfg
        swing = 0.5 * np.pi * np.sin(2 * np.pi * t / 8.0)
        axis = np.array([np.cos(swing), 0.0, np.sin(swing)])
        R = cv2.Rodrigues(axis * np.radians(c.speed_deg_s) * t)[0]
        return make_T(np.eye(3), self._centre) @ make_T(R, np.zeros(3)) @ make_T(np.eye(3), -self._centre)

    def frame(self, i: int) -> Frame:
        """Render frame i (0-based)."""
        t = i / self.cfg.fps
        if self.cfg.scene == "in_hand":
            M = self._hand_motion(t)
            for b in self._moving:
                b.T_world = M @ self._rest[id(b)]
        T_world_cam = self.camera(t)
        merged = MergedMeshes(self.scene.bodies)
        c = self.cfg
        g = trace(self.scene, self.K, T_world_cam, c.width, c.height, merged)
        # one camera for the whole video: the same blur, exposure key and noise draw in every frame
        rgb = finish_image(shade(self.scene, g, merged), np.random.default_rng([self._rng_seed, 7]))
        T_cam_obj = inv_T(T_world_cam) @ self.focus.T_world_obj()
        visible = annotate(self.focus.model, self.focus.label, T_cam_obj, self.K, g.index, g.depth).info["visib_fract"]
        return Frame(rgb, t, T_cam_obj, float(visible))
