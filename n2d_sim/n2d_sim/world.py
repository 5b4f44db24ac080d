"""The simulated turntable world: its config and the ground-truth geometry, in plain numpy (no bpy).

A fixed camera looks at a turntable standing on a lab table. A ChArUco board lies centred on the
plate and the object stands on the board centre; plate, board and object turn together about the
turntable's Z axis. Frames (see design.md): `turntable` has its origin at the plate centre on the
board's surface, Z up along the rotation axis, X along the board's x axis at angle 0; the plate
frame is the turntable frame turned by the plate angle; the camera frame is OpenCV's.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np

from n2d_common.errors import ContractError
from n2d_common.formats.board import BoardSpec, T_plate_board
from n2d_common.frames import inv_T, make_T, project, rot_z
from n2d_sim.objects import SAMPLE_OBJECTS, sample_object_dir


@dataclass
class SimWorldConfig:
    """Everything the simulated camera renders: object, camera, turntable, board, clutter, light, noise."""

    object: str = "box"
    """A sample object name (box, bottle) or the path of a model directory (mesh.obj, models_info.json)."""
    placement_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """How the object lies on the plate: rotations about the model frame's X, then Y, then Z axes (fixed axes),
    degrees, about the model origin, before the object is lowered onto the board (its lowest vertex on the board,
    the origin over the plate centre; see `T_plate_obj`). (0, 0, 0): upright, as the model frame stands;
    (90, 0, 0): on its side, the old underside facing -Y. A capture session's second placement turns the object
    over with it, so that the first placement's underside is seen."""
    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    focal_px: float = 600.0
    """Focal length in pixels, fx = fy (square pixels: Blender 5.0.1 fails to write the multi-part EXR of a
    non-square pixel aspect). The principal point is the image centre, ((W-1)/2, (H-1)/2)."""
    camera_distance_m: float = 0.50
    """Distance from the camera centre to the point it looks at, metres."""
    camera_elevation_deg: float = 45.0
    """Elevation of the camera above the plate plane, seen from the point it looks at, degrees."""
    camera_azimuth_deg: float = -90.0
    """Azimuth of the camera about the turntable Z axis from +X, degrees (-90: camera on the -Y side). The
    room (lights, table, wall, distractors) turns with it, so the clutter always stands behind the plate."""
    camera_target_height_m: float = 0.03
    """Height above the plate centre of the point the camera looks at, metres."""
    board: BoardSpec = field(default_factory=BoardSpec)
    """The ChArUco board on the plate (its plate_diameter_m sets the plate)."""
    board_visible: bool = True
    """Lay the board on the plate; False: the object stands on the bare plate (captures without a board)."""
    plate_height_m: float = 0.045
    """Height of the board surface above the table top, metres (plate plus turntable base)."""
    samples: int = 4
    """Cycles samples per pixel of each new frame (the turntable and object; see render_worker)."""
    background_samples: int = 16
    """Cycles samples of the surroundings, rendered once at start and reused for every frame."""
    denoiser: Literal["none", "oidn"] = "oidn"
    """Denoiser: none, or OpenImageDenoise guided by albedo and normal passes."""
    device: Literal["auto", "cpu", "gpu"] = "auto"
    """Cycles device: auto uses a GPU (OptiX, CUDA, HIP, oneAPI, Metal) when one is present."""
    threads: int = 0
    """CPU render threads (0: all cores)."""
    max_bounces: int = 3
    """Light bounces (diffuse and glossy alike)."""
    exposure_ev: float = 0.0
    """Exposure correction, stops, applied to the linear image before the sRGB transfer curve."""
    key_light_w: float = 12.0
    """Power of the soft key light (an area light above, to the left in front), watts."""
    fill_light_w: float = 3.0
    """Power of the fill light (an area light on the right), watts."""
    ceiling_light_w: float = 6.0
    """Power of the large ceiling panel, watts."""
    world_strength: float = 0.15
    """Strength of the dim grey ambient light from the surroundings."""
    clutter: bool = True
    """Put a lab table, a back wall, a poster and distractor objects around the turntable."""
    clutter_seed: int = 0
    """Seed of the distractors' placement, shapes and colours."""
    read_noise_dn: float = 1.2
    """Gaussian read noise of the sensor, standard deviation in 8-bit digital numbers."""
    shot_noise: float = 0.1
    """Shot noise gain: at an 8-bit value v the noise is sqrt(read_noise_dn^2 + shot_noise * v) DN
    (3.4 DN at v = 100, 4.6 DN at v = 200 by default)."""
    cache_size: int = 16
    """Renders SimCamera keeps, keyed by plate angle."""

    def __post_init__(self):
        for name in ("width", "height", "samples", "background_samples", "cache_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("focal_px", "camera_distance_m", "plate_height_m"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 5.0 <= self.camera_elevation_deg <= 89.0:
            raise ValueError(f"camera_elevation_deg must be in [5, 89], got {self.camera_elevation_deg}")
        for name in ("threads", "max_bounces", "read_noise_dn", "shot_noise", "world_strength", "key_light_w",
                     "fill_light_w", "ceiling_light_w"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if len(self.placement_deg) != 3 or not np.all(np.isfinite(self.placement_deg)):
            raise ValueError(f"placement_deg must be three angles in degrees, got {self.placement_deg}")
        self.placement_deg = tuple(float(a) for a in self.placement_deg)
        if self.object not in SAMPLE_OBJECTS and not Path(self.object).is_dir():
            raise ValueError(f"object {self.object!r} is neither a sample object "
                             f"({', '.join(SAMPLE_OBJECTS)}) nor a model directory")
        uv = project(K(self), T_cam_turntable(self), plate_rim(self))
        if not ((uv >= 0).all() and (uv <= [self.width - 1, self.height - 1]).all()):
            raise ValueError("the camera does not see the whole plate: increase camera_distance_m or "
                             "lower focal_px")


def object_dir(cfg: SimWorldConfig) -> Path:
    """The model directory of the configured object."""
    return sample_object_dir(cfg.object) if cfg.object in SAMPLE_OBJECTS else Path(cfg.object)


@lru_cache(maxsize=32)
def _models_info(path: str) -> dict:
    try:
        info = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ContractError(f"cannot read {path}: {exc}", "is this an n2d model directory?") from None
    return next(iter(info.values())) if "diameter" not in info else info


@lru_cache(maxsize=32)
def _obj_vertices(path: str) -> np.ndarray:
    """The vertex positions of an OBJ file (N x 3, metres)."""
    try:
        rows = [line.split()[1:4] for line in Path(path).read_text().splitlines() if line.startswith("v ")]
    except OSError as exc:
        raise ContractError(f"cannot read {path}: {exc}", "is this an n2d model directory?") from None
    return np.array(rows, dtype=float).reshape(-1, 3)


def model_vertices(model_dir: str | Path) -> np.ndarray:
    """N x 3 vertices of a model directory's mesh.obj in its model frame, metres."""
    return _obj_vertices(str(Path(model_dir) / "mesh.obj"))


def object_vertices(cfg: SimWorldConfig) -> np.ndarray:
    """N x 3 vertices of the configured object's mesh in its model frame, metres."""
    return model_vertices(object_dir(cfg))


def placement_R(placement_deg) -> np.ndarray:
    """3x3 rotation of a placement: about X, then Y, then Z (fixed axes), degrees (`SimWorldConfig.placement_deg`)."""
    x, y, z = np.radians(np.asarray(placement_deg, dtype=float))
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def object_info(cfg: SimWorldConfig) -> dict:
    """The object's BOP models_info entry (millimetres: diameter, min_x.., size_x..)."""
    return _models_info(str(object_dir(cfg) / "models_info.json"))


def K(cfg: SimWorldConfig) -> np.ndarray:
    """3x3 intrinsics; principal point at the image centre in OpenCV's pixel-centre convention."""
    return np.array([[cfg.focal_px, 0.0, (cfg.width - 1) / 2],
                     [0.0, cfg.focal_px, (cfg.height - 1) / 2],
                     [0.0, 0.0, 1.0]])


def T_turntable_cam(cfg: SimWorldConfig) -> np.ndarray:
    """4x4 pose of the (OpenCV) camera in the turntable frame: looking at the target, image x horizontal."""
    el, az = math.radians(cfg.camera_elevation_deg), math.radians(cfg.camera_azimuth_deg)
    target = np.array([0.0, 0.0, cfg.camera_target_height_m])
    centre = target + cfg.camera_distance_m * np.array([math.cos(el) * math.cos(az),
                                                        math.cos(el) * math.sin(az), math.sin(el)])
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.stack([x, np.cross(z, x), z], axis=1), centre)


def T_cam_turntable(cfg: SimWorldConfig) -> np.ndarray:
    """4x4 transform from the turntable frame into the camera frame."""
    return inv_T(T_turntable_cam(cfg))


def T_turntable_plate(angle_rad: float) -> np.ndarray:
    """4x4 pose of the plate (which carries the board and the object) at plate angle `angle_rad`."""
    return rot_z(angle_rad)


def T_plate_obj(cfg: SimWorldConfig) -> np.ndarray:
    """4x4 pose of the object on the plate: turned by `placement_deg` about the model origin, the origin over the
    plate centre, the lowest vertex on the board (upright: the models_info min_z)."""
    if not any(cfg.placement_deg):
        return make_T(np.eye(3), [0.0, 0.0, -object_info(cfg)["min_z"] / 1000])
    R = placement_R(cfg.placement_deg)
    return make_T(R, [0.0, 0.0, -float((object_vertices(cfg) @ R[2]).min())])


def T_turntable_obj(cfg: SimWorldConfig, angle_rad: float) -> np.ndarray:
    """4x4 pose of the object in the turntable frame at plate angle `angle_rad`."""
    return T_turntable_plate(angle_rad) @ T_plate_obj(cfg)


def T_cam_obj(cfg: SimWorldConfig, angle_rad: float) -> np.ndarray:
    """4x4 transform from the object frame into the camera frame at plate angle `angle_rad`."""
    return T_cam_turntable(cfg) @ T_turntable_obj(cfg, angle_rad)


def T_cam_board(cfg: SimWorldConfig, angle_rad: float) -> np.ndarray:
    """4x4 transform from the (OpenCV) board frame into the camera frame at plate angle `angle_rad`."""
    return T_cam_turntable(cfg) @ T_turntable_plate(angle_rad) @ T_plate_board(cfg.board)


def plate_rim(cfg: SimWorldConfig, n: int = 72) -> np.ndarray:
    """n x 3 points on the rim of the plate's top surface, turntable frame."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = cfg.board.plate_diameter_m / 2
    return np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)
