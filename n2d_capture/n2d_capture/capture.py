"""A capture session from sweeps: camera intrinsics, board poses, the turntable frame, camera poses, masks.

`capture()` is what the `capture` action and `n2d capture` run. Its first call with
`empty_plate=True` records the empty-plate sweep (the background reference) and leaves the session
unfinished; the next call records (or resumes) the object sweep at the same angles and then
`process_session()` turns both into the session contract: every view posed in the metric,
gravity-aligned, plate-attached turntable frame, and masked. A view's pose comes from its servo angle
composed with the rotation axis fitted over the whole sweep (`pose_from: axis`, the default: the fit
averages the board's per-view noise; in the simulator it is ten times more accurate than single board
poses), or from its own board pose (`pose_from: board`, or where the servo angle is unknown or does
not follow the plate), or from the servo angle where the object hides the board. Objects that hide the
board in most views, or captures without one, take `pose_from: colmap`: structure from motion on the
object gives each view a board pose (see `sfm`), metric from the board where it shows or from a measured
camera distance.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from n2d_capture.board import CalibrationError, board_pose, detect_board
from n2d_capture.calibration import Intrinsics, calibrate
from n2d_capture.masks import MaskConfig, ViewGeometry, foreground_mask, foreground_mask_no_reference, write_mask
from n2d_capture.sfm import COLMAP_DIR, SfmConfig, sfm_poses
from n2d_capture.sweep import FrameSource, Rotator, SweepConfig, read_sweep, run_sweep
from n2d_capture.turntable_frame import camera_pose, fit_turntable
from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, stage_output
from n2d_common.errors import ContractError
from n2d_common.formats.board import BoardSpec
from n2d_common.formats.session import transforms_json
from n2d_common.frames import inv_T
from n2d_common.images import contact_sheet, draw_mask_outline, read_png, write_png
from n2d_common.progress import Progress, ProgressFn, no_progress


@dataclass
class CaptureConfig:
    """How a session is captured and processed."""

    sweep: SweepConfig = field(default_factory=SweepConfig)
    """The stops of the plate."""
    board: BoardSpec = field(default_factory=BoardSpec)
    """The ChArUco board lying on the plate."""
    masks: MaskConfig = field(default_factory=MaskConfig)
    """Foreground segmentation."""
    intrinsics: Literal["camera_info", "calibrate"] = "camera_info"
    """Where K comes from: the camera's CameraInfo, or a calibration from the board in the sweeps."""
    max_board_rms_px: float = 1.0
    """Board poses with a larger corner reprojection error (px) are not trusted."""
    pose_from: Literal["axis", "board", "colmap"] = "axis"
    """axis: views with a servo angle are posed from it and the axis fitted over the sweep; board: each view
    from its own board pose where the board is visible; colmap: each view from structure from motion on the
    object (for objects that hide the board; see `sfm`)."""
    sfm: SfmConfig = field(default_factory=SfmConfig)
    """Structure from motion, used with pose_from: colmap."""

    def __post_init__(self):
        if self.max_board_rms_px <= 0:
            raise ValueError("max_board_rms_px must be > 0")


def capture(session_dir: str | Path, cfg: CaptureConfig, rotator: Rotator, camera: FrameSource, *,
            empty_plate: bool = False, overwrite: bool = False,
            progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> dict:
    """Record one sweep into `session_dir` (see the module doc); returns a summary dict.

    Raises ContractError for an existing/foreign output, DeviceError for hardware faults, Cancelled.
    Views already taken are kept in `<session_dir>.partial` and the next call resumes there.
    """
    total = cfg.sweep.views
    with stage_output(session_dir, "capture_session", overwrite=overwrite, resume=not overwrite,
                      config=to_dict(cfg)) as out:
        def sweep_progress(p: Progress) -> None:
            p.info["views"] = total
            progress(p)

        if empty_plate:
            views = run_sweep(out.path, "empty", cfg.sweep, rotator, camera, progress=sweep_progress, cancel=cancel)
            return {"views": len(views), "complete": False,
                    "message": "empty-plate sweep recorded: place the object on the plate and capture again"}
        views = run_sweep(out.path, "images", cfg.sweep, rotator, camera, progress=sweep_progress, cancel=cancel)
        summary = process_session(out.path, cfg, progress)
        out.finish(config=to_dict(cfg), extra=summary)
        return {"views": len(views), "complete": True, "message": "", **summary}


def _intrinsics(cfg: CaptureConfig, views: list[dict], detections: list, size: tuple[int, int]) -> Intrinsics:
    if cfg.intrinsics == "calibrate":
        # The board only lies on the plate, all views of it are nearly parallel planes: they fix the
        # focal length, not the principal point or distortion.
        return calibrate(detections, size, fix_principal_point=True, fix_aspect_ratio=True, zero_distortion=True)
    if "K" not in views[0]:
        raise CalibrationError("the camera sent no CameraInfo, so its intrinsics are unknown",
                               "calibrate the camera, or set intrinsics: calibrate to use the board in the sweep")
    return Intrinsics(views[0]["K"], list(views[0].get("dist") or []), size[0], size[1])


def process_session(directory: Path, cfg: CaptureConfig, progress: ProgressFn = no_progress) -> dict:
    """Poses, masks, transforms.json, capture.json and contact_sheet.png of the sweeps in `directory`."""
    t0 = time.monotonic()
    views = read_sweep(directory, "images")
    empty = {v["index"]: v for v in read_sweep(directory, "empty")}
    if not views:
        raise ContractError(f"{directory} holds no views", "run the capture sweep first")
    progress(Progress(0.0, "posing", message="detecting the board"))
    images = [read_png(directory / v["file"]) for v in views]
    references = {i: read_png(directory / v["file"]) for i, v in empty.items()}
    height, width = images[0].shape[:2]
    detections = [detect_board(img, cfg.board) for img in images]
    empty_detections = {i: detect_board(img, cfg.board) for i, img in references.items()}
    intr = _intrinsics(cfg, views, detections + list(empty_detections.values()), (width, height))

    def pose(det):
        p = board_pose(det, intr.K, intr.dist) if det is not None else None
        return p if p is not None and p.rms_px <= cfg.max_board_rms_px else None

    poses = [pose(d) for d in detections]
    # A view's own pose: its board pose, or with colmap the board pose structure from motion gives it.
    own = [p.T_cam_board if p else None for p in poses]
    sfm = None
    if cfg.pose_from == "colmap":
        sfm = sfm_poses(directory, [v["file"] for v in views], images, intr, own, cfg.sfm,
                        directory / COLMAP_DIR, progress)
        own = sfm.T_cam_board
    # The empty plate shows the whole board: fit the axis on those views when the sweep has them.
    fit_views = [empty[i] for i in sorted(empty)] if len(empty) >= 3 and sfm is None else views
    fit_poses = ([pose(empty_detections[v["index"]]) for v in fit_views] if fit_views is not views else None)
    fit_angles = [v["angle_rad"] for v in fit_views]  # None: an imported photo of unknown plate angle
    fit = fit_turntable([p.T_cam_board if p else None for p in fit_poses] if fit_poses is not None else own,
                        None if None in fit_angles else fit_angles)
    unplaced = [v.get("source", v["file"]) for v, T in zip(views, own) if T is None and v["angle_rad"] is None]
    if unplaced:
        raise CalibrationError(f"{len(unplaced)} view(s) have no board pose and no plate angle, so nothing can "
                               f"place them: {', '.join(unplaced)}",
                               "give the plate angle of every photo, or leave out those that hide the board")

    records, frames, sheet = [], [], []
    for i, (view, img) in enumerate(zip(views, images)):
        progress(Progress(0.2 + 0.7 * i / len(views), "masking", message=f"view {i + 1}/{len(views)}"))
        source = ("axis" if cfg.pose_from == "axis" and view["angle_rad"] is not None and fit.servo_usable
                  else "servo" if own[i] is None else "colmap" if sfm else "board")
        T_turntable_cam = camera_pose(fit, own[i] if source in ("board", "colmap") else None, view["angle_rad"])
        geometry = ViewGeometry(intr.K, inv_T(T_turntable_cam), cfg.board)
        ref = references.get(view["index"])
        mask = (foreground_mask(img, ref, geometry, cfg.masks) if ref is not None
                else foreground_mask_no_reference(img, geometry, cfg.masks))
        mask_file = f"masks/{view['index']:04d}.png"
        write_mask(directory / mask_file, mask)
        frames.append((view["file"], mask_file, T_turntable_cam))
        records.append({"index": view["index"], "file": view["file"], "mask": mask_file,
                        "angle_rad": view["angle_rad"], "stamp_s": view["stamp_s"],
                        "pose_source": source,
                        "board_corners": len(detections[i]) if detections[i] is not None else 0,
                        "board_rms_px": poses[i].rms_px if poses[i] else None,
                        "mask_pixels": int(mask.sum()), "mask_method": "reference" if ref is not None else "geometry"})
        angle = view["angle_rad"]
        label = f"{math.degrees(angle):.0f} deg" if angle is not None else f"view {view['index']}"
        sheet.append(overlay_view(img, mask, intr, inv_T(T_turntable_cam), label))
    progress(Progress(0.95, "writing"))
    atomic_write_json(directory / "transforms.json", transforms_json(intr.K, intr.dist, width, height, frames))
    sources = [r["pose_source"] for r in records]
    info = {"board": cfg.board.to_dict(), "intrinsics": intr.to_dict(), "intrinsics_source": cfg.intrinsics,
            "turntable_fit": fit.to_dict(), "fit_on": "empty" if fit_views is not views else "images",
            "views": records, "empty_views": len(empty), "process_s": round(time.monotonic() - t0, 2)}
    if sfm is not None:
        info["sfm"] = sfm.to_dict()
    atomic_write_json(directory / "capture.json", info)
    write_png(directory / "contact_sheet.png", contact_sheet(sheet, cols=min(6, len(sheet)), thumb_width=240))
    inl = fit.inliers
    progress(Progress(1.0, "writing"))
    return {"views": len(records), "posed_from_axis": sources.count("axis"), "posed_from_board": sources.count("board"),
            "posed_from_servo": sources.count("servo"), "posed_from_colmap": sources.count("colmap"),
            "fit_rotation_residual_deg": float(np.nanmedian(fit.rotation_residual_deg[inl])),
            "fit_translation_residual_mm": float(np.nanmedian(fit.translation_residual_mm[inl])),
            "focal_px": intr.fx}


def overlay_view(rgb: np.ndarray, mask: np.ndarray, intr: Intrinsics, T_cam_turntable: np.ndarray,
             label: str) -> np.ndarray:
    """A view with its mask outline, the turntable axes (x red, y green, z blue, 5 cm) and a label."""
    out = draw_mask_outline(rgb, mask, (255, 255, 0), 2)
    rvec, _ = cv2.Rodrigues(T_cam_turntable[:3, :3])
    cv2.drawFrameAxes(out, intr.K, intr.dist, rvec, T_cam_turntable[:3, 3], 0.05, 2)
    cv2.putText(out, label, (8, out.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    return out
