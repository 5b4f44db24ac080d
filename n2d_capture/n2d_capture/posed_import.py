"""Import of posed photos: a nerfstudio `transforms.json` or a COLMAP sparse model into a capture session.

`import_posed()` reads the views, their intrinsics and their poses in the source's own world frame (any
position, orientation and scale), finds the session's metric turntable frame and writes an ordinary capture
session (`images/`, `masks/`, `transforms.json`, `capture.json` with an `import` section, the contact sheet).

Sources:
- nerfstudio: `DIR/transforms.json` with nerfstudio's fields (`camera_model` OPENCV, PINHOLE or
  SIMPLE_PINHOLE; `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, `k1`, `k2`, `k3`, `p1`, `p2`, each also allowed per
  frame; `frames[].file_path`, `frames[].transform_matrix` camera-to-world with OpenGL camera axes, optional
  `frames[].mask_path`; optional `ply_file_path`, the sparse points). Paths are relative to DIR. The
  intrinsics must be the same in every frame.
- colmap: a sparse model (`cameras`, `images`, `points3D` as `.bin` or `.txt`) in `DIR/sparse/0`,
  `DIR/sparse` or DIR itself, the images in `DIR/images` (or DIR) under their COLMAP names, optional masks
  in `DIR/masks` as COLMAP names them (`NAME.png`, or the image's stem with `.png`). One camera of model
  SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV; poses are world-to-camera, OpenCV axes.

The turntable frame (see docs/formats.md):
- Metric scale: from the ChArUco board where it shows in 3 or more views (the similarity that carries the
  imported camera centres onto the centres seen from the board; its RMS disagreement is checked), or from
  `scale_from`, a known distance between two camera centres (`cam:IMG_A,IMG_B=0.35`, metres). Without
  either the import is refused: a session must be metric.
- Z: the axis of the camera ring, the normal of the plane the camera centres lie in through the centre
  of the circle fitted to them (a turntable's rotation axis), pointing to the board's printed side, or
  without a board to the side the cameras look down from.
- Origin: where that axis meets the plate: the board's top plane, or without a board the plane under the
  lowest sparse points near the axis (COLMAP's points3D or nerfstudio's `ply_file_path`: the plate top or
  the object's foot).
- Cameras that are no ring (a hand-held walk at several heights): Z is the board's normal, or without a board
  the normal of the sparse points' dominant plane (the table), and the axis stands at the centre of the circle
  fitted to the camera centres seen along it.
- X: the board's x axis (without a board: towards the first camera), level.

Masks: the source's masks where it has them (nerfstudio `mask_path`, COLMAP `masks/`, or an image's alpha
channel), else made as a capture without an empty-plate sweep makes them (from the board on the plate).
Nothing is left behind when the import fails.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from n2d_capture.board import BoardPose, CalibrationError, board_pose, detect_board
from n2d_capture.calibration import Intrinsics
from n2d_capture.capture import CaptureConfig, overlay_view
from n2d_capture.importer import import_output, read_photo
from n2d_capture.masks import ViewGeometry, foreground_mask_no_reference, write_mask
from n2d_capture.sfm import similarity
from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json
from n2d_common.errors import ConfigError, ContractError
from n2d_common.formats.session import OPENGL_FROM_OPENCV, PIXEL_EDGE, transforms_json
from n2d_common.frames import inv_T, make_T
from n2d_common.images import contact_sheet, write_png
from n2d_common.progress import Progress, ProgressFn, no_progress

SOURCES = ("nerfstudio", "colmap")
"""Formats `import_posed` reads."""
THUMB_WIDTH = 240
"""Width of a view on the contact sheet, pixels."""
_NERFSTUDIO_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2")
_SCALE_FROM = re.compile(r"^cam:([^,=]+),([^,=]+)=([^=]+)$")
_SCALE_HINT = ("let the ChArUco board show in 3+ views, or give a known distance between two camera centres: "
               "--scale-from cam:IMG_A,IMG_B=0.35 (metres)")


@dataclass
class PosedImportConfig:
    """How posed photos are placed in the turntable frame."""

    capture: CaptureConfig = field(default_factory=CaptureConfig)
    """The board spec, board pose thresholds and mask settings, as a capture uses them."""
    scale_from: str = ""
    """Known distance between two camera centres, `cam:IMG_A,IMG_B=METRES` (image names as the source gives
    them, or their file names); empty: the scale from the board."""
    min_board_views: int = 3
    """Views with a good board pose the board scale needs at least."""
    max_alignment_mm: float = 5.0
    """Largest RMS distance between the imported camera centres, scaled and moved onto the board's, and
    the camera centres seen from the board, mm."""
    max_ring_residual: float = 0.05
    """Camera centres further (RMS) from the circle fitted to them than this share of its radius are no ring
    (a hand-held walk at several heights): Z then is the board's normal, or the normal of the sparse points'
    dominant plane (the table)."""
    plane_tolerance_m: float = 0.003
    """Sparse points within this distance of a plane count as on it (the table plane without a ring), metres."""
    plate_radius_fraction: float = 0.5
    """Without a board: sparse points within this share of the camera ring's radius of the axis are searched
    for the plate's height."""
    plate_percentile: float = 2.0
    """Without a board: the plate lies at this percentile of those points' heights (robust to stray points)."""

    def __post_init__(self):
        if self.min_board_views < 3:
            raise ValueError("min_board_views must be >= 3")
        if self.max_alignment_mm <= 0:
            raise ValueError("max_alignment_mm must be > 0")
        if self.max_ring_residual <= 0 or self.plane_tolerance_m <= 0:
            raise ValueError("max_ring_residual and plane_tolerance_m must be > 0")
        if not 0 < self.plate_radius_fraction <= 1:
            raise ValueError("plate_radius_fraction must be in (0, 1]")
        if not 0 <= self.plate_percentile < 50:
            raise ValueError("plate_percentile must be in [0, 50)")
        if self.scale_from:
            parse_scale_from(self.scale_from)


@dataclass
class ScaleFrom:
    """A known distance between the centres of two views' cameras."""

    image_a: str
    image_b: str
    distance_m: float


@dataclass
class PosedViews:
    """Views with poses in a source's world frame (arbitrary similarity of the turntable frame)."""

    images: list[Path]
    """Image files."""
    names: list[str]
    """The source's name of each view (nerfstudio file_path, COLMAP image name)."""
    masks: list[Path | None]
    """Mask file of each view, or None."""
    intrinsics: Intrinsics
    """The camera, OpenCV convention (pixel centres at integers)."""
    T_world_cam: np.ndarray
    """(V, 4, 4) camera-to-world poses, OpenCV camera axes, the source's units."""
    points: np.ndarray | None = None
    """(P, 3) sparse points in the world frame, or None."""


def parse_scale_from(text: str) -> ScaleFrom:
    """`cam:IMG_A,IMG_B=METRES` as a ScaleFrom; ConfigError when malformed."""
    match = _SCALE_FROM.match(text.strip())
    try:
        distance = float(match.group(3)) if match else math.nan
    except ValueError:
        distance = math.nan
    if not match or not math.isfinite(distance) or distance <= 0:
        raise ConfigError(f"--scale-from {text!r}: expected cam:IMG_A,IMG_B=METRES with a positive distance",
                          "e.g. --scale-from cam:frame_00001.png,frame_00019.png=0.42")
    return ScaleFrom(match.group(1).strip(), match.group(2).strip(), distance)


# ------------------------------------------------------------------------------------------------- readers

def read_nerfstudio(directory: str | Path) -> PosedViews:
    """The views of a nerfstudio dataset (`directory/transforms.json`, see the module doc)."""
    directory = Path(directory)
    path = directory / "transforms.json"
    if not path.is_file():
        raise ContractError(f"{path} does not exist", "give the folder of a nerfstudio dataset (it holds "
                            "transforms.json), or use --from colmap for a COLMAP model")
    try:
        data = json.loads(path.read_text())
        frames = data["frames"]
    except (OSError, json.JSONDecodeError) as exc:
        raise ContractError(f"cannot read {path}: {exc}", "is it a nerfstudio transforms.json?") from None
    except (KeyError, TypeError):
        raise ContractError(f"{path} has no frames list", "is it a nerfstudio transforms.json?") from None
    if not isinstance(frames, list) or not frames:
        raise ContractError(f"{path} lists no frames", "a dataset needs posed frames")
    intrinsics, images, names, masks, poses = None, [], [], [], []
    for i, frame in enumerate(frames):
        where = f"{path} frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise ContractError(f"{where} lacks file_path or transform_matrix", "every frame needs both")
        intr = _nerfstudio_intrinsics({**data, **frame}, where)
        if intrinsics is not None and not _same_camera(intrinsics, intr):
            raise ContractError(f"{where} has other intrinsics than frame 0 ({_camera_text(intr)} vs "
                                f"{_camera_text(intrinsics)})", "a session has one camera: import the frames "
                                "of one camera setting")
        intrinsics = intrinsics or intr
        images.append(_existing_file(directory, frame["file_path"], where))
        names.append(str(frame["file_path"]))
        masks.append(_existing_file(directory, frame["mask_path"], where) if frame.get("mask_path") else None)
        poses.append(_rigid(frame["transform_matrix"], where) @ OPENGL_FROM_OPENCV)
    points = _ply_points(_existing_file(directory, data["ply_file_path"], str(path))) if data.get("ply_file_path") \
        else None
    return PosedViews(images, names, masks, intrinsics, np.stack(poses), points)


def _ply_points(path: Path) -> np.ndarray | None:
    """(P, 3) finite vertices of a PLY point cloud (nerfstudio's sparse_pc.ply), None when it has none."""
    import trimesh

    try:
        vertices = np.asarray(trimesh.load(path, process=False).vertices, dtype=float).reshape(-1, 3)
    except Exception as exc:  # trimesh raises many kinds on a damaged file
        raise ContractError(f"cannot read the point cloud {path}: {exc}", "re-export it, or remove "
                            "ply_file_path from transforms.json") from None
    vertices = vertices[np.isfinite(vertices).all(1)]
    return vertices if len(vertices) else None


def _nerfstudio_intrinsics(d: dict, where: str) -> Intrinsics:
    model = d.get("camera_model", "OPENCV")
    if model not in _NERFSTUDIO_MODELS:
        raise ContractError(f"{where}: camera_model {model!r} is not supported",
                            f"n2d reads {', '.join(_NERFSTUDIO_MODELS)} cameras; undistort the images first")
    try:
        v = {k: float(d[k] if k in ("fl_x", "cx", "cy") else d.get(k, 0.0)) for k in _INTRINSIC_KEYS}
        v["fl_y"] = float(d.get("fl_y", v["fl_x"]))
        width, height = int(d["w"]), int(d["h"])
    except KeyError as exc:
        raise ContractError(f"{where}: missing {exc.args[0]!r}", "nerfstudio needs fl_x, cx, cy, w and h") from None
    except (TypeError, ValueError) as exc:
        raise ContractError(f"{where}: intrinsics must be numbers ({exc})") from None
    if not all(math.isfinite(x) for x in v.values()) or v["k4"] != 0:
        raise ContractError(f"{where}: intrinsics must be finite, and k4 (fisheye) is not supported",
                            "undistort fisheye images first")
    K = np.array([[v["fl_x"], 0.0, v["cx"] - PIXEL_EDGE], [0.0, v["fl_y"], v["cy"] - PIXEL_EDGE], [0.0, 0.0, 1.0]])
    return Intrinsics(K, np.array([v["k1"], v["k2"], v["p1"], v["p2"], v["k3"]]), width, height)


def read_colmap(directory: str | Path) -> PosedViews:
    """The registered views of a COLMAP sparse model and its images (see the module doc)."""
    import pycolmap

    directory = Path(directory)
    model_dir = next((d for d in (directory / "sparse" / "0", directory / "sparse", directory)
                      if any((d / f"cameras.{ext}").is_file() for ext in ("bin", "txt"))), None)
    if model_dir is None:
        raise ContractError(f"{directory} holds no COLMAP sparse model (sparse/0/cameras.bin or .txt)",
                            "give the folder with images/ and sparse/0/, or use --from nerfstudio")
    try:
        model = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises its own runtime errors on a damaged model
        raise ContractError(f"cannot read the COLMAP model in {model_dir}: {exc}",
                            "is it a complete sparse model (cameras, images, points3D)?") from None
    image_dir = directory / "images" if (directory / "images").is_dir() else directory
    registered = sorted((im for im in model.images.values() if im.has_pose), key=lambda im: im.name)
    if not registered:
        raise ContractError(f"the COLMAP model in {model_dir} has no posed images", "run COLMAP's mapper first")
    cameras = {im.camera_id for im in registered}
    intrinsics = [_colmap_intrinsics(model.cameras[c]) for c in sorted(cameras)]
    if any(not _same_camera(intrinsics[0], intr) for intr in intrinsics[1:]):
        raise ContractError(f"the COLMAP model has {len(cameras)} different cameras",
                            "a session has one camera: map with a single shared camera")
    images, masks, poses = [], [], []
    for im in registered:
        where = f"COLMAP image {im.name}"
        images.append(_existing_file(image_dir, im.name, where))
        masks.append(_colmap_mask(directory / "masks", im.name))
        T = np.eye(4)
        T[:3] = im.cam_from_world().matrix()
        poses.append(inv_T(_rigid(T, where)))
    points = np.array([p.xyz for p in model.points3D.values()], dtype=float).reshape(-1, 3)
    return PosedViews(images, [im.name for im in registered], masks, intrinsics[0], np.stack(poses),
                      points if len(points) else None)


def _colmap_intrinsics(camera) -> Intrinsics:
    p = [float(x) for x in camera.params]
    model = camera.model_name if hasattr(camera, "model_name") else str(camera.model).split(".")[-1]
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1:3]
        dist = [p[3] if len(p) > 3 else 0.0, p[4] if len(p) > 4 else 0.0, 0.0, 0.0, 0.0]
    elif model in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy = p[:4]
        dist = (p[4:8] if model == "OPENCV" else [0.0] * 4) + [0.0]
    else:
        raise ContractError(f"COLMAP camera model {model} is not supported",
                            "use SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV, or undistort the "
                            "model first (colmap image_undistorter)")
    K = np.array([[fx, 0.0, cx - PIXEL_EDGE], [0.0, fy, cy - PIXEL_EDGE], [0.0, 0.0, 1.0]])
    return Intrinsics(K, np.array(dist), int(camera.width), int(camera.height))


def _colmap_mask(mask_dir: Path, name: str) -> Path | None:
    for candidate in (mask_dir / f"{name}.png", (mask_dir / name).with_suffix(".png")):
        if candidate.is_file():
            return candidate
    return None


def _existing_file(directory: Path, relative, where: str) -> Path:
    path = directory / str(relative)
    if not path.is_file():
        raise ContractError(f"{where}: {path} does not exist", "every frame's files must be in the dataset")
    return path


def _rigid(matrix, where: str) -> np.ndarray:
    """A 3x4 or 4x4 rigid pose as 4x4; ContractError when malformed, non-finite or not a rotation."""
    try:
        M = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        M = np.zeros(0)
    if M.shape not in ((3, 4), (4, 4)) or not np.isfinite(M).all():
        raise ContractError(f"{where}: the pose is not a finite 3x4 or 4x4 matrix", "re-export the poses")
    R = M[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise ContractError(f"{where}: the pose's rotation is not a rotation (scaled, sheared or mirrored)",
                            "re-export the poses as rigid camera-to-world transforms")
    return make_T(R, M[:3, 3])


def _same_camera(a: Intrinsics, b: Intrinsics) -> bool:
    return ((a.width, a.height) == (b.width, b.height) and np.allclose(a.K, b.K, atol=1e-6)
            and np.allclose(a.dist, b.dist, atol=1e-9))


def _camera_text(intr: Intrinsics) -> str:
    return f"{intr.width}x{intr.height}, f {intr.K[0, 0]:.1f}/{intr.K[1, 1]:.1f} px"


# ------------------------------------------------------------------------------------------------ geometry

@dataclass
class Placement:
    """Where the imported world frame lies in the turntable frame, and how well the evidence agrees."""

    T_turntable_world: np.ndarray
    """4x4 similarity (scale s R, translation) from the source's world frame into the turntable frame, metres."""
    scale_from: str
    """board or distance."""
    scale: float
    """Metres per source unit."""
    up_from: str
    """ring (the camera ring's axis), board (its normal) or points (the dominant plane of the sparse points)."""
    plate_from: str
    """board or points: what fixed the plate's height."""
    alignment_mm: float | None
    """RMS distance between the mapped camera centres and those seen from the board (board scale only)."""
    ring_residual_mm: float
    """RMS distance of the camera centres from the fitted ring circle, mm."""
    ring_radius_m: float
    """Radius of the camera ring, metres."""
    board_tilt_deg: float | None
    """Angle between the ring's axis and the board's normal."""

    def to_dict(self) -> dict:
        """JSON-safe form for capture.json."""
        return {"T_turntable_world": self.T_turntable_world.tolist(), "scale_from": self.scale_from,
                "scale_m_per_unit": self.scale, "up_from": self.up_from,
                "plate_from": self.plate_from, "alignment_mm": self.alignment_mm,
                "ring_residual_mm": self.ring_residual_mm, "ring_radius_m": self.ring_radius_m,
                "board_tilt_deg": self.board_tilt_deg}


def fit_ring(centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(unit normal of arbitrary sign, circle centre, radius, RMS distance from the circle) of (V, 3) points
    on a ring: the plane by SVD, the circle in it by `axis_through`."""
    _, S, Vt = np.linalg.svd(centres - centres.mean(0))
    if len(centres) < 3 or S[1] < 0.05 * S[0]:
        raise CalibrationError(f"the {len(centres)} camera centres do not span a ring (they lie on a line)",
                               "import views from around the object: a turntable sweep or a walk around it")
    normal = Vt[2]
    centre, radius = axis_through(centres, normal)
    offsets = centres - centre
    height = offsets @ normal
    radial = np.linalg.norm(offsets - height[:, None] * normal, axis=1) - radius
    return normal, centre, radius, float(np.sqrt((radial ** 2 + height ** 2).mean()))


def axis_through(centres: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, float]:
    """(a point of the axis along `up` the (V, 3) camera centres stand around, their mean distance from it):
    the circle fitted to their projections onto the plane normal to `up` (algebraic least squares, Kasa),
    at their mean height."""
    mean = centres.mean(0)
    u = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(up, u)
    xy = np.stack([(centres - mean) @ u, (centres - mean) @ v], 1)
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    (a, b, c), *_ = np.linalg.lstsq(A, (xy ** 2).sum(1), rcond=None)
    return mean + a * u + b * v, math.sqrt(max(c + a * a + b * b, 0.0))


def table_plane(points: np.ndarray, tolerance_m: float, iterations: int = 300,
                seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """(unit normal of arbitrary sign, a point, inlier share) of the dominant plane of (P, 3) points in metres:
    RANSAC over point triples (at most 5000 points scored), refined by SVD over the inliers."""
    rng = np.random.default_rng(seed)
    sample = points[rng.choice(len(points), min(len(points), 5000), replace=False)]
    triples = sample[rng.integers(0, len(sample), (iterations, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-12
    normals, base = normals[good] / length[good, None], triples[good, 0]
    if not len(normals):
        raise ContractError("the sparse points hold no plane", "let the board show in 3+ views")
    counts = (np.abs(np.einsum("ij,pj->ip", normals, sample) - (normals * base).sum(1)[:, None]) < tolerance_m).sum(1)
    best = int(np.argmax(counts))
    inliers = points[np.abs((points - base[best]) @ normals[best]) < tolerance_m]
    centre = inliers.mean(0)
    normal = np.linalg.svd(inliers - centre)[2][2]
    return normal, centre, float(counts[best] / len(sample))


def find_board(rgb: np.ndarray, intr: Intrinsics, cfg: CaptureConfig) -> BoardPose | None:
    """The board's pose in one view, None where it is not found or its corners fit worse than
    `cfg.max_board_rms_px`."""
    det = detect_board(rgb, cfg.board)
    p = board_pose(det, intr.K, intr.dist) if det is not None else None
    return p if p is not None and p.rms_px <= cfg.max_board_rms_px else None


def _board_scale(views: PosedViews, poses: list[BoardPose | None], cfg: PosedImportConfig
                 ) -> tuple[np.ndarray | None, float | None]:
    """(similarity world to board frame, RMS centre disagreement mm) from the views' board poses (None where
    a view has none); (None, None) when the board shows in too few views."""
    seen = [i for i, p in enumerate(poses) if p is not None]
    if len(seen) < cfg.min_board_views:
        return None, None
    world = views.T_world_cam[seen, :3, 3]
    board = np.stack([inv_T(poses[i].T_cam_board)[:3, 3] for i in seen])
    s, R, t = similarity(world, board)
    alignment = float(1000 * np.sqrt(((s * world @ R.T + t - board) ** 2).sum(1).mean()))
    if alignment > cfg.max_alignment_mm:
        raise CalibrationError(f"the imported camera centres and those seen from the board disagree by "
                               f"{alignment:.1f} mm RMS over {len(seen)} views",
                               "check the board spec (--board, square size) and that the poses and images match")
    return make_T(s * R, t), alignment  # board = s R world + t


def _distance_scale(views: PosedViews, scale_from: ScaleFrom) -> np.ndarray:
    """Similarity (a pure scale) from the world frame into metres from a known camera-centre distance."""
    def index(name: str) -> int:
        hits = [i for i, (n, p) in enumerate(zip(views.names, views.images)) if name in (n, p.name)]
        if len(hits) != 1:
            raise ConfigError(f"--scale-from: {'no' if not hits else 'more than one'} view named {name!r}",
                              f"name a view as the source does, e.g. {views.names[0]!r}")
        return hits[0]

    a, b = index(scale_from.image_a), index(scale_from.image_b)
    units = float(np.linalg.norm(views.T_world_cam[a, :3, 3] - views.T_world_cam[b, :3, 3]))
    if a == b or units < 1e-9 * max(1.0, float(np.abs(views.T_world_cam[:, :3, 3]).max())):
        raise ConfigError("--scale-from: the two views' cameras stand at the same place",
                          "pick two views far apart, e.g. opposite sides of the ring")
    return np.diag([scale_from.distance_m / units] * 3 + [1.0])


def place_views(views: PosedViews, board_poses: list[BoardPose | None], cfg: PosedImportConfig) -> Placement:
    """The turntable frame of the views (see the module doc); `board_poses`: each view's (`find_board`), or
    None (all None with `cfg.scale_from`)."""
    scale_from = parse_scale_from(cfg.scale_from) if cfg.scale_from else None
    alignment = None
    if scale_from is None:
        S, alignment = _board_scale(views, board_poses, cfg)
        if S is None:
            seen = sum(p is not None for p in board_poses)
            raise ConfigError(f"the board shows in {seen} view(s), too few to make the session metric",
                              _SCALE_HINT)
    else:
        S = _distance_scale(views, scale_from)
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    T_M_cam = S @ views.T_world_cam  # metric frame M: the board's, or the source's scaled
    T_M_cam[:, :3, :3] /= scale
    centres = T_M_cam[:, :3, 3]
    ring = fit_ring(centres)
    normal, origin, radius, up_from, plate_from, tilt = _up_and_origin(
        views, S, ring, T_M_cam[:, :3, 2].mean(0), board=scale_from is None, cfg=cfg)
    x = np.array([1.0, 0.0, 0.0]) if scale_from is None else centres[0] - origin
    x = x - (x @ normal) * normal
    if np.linalg.norm(x) < 1e-9:
        raise CalibrationError("the X axis of the turntable frame is undefined (the board stands upright)",
                               "the board must lie flat on the plate")
    x /= np.linalg.norm(x)
    T_turntable_M = inv_T(make_T(np.stack([x, np.cross(normal, x), normal], axis=1), origin))
    placement = Placement(T_turntable_M @ S, "board" if scale_from is None else "distance", scale, up_from,
                          plate_from, alignment, 1000 * ring[3], radius, tilt)
    return placement


def _up_and_origin(views: PosedViews, S: np.ndarray, ring: tuple, looking: np.ndarray, *, board: bool,
                   cfg: PosedImportConfig) -> tuple[np.ndarray, np.ndarray, float, str, str, float | None]:
    """(Z, origin, ring radius, up_from, plate_from, board tilt in degrees or None) of the turntable frame in
    the metric frame M (the board's with `board`, else the source's scaled by S); `ring` is `fit_ring`'s
    result, `looking` the cameras' mean optical axis (they look down at the object: against up)."""
    normal, centre, radius, ring_rms = ring
    is_ring = ring_rms <= cfg.max_ring_residual * radius
    board_up = np.array([0.0, 0.0, -1.0])  # board z points into the board
    tilt = None
    if board:  # the plate is the board's top plane, z = 0 in M
        plate_normal, plate_point, plate_from = board_up, np.zeros(3), "board"
        normal, up_from = (normal, "ring") if is_ring else (board_up, "board")
        normal = normal if normal @ board_up > 0 else -normal
        tilt = math.degrees(math.acos(min(1.0, float(normal @ board_up))))
    elif is_ring:  # a plane normal to the axis, under the lowest points near it
        normal, up_from, plate_from = (normal if normal @ looking < 0 else -normal), "ring", "points"
        plate_normal = normal
        plate_point = centre + _plate_height(_metric_points(views, S), centre, normal, radius, cfg) * normal
    else:  # no ring: the dominant plane of the sparse points is the table
        plate_normal, plate_point, _ = table_plane(_metric_points(views, S), cfg.plane_tolerance_m)
        normal = plate_normal = plate_normal if plate_normal @ looking < 0 else -plate_normal
        up_from, plate_from = "points", "points"
    if not is_ring:
        centre, radius = axis_through(views.T_world_cam[:, :3, 3] @ S[:3, :3].T + S[:3, 3], normal)
    origin = centre + (plate_normal @ (plate_point - centre)) / (plate_normal @ normal) * normal
    return normal, origin, radius, up_from, plate_from, tilt


def _metric_points(views: PosedViews, S: np.ndarray) -> np.ndarray:
    """The sparse points carried by the similarity S into metres; ContractError when the source has none."""
    if views.points is None or len(views.points) < 10:
        raise ContractError("without the board nothing places the plate: the source has no sparse points",
                            "let the board show in 3+ views, or give the sparse points (COLMAP's points3D, "
                            "nerfstudio's ply_file_path)")
    return views.points @ S[:3, :3].T + S[:3, 3]


def _plate_height(points: np.ndarray, centre: np.ndarray, up: np.ndarray, radius: float,
                  cfg: PosedImportConfig) -> float:
    """Height along `up` of the plate above the ring's centre, from the (P, 3) points near the axis, metres."""
    offsets = points - centre
    heights = offsets @ up
    lateral = np.linalg.norm(offsets - heights[:, None] * up, axis=1)
    near = heights[(lateral <= cfg.plate_radius_fraction * radius) & (heights < 0)]
    if len(near) < 10:
        raise ContractError(f"only {len(near)} sparse points lie under the cameras near the ring's axis, too few "
                            "to place the plate", "let the board show in 3+ views")
    return float(np.percentile(near, cfg.plate_percentile))


# ------------------------------------------------------------------------------------------------- writing

def _read_image(image: Path, size: tuple[int, int]) -> np.ndarray:
    """RGB of a view; ContractError when it is not of the camera's size."""
    rgb = read_photo(image)
    if (rgb.shape[1], rgb.shape[0]) != size:
        raise ContractError(f"{image} is {rgb.shape[1]}x{rgb.shape[0]}, the camera's images are {size[0]}x{size[1]}",
                            "all images must be of the camera's size (not downscaled copies)")
    return rgb


def _read_view(image: Path, mask: Path | None, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
    """(RGB, mask or None) of a view: the mask file, or the image's alpha channel where it has one."""
    rgb = _read_image(image, size)
    if mask is not None:
        m = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
        if m is None or (m.shape[1], m.shape[0]) != size:
            raise ContractError(f"mask {mask} is unreadable or not {size[0]}x{size[1]}",
                                "masks must be 8-bit images of the photos' size")
        return rgb, m > 127
    raw = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if raw is not None and raw.ndim == 3 and raw.shape[2] == 4 and raw[..., 3].min() < raw[..., 3].max():
        return rgb, raw[..., 3] > raw[..., 3].max() / 2
    return rgb, None


def _write_view(directory: Path, i: int, views: PosedViews, T_turntable_cam: np.ndarray, pose: BoardPose | None,
                cfg: CaptureConfig) -> tuple[dict, np.ndarray]:
    """Write view `i`'s image and mask (the source's, or made from the board) into the session `directory`;
    returns its capture.json record and its contact-sheet thumbnail."""
    intr = views.intrinsics
    rgb, mask = _read_view(views.images[i], views.masks[i], (intr.width, intr.height))
    image_file, mask_file = f"images/{i:04d}.png", f"masks/{i:04d}.png"
    write_png(directory / image_file, rgb)
    given = mask is not None
    if not given:
        mask = foreground_mask_no_reference(rgb, ViewGeometry(intr.K, inv_T(T_turntable_cam), cfg.board), cfg.masks)
    write_mask(directory / mask_file, mask)
    record = {"index": i, "file": image_file, "mask": mask_file, "source": views.names[i], "angle_rad": None,
              "pose_source": "imported", "board_rms_px": pose.rms_px if pose else None,
              "board_corners": pose.n_corners if pose else 0, "mask_pixels": int(mask.sum()),
              "mask_method": "given" if given else "geometry"}
    thumb = overlay_view(rgb, mask, intr, inv_T(T_turntable_cam), Path(views.names[i]).name)
    # the sheet's thumbnail size now, so a dataset of many large photos is never held in memory whole
    return record, cv2.resize(thumb, (THUMB_WIDTH, round(thumb.shape[0] * THUMB_WIDTH / thumb.shape[1])),
                              interpolation=cv2.INTER_AREA)


def import_posed(source_dir: str | Path, session_dir: str | Path, cfg: PosedImportConfig, *,
                 source: Literal["nerfstudio", "colmap"] = "nerfstudio", overwrite: bool = False,
                 progress: ProgressFn = no_progress) -> dict:
    """Turn a nerfstudio dataset or a COLMAP model into a complete capture session (see the module doc).

    Args:
        source_dir: the dataset folder (nerfstudio: holds transforms.json; colmap: images/ and sparse/0/).
        session_dir: the capture session to write.
        cfg: board, masks, scale and plate settings.
        source: "nerfstudio" or "colmap".
        overwrite: replace an existing session (only once the new one is complete).
        progress: progress reports.

    Returns:
        A summary: views, scale_from, alignment_mm, ring_residual_mm, masks_given, masks_made, message.

    Raises:
        ContractError: missing or malformed source, files it names missing, images of another size, an
            existing output without `overwrite`, nothing to place the plate.
        ConfigError: no scale source, or a malformed `scale_from`.
        CalibrationError: the board disagrees with the poses, or the cameras do not form a ring.
    """
    if source not in SOURCES:
        raise ConfigError(f"unknown source {source!r}", f"use one of {', '.join(SOURCES)}")
    t0 = time.monotonic()
    source_dir = Path(source_dir)
    views = read_nerfstudio(source_dir) if source == "nerfstudio" else read_colmap(source_dir)
    intr, n = views.intrinsics, len(views.images)
    board_poses = [None] * n  # one image in memory at a time: datasets may hold hundreds of large photos
    for i, image in enumerate(views.images if not cfg.scale_from else []):
        progress(Progress(0.4 * i / n, "posing", message=f"board in {image.name}"))
        board_poses[i] = find_board(_read_image(image, (intr.width, intr.height)), intr, cfg.capture)
    placement = place_views(views, board_poses, cfg)
    T_turntable_cam = [placement.T_turntable_world @ T for T in views.T_world_cam]
    for T in T_turntable_cam:
        T[:3, :3] /= placement.scale

    with import_output(session_dir, to_dict(cfg), overwrite) as out:
        records, frames, sheet = [], [], []
        for i, T in enumerate(T_turntable_cam):
            progress(Progress(0.4 + 0.5 * i / n, "writing", message=f"view {i + 1}/{n}"))
            record, thumb = _write_view(out.path, i, views, T, board_poses[i], cfg.capture)
            records.append(record)
            frames.append((record["file"], record["mask"], T))
            sheet.append(thumb)
        atomic_write_json(out.path / "transforms.json",
                          transforms_json(intr.K, intr.dist, intr.width, intr.height, frames))
        made = sum(r["mask_method"] == "geometry" for r in records)
        atomic_write_json(out.path / "capture.json", {
            "board": cfg.capture.board.to_dict(), "intrinsics": intr.to_dict(), "intrinsics_source": source,
            "views": records, "empty_views": 0, "process_s": round(time.monotonic() - t0, 2),
            "import": {"from": source, "source_dir": str(source_dir.absolute()), **placement.to_dict()}})
        write_png(out.path / "contact_sheet.png", contact_sheet(sheet, cols=min(6, len(sheet)),
                                                                   thumb_width=THUMB_WIDTH))
        summary = {"views": n, "posed_from_import": n, "scale_from": placement.scale_from,
                   "alignment_mm": placement.alignment_mm, "ring_residual_mm": placement.ring_residual_mm,
                   "board_tilt_deg": placement.board_tilt_deg, "masks_given": n - made, "masks_made": made}
        out.finish(config=to_dict(cfg), inputs={source: source_dir.absolute()}, extra=summary)
    progress(Progress(1.0, "writing"))
    return {**summary, "message": ""}
