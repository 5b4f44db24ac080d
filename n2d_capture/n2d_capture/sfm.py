"""Camera poses from the object itself: pycolmap structure from motion over a turntable sweep, made metric.

The alternative to the board for captures where it is hidden or absent (`pose_from: colmap`). COLMAP
(SIFT, matching of each view with its neighbours around the turn, incremental mapping with the known
intrinsics held fixed) poses every view in a world frame of its own, up to scale. The camera stands still
while the plate turns, so only the turning part may give features: a feature mask keeps the pixels that
change over the sweep (the object, the plate and the board turn; the room does not).

COLMAP poses each view on its own; a small object seen from a ring of views leaves them loose (in the
simulator about 1 degree and 10 mm apart from a rigid turn). So they are adjusted as what they are: one
fixed camera and a plate turning about one axis. A bundle adjustment over COLMAP's points and observations
with one camera-to-plate pose and a plate angle per view (`turntable_adjust`) makes every pose an exact
turn of the others.

That world frame is attached to the plate as the board is. `sfm_poses` maps it onto the board's frame and
metres, so the result is a board pose per view and the rest of the capture (turntable fit, masks) runs
unchanged:
- board found in 3+ registered views: the similarity (scale, rotation, shift; Umeyama) that carries the
  COLMAP camera centres onto the camera centres seen from the board;
- otherwise: a virtual board lying on the plate where the object stands. Its z points down the rotation
  axis (the axis of the turns between views; the camera looks down at the plate, which fixes the sign),
  its origin is where the axis meets the plane of the object's lowest points, and the scale comes from
  `camera_distance_m`, the distance from the camera to that point measured by hand.

The sparse model is kept in the session's `colmap/` folder (COLMAP's binary format) for inspection.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from n2d_capture.board import CalibrationError
from n2d_capture.calibration import Intrinsics
from n2d_capture.turntable_frame import turn_axis
from n2d_common.frames import inv_T, make_T, rot_z
from n2d_common.progress import Progress, ProgressFn, no_progress

COLMAP_DIR = "colmap"
"""Folder of a session holding COLMAP's database, feature masks and sparse model."""

_NO_SCALE = "the board shows in only {} posed view(s), so the scale of the views posed from the object is unknown"
_SFM_HINT = ("the object needs texture, the views at most ~15 degrees apart and a fixed exposure; "
             "or use the board (pose_from: axis)")
_NO_SCALE_HINT = ("measure the distance from the camera to the plate centre and set sfm.camera_distance_m "
                  "(metres), or let the board show in 3+ views")


@dataclass
class SfmConfig:
    """Structure from motion over the object views (used with `pose_from: colmap`)."""

    max_features: int = 4096
    """SIFT features per image at most."""
    neighbours: int = 4
    """Each view is matched with this many views on either side of it around the turn."""
    change_threshold_dn: float = 10.0
    """Feature mask: pixels whose brightness varies over the sweep by more than this standard deviation
    (8-bit levels) turn with the plate; the rest is the room, and gives no features."""
    mask_dilation_px: int = 15
    """Growth of the feature mask, so features at the turning part's edges keep their support."""
    camera_distance_m: float = 0.0
    """Without the board in 3+ views: the distance from the camera's centre to the point where the rotation
    axis meets the plate (under the object), measured by hand, metres; it sets the scale. 0: the board must
    give the scale."""
    min_registered: float = 0.7
    """Fail when COLMAP poses a smaller fraction of the views."""
    max_alignment_mm: float = 5.0
    """Fail when the COLMAP camera centres and the board's disagree by more than this (RMS, mm)."""
    threads: int = 0
    """CPU threads (0: all cores)."""
    seed: int = 0
    """Seed of COLMAP's random sampling."""

    def __post_init__(self):
        if self.max_features < 100 or self.neighbours < 1:
            raise ValueError("sfm.max_features must be >= 100 and sfm.neighbours >= 1")
        if self.camera_distance_m < 0 or self.change_threshold_dn <= 0 or self.mask_dilation_px < 0:
            raise ValueError("sfm.camera_distance_m and sfm.mask_dilation_px must be >= 0, "
                             "sfm.change_threshold_dn > 0")
        if self.max_alignment_mm <= 0:
            raise ValueError(f"sfm.max_alignment_mm must be > 0, got {self.max_alignment_mm}")
        if not 0.0 < self.min_registered <= 1.0:
            raise ValueError(f"sfm.min_registered must be in (0, 1], got {self.min_registered}")


@dataclass
class SfmResult:
    """Metric board poses from structure from motion, and how they were made."""

    T_cam_board: list[np.ndarray | None]
    """Per view: 4x4 board (or virtual board) -> camera, metres; None where COLMAP could not pose the view."""
    scale_from: str
    """"board" (similarity to the board's camera centres) or "camera_distance" (virtual board)."""
    registered: int
    points: int
    """3D points of the sparse model."""
    reprojection_px: float
    """COLMAP's mean reprojection error."""
    turntable_rms_px: float
    """RMS reprojection error after the turntable adjustment (one camera pose, one plate angle per view)."""
    alignment_mm: float | None
    """RMS distance between the aligned COLMAP camera centres and the board's (board scale only)."""

    def to_dict(self) -> dict:
        return {"scale_from": self.scale_from, "registered": self.registered, "points": self.points,
                "reprojection_px": self.reprojection_px, "turntable_rms_px": self.turntable_rms_px,
                "alignment_mm": self.alignment_mm}


def feature_masks(images: Sequence[np.ndarray], cfg: SfmConfig) -> list[np.ndarray]:
    """Per view a uint8 mask (255: features allowed): pixels that change over the sweep, in that view's image
    where it differs from the sweep's per-pixel median (the still room), grown by `mask_dilation_px`."""
    gray = np.stack([cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32) for img in images])
    still = np.median(gray, axis=0)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * cfg.mask_dilation_px + 1,) * 2)
    moving = gray.std(axis=0) > cfg.change_threshold_dn
    out = []
    for g in gray:
        changed = (np.abs(cv2.GaussianBlur(g - still, (0, 0), 2.0)) > cfg.change_threshold_dn) & moving
        out.append(cv2.dilate(changed.astype(np.uint8) * 255, kernel))
    return out


def _run_colmap(work: Path, image_dir: Path, names: list[str], images: Sequence[np.ndarray], intr: Intrinsics,
                cfg: SfmConfig, progress: ProgressFn):
    import pycolmap

    if work.exists():
        shutil.rmtree(work)
    (work / "masks").mkdir(parents=True)
    for name, mask in zip(names, feature_masks(images, cfg)):
        path = work / "masks" / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), mask)
    database = work / "database.db"
    d = np.zeros(8)
    d[:min(8, len(intr.dist))] = np.ravel(intr.dist)[:8]
    K = intr.K
    # COLMAP puts pixel centres at +0.5; FULL_OPENCV takes OpenCV's k1 k2 p1 p2 k3 k4 k5 k6
    params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, *d]
    reader = pycolmap.ImageReaderOptions(camera_model="FULL_OPENCV", camera_params=",".join(map(str, params)),
                                         mask_path=str(work / "masks"))
    # SIFT features and brute-force SIFT matching on the pair list written below, named explicitly rather than
    # left to COLMAP's defaults: every input COLMAP gets here is made from this session's images
    extraction = pycolmap.FeatureExtractionOptions(num_threads=cfg.threads or -1,
                                                   type=pycolmap.FeatureExtractorType.SIFT)
    extraction.sift.max_num_features = cfg.max_features
    progress(Progress(0.05, "sfm", message="COLMAP: SIFT features"))
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    n = len(names)
    pairs = {tuple(sorted((names[i], names[(i + k) % n]))) for i in range(n)
             for k in range(1, min(cfg.neighbours, (n - 1) // 2 or 1) + 1)}
    (work / "pairs.txt").write_text("".join(f"{a} {b}\n" for a, b in sorted(pairs)))
    progress(Progress(0.1, "sfm", message=f"COLMAP: matching {len(pairs)} pairs"))
    matching = pycolmap.FeatureMatchingOptions(num_threads=cfg.threads or -1,
                                               type=pycolmap.FeatureMatcherType.SIFT_BRUTEFORCE)
    pycolmap.match_image_pairs(database, matching,
                               pycolmap.ImportedPairingOptions(match_list_path=str(work / "pairs.txt")),
                               device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions(ba_refine_focal_length=False, ba_refine_principal_point=False,
                                                  ba_refine_extra_params=False, num_threads=cfg.threads or -1,
                                                  random_seed=cfg.seed, multiple_models=False)
    registered = [0]

    def next_image():
        registered[0] += 1
        progress(Progress(0.15 + 0.05 * min(1.0, registered[0] / n), "sfm",
                          message=f"COLMAP: {registered[0]}/{n} views posed"))

    models = pycolmap.incremental_mapping(database, image_dir, work / "sparse", options=options,
                                          next_image_callback=next_image)
    if not models:
        raise CalibrationError("COLMAP could not pose the views from the object alone", _SFM_HINT)
    return max(models.values(), key=lambda r: r.num_reg_images())


def turntable_adjust(model, names: list[str], intr: Intrinsics
                     ) -> tuple[list[np.ndarray | None], np.ndarray, float]:
    """(per view T_cam_plate or None where unposed, points in the plate frame (P, 3), RMS px) of a COLMAP model
    re-adjusted as one fixed camera and a turning plate: x_ij = project(A Rz(phi_i) X_j), over A (6), the
    angles phi_i (the first posed view's fixed at 0) and the points, with a robust (soft L1, 0.5 px) loss.
    The plate frame's Z is the rotation axis; its origin, yaw and the scale are COLMAP's (gauge-free)."""
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    index = {name: i for i, name in enumerate(names)}
    images = {img.image_id: img for img in model.images.values() if img.has_pose and img.name in index}
    views = sorted(index[img.name] for img in images.values())
    slot = {v: k for k, v in enumerate(views)}
    T0 = np.stack([_pose(img) for img in sorted(images.values(), key=lambda img: index[img.name])])
    obs_view, obs_point, obs_px, points = [], [], [], []
    for p in model.points3D.values():
        track = [(slot[index[images[e.image_id].name]], images[e.image_id].points2D[e.point2D_idx].xy)
                 for e in p.track.elements if e.image_id in images]
        if len(track) < 2:
            continue
        for k, xy in track:
            obs_view.append(k)
            obs_point.append(len(points))
            obs_px.append(np.asarray(xy) - 0.5)  # COLMAP pixel centres at +0.5
        points.append(p.xyz)
    obs_view, obs_point = np.array(obs_view), np.array(obs_point)
    f = float(intr.K[0, 0])
    obs = cv2.undistortPoints(np.array(obs_px, np.float64)[:, None], intr.K, np.ravel(intr.dist)).reshape(-1, 2)

    # Initial turntable model: the axis from the views' relative turns, each view's angle about it.
    up, centre = turn_axis(T0)
    x = np.cross(up, [0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.cross(up, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    A = make_T(np.stack([x, np.cross(up, x), up], axis=1), centre)
    M = inv_T(A) @ T0  # Rz(phi_i) T_plate_world
    Q = M[:, :3, :3] @ M[0, :3, :3].T
    phi0 = np.arctan2(Q[:, 1, 0] - Q[:, 0, 1], Q[:, 0, 0] + Q[:, 1, 1])
    X0 = np.asarray(points) @ M[0, :3, :3].T + M[0, :3, 3]
    n_views, n_points = len(views), len(X0)

    def unpack(params):
        R_A = cv2.Rodrigues(params[:3])[0]
        phi = np.concatenate([[0.0], params[6:5 + n_views]])
        return R_A, params[3:6], phi, params[5 + n_views:].reshape(n_points, 3)

    def residuals(params):
        R_A, t_A, phi, X = unpack(params)
        c, s = np.cos(phi[obs_view]), np.sin(phi[obs_view])
        Xp = X[obs_point]
        turned = np.stack([c * Xp[:, 0] - s * Xp[:, 1], s * Xp[:, 0] + c * Xp[:, 1], Xp[:, 2]], axis=1)
        cam = turned @ R_A.T + t_A
        return (f * (cam[:, :2] / cam[:, 2:3] - obs)).ravel()

    # Which parameters each residual depends on: A (6), its view's angle (none for the first), its point (3).
    o = np.arange(len(obs_view))
    cols = [np.broadcast_to(np.arange(6), (len(o), 6)), np.where(obs_view > 0, 5 + obs_view, 0)[:, None],
            5 + n_views + 3 * obs_point[:, None] + np.arange(3)]
    cols = np.concatenate(cols, axis=1)
    rows = np.repeat(np.stack([2 * o, 2 * o + 1], axis=1), cols.shape[1], axis=1)
    sparsity = coo_matrix((np.ones(rows.size, np.uint8), (rows.ravel(), np.tile(cols, 2).ravel())),
                          shape=(2 * len(o), 5 + n_views + 3 * n_points)).tocsr()
    start = np.concatenate([cv2.Rodrigues(A[:3, :3])[0].ravel(), A[:3, 3], phi0[1:], X0.ravel()])
    fit = least_squares(residuals, start, jac_sparsity=sparsity, loss="soft_l1", f_scale=0.5, x_scale="jac",
                        max_nfev=200)
    R_A, t_A, phi, X = unpack(fit.x)
    A = make_T(R_A, t_A)
    poses: list[np.ndarray | None] = [None] * len(names)
    for v, angle in zip(views, phi):
        poses[v] = A @ rot_z(angle)
    return poses, X, float(np.sqrt(np.mean(fit.fun ** 2)))


def _pose(image) -> np.ndarray:
    T = np.eye(4)
    T[:3] = image.cam_from_world().matrix()
    return T


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising |dst - (s R src + t)|^2 over (N, 3) point pairs (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a ** 2).sum(1).mean())
    return s, R, md - s * R @ ms


def _virtual_board(T_cam_world: np.ndarray, points_world: np.ndarray,
                   camera_distance_m: float) -> tuple[float, np.ndarray]:
    """(metres per COLMAP unit, T_world_board) of a board lying on the plate under the object (see the module
    doc), from the registered views' poses (V, 4, 4) and the sparse points (P, 3)."""
    up, centre = turn_axis(T_cam_world)
    if up[2] > 0:  # the camera looks down at the plate: its optical axis (camera z) points against up
        up = -up
    T_ref = T_cam_world[0]
    heights = (points_world @ T_ref[:3, :3].T + T_ref[:3, 3] - centre) @ up
    origin = centre + np.percentile(heights, 2) * up  # the camera's frame, COLMAP units
    scale = camera_distance_m / float(np.linalg.norm(origin))
    x = np.cross(up, origin)  # level, across the line of sight
    x /= np.linalg.norm(x)
    down = -up
    T_cam_board = make_T(np.stack([x, np.cross(down, x), down], axis=1), origin)
    return scale, inv_T(T_ref) @ T_cam_board


def sfm_poses(image_dir: Path, names: list[str], images: Sequence[np.ndarray], intr: Intrinsics,
              board_poses: Sequence[np.ndarray | None], cfg: SfmConfig, work: Path,
              progress: ProgressFn = no_progress) -> SfmResult:
    """Metric board poses of the views `names` (relative to `image_dir`; `images` their RGB pixels) from COLMAP
    (see the module doc). `board_poses`: per view the board pose where the board was found, else None.

    Raises:
        CalibrationError: COLMAP posed too few views, no scale is available, or the board disagrees.
    """
    if sum(T is not None for T in board_poses) < 3 and cfg.camera_distance_m <= 0:
        raise CalibrationError(_NO_SCALE.format(sum(T is not None for T in board_poses)), _NO_SCALE_HINT)
    model = _run_colmap(work, image_dir, names, images, intr, cfg, progress)
    T_world, points, rms = turntable_adjust(model, names, intr)
    posed = [i for i, T in enumerate(T_world) if T is not None]
    if len(posed) < max(3, cfg.min_registered * len(names)):
        raise CalibrationError(f"COLMAP posed {len(posed)} of {len(names)} views", _SFM_HINT)
    both = [i for i in posed if board_poses[i] is not None]
    alignment = None
    if len(both) >= 3:
        centres_world = np.stack([inv_T(T_world[i])[:3, 3] for i in both])
        centres_board = np.stack([inv_T(board_poses[i])[:3, 3] for i in both])
        s, R, t = similarity(centres_world, centres_board)  # board = s R world + t, in metres
        alignment = float(1000 * np.sqrt(((s * centres_world @ R.T + t - centres_board) ** 2).sum(1).mean()))
        if alignment > cfg.max_alignment_mm:
            raise CalibrationError(f"the COLMAP camera centres and the board's disagree by {alignment:.1f} mm RMS",
                                   "check the board spec (square size) and the intrinsics")
        scale, T_world_board, scale_from = s, inv_T(make_T(R, t)), "board"
    elif cfg.camera_distance_m > 0:
        scale, T_units = _virtual_board(np.stack([T_world[i] for i in posed]), points, cfg.camera_distance_m)
        T_world_board, scale_from = _metric(T_units, scale), "camera_distance"
    else:
        raise CalibrationError(_NO_SCALE.format(len(both)), _NO_SCALE_HINT)
    poses = [None if T is None else _metric(T, scale) @ T_world_board for T in T_world]
    return SfmResult(poses, scale_from, len(posed), model.num_points3D(),
                     float(model.compute_mean_reprojection_error()), rms, alignment)


def _metric(T: np.ndarray, scale: float) -> np.ndarray:
    """A pose with its translation from COLMAP units into metres."""
    out = np.array(T, dtype=float)
    out[:3, 3] *= scale
    return out
