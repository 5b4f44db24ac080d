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

A session of two placements (`placements: 2`, for the underside: the reconstruction registers and fuses them)
sweeps the object, then asks for it to be turned over: `capture()` reports the stage `TURN_OVER` and calls its
`turn_over` callback, which returns once the object lies the other way (the capture action waits for its
`capture/continue` service, `n2d capture` for Enter), and sweeps again into `images2/`. The board and the camera
stay where they are, so the one empty-plate sweep is the reference of both. `placement.json` records that the
object was turned over: a capture stopped anywhere resumes in the right placement (asking again only when it
stopped while waiting).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
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

TURN_OVER = "turn_over"
"""The progress (and Capture feedback) stage of a capture of two placements waiting, after the first sweep, for
the object to be turned over; the capture action continues on its `capture/continue` service."""
PLACEMENT_FILE = "placement.json"
"""In an unfinished session: the placement the object stands in now (written once it was turned over)."""


def sweep_name(placement: int) -> str:
    """The sweep (and image folder) of placement `placement` (0-based): images, images2."""
    return "images" if placement == 0 else f"images{placement + 1}"


def turn_over_request(placement: int, placements: int) -> Progress:
    """The progress report that asks for the object to be turned over before placement `placement` (0-based)."""
    return Progress(placement / placements, TURN_OVER, -1.0,
                    f"turn the object over for placement {placement + 1} of {placements} "
                    "(the side it stood on facing the camera), then continue")


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
    placements: int = 1
    """Sweeps of the object: 2 sweeps it, waits for it to be turned over (stage `turn_over`) and sweeps it again, so
    that the reconstruction also sees its underside (1 or 2)."""

    def __post_init__(self):
        if self.placements not in (1, 2):
            raise ValueError(f"placements is 1 or 2, got {self.placements}")
        if self.max_board_rms_px <= 0:
            raise ValueError("max_board_rms_px must be > 0")


def capture(session_dir: str | Path, cfg: CaptureConfig, rotator: Rotator, camera: FrameSource, *,
            empty_plate: bool = False, overwrite: bool = False,
            progress: ProgressFn = no_progress, cancel: threading.Event | None = None,
            turn_over: Callable[[int], None] | None = None) -> dict:
    """Record one sweep into `session_dir` (see the module doc); returns a summary dict.

    With `cfg.placements` 2, `turn_over(placement)` is called (after the `TURN_OVER` progress report) when the
    object must be turned over for `placement` (0-based); it returns once it is, or raises Cancelled.
    Raises ContractError for an existing/foreign output, DeviceError for hardware faults, Cancelled.
    Views already taken are kept in `<session_dir>.partial` and the next call resumes there.
    """
    total = cfg.sweep.views
    with stage_output(session_dir, "capture_session", overwrite=overwrite, resume=not overwrite,
                      config=to_dict(cfg)) as out:
        def sweep_progress(p: Progress, placement: int = 0, of: int = 1) -> None:
            p.info["views"] = total
            progress(replace(p, fraction=(placement + p.fraction) / of))

        if empty_plate:
            views = run_sweep(out.path, "empty", cfg.sweep, rotator, camera, progress=sweep_progress, cancel=cancel)
            return {"views": len(views), "complete": False,
                    "message": "empty-plate sweep recorded: place the object on the plate and capture again"}
        views = []
        for placement in range(cfg.placements):
            if placement > _standing(out.path):
                if turn_over is None:
                    raise ContractError(f"a capture of {cfg.placements} placements needs someone to turn the "
                                        "object over between its sweeps", "capture through the capture action, "
                                        "or n2d capture in a terminal")
                progress(turn_over_request(placement, cfg.placements))
                turn_over(placement)
                atomic_write_json(out.path / PLACEMENT_FILE, {"placement": placement})
            views += run_sweep(out.path, sweep_name(placement), cfg.sweep, rotator, camera,
                               progress=lambda p, placement=placement: sweep_progress(p, placement, cfg.placements),
                               cancel=cancel)
        summary = process_session(out.path, cfg, progress)
        out.finish(config=to_dict(cfg), extra=summary)
        return {"views": len(views), "complete": True, "message": "", **summary}


def _standing(directory: Path) -> int:
    """The placement the object stands in, by the unfinished session in `directory` (0: as first placed)."""
    path = directory / PLACEMENT_FILE
    return int(json.loads(path.read_text())["placement"]) if path.is_file() else 0


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
    """Poses, masks, transforms.json, capture.json and contact_sheet.png of the sweeps in `directory`.

    With `cfg.placements` 2 the second placement's sweep (`images2/`) is processed like the first: posed with the
    empty plate's axis fit, or without one with the first placement's (the turned object may hide the board), and
    masked against the same empty-plate reference; the frames of transforms.json carry their placement index."""
    t0 = time.monotonic()
    sweeps = [read_sweep(directory, sweep_name(p)) for p in range(cfg.placements)]
    empty = {v["index"]: v for v in read_sweep(directory, "empty")}
    missing = [p + 1 for p, views in enumerate(sweeps) if not views]
    if missing:
        which = f" of placement {missing[0]}" if cfg.placements > 1 else ""
        raise ContractError(f"{directory} holds no views{which}", "run the capture sweep first")
    progress(Progress(0.0, "posing", message="detecting the board"))
    images = [[read_png(directory / v["file"]) for v in views] for views in sweeps]
    references = {i: read_png(directory / v["file"]) for i, v in empty.items()}
    height, width = images[0][0].shape[:2]
    detections = [[detect_board(img, cfg.board) for img in placed] for placed in images]
    empty_detections = {i: detect_board(img, cfg.board) for i, img in references.items()}
    intr = _intrinsics(cfg, sweeps[0], [d for placed in detections for d in placed] + list(empty_detections.values()),
                       (width, height))

    def pose(det):
        p = board_pose(det, intr.K, intr.dist) if det is not None else None
        return p if p is not None and p.rms_px <= cfg.max_board_rms_px else None

    # The empty plate shows the whole board: fit the axis on those views when the sweep has them.
    empty_fit = None
    if len(empty) >= 3 and cfg.pose_from != "colmap":
        fit_views = [empty[i] for i in sorted(empty)]
        fit_angles = [v["angle_rad"] for v in fit_views]
        empty_fit = fit_turntable([_T(pose(empty_detections[v["index"]])) for v in fit_views],
                                  None if None in fit_angles else fit_angles)
    total = sum(len(views) for views in sweeps)
    shared_fit = empty_fit
    records, frames, sheet, placements = [], [], [], []
    for p, views in enumerate(sweeps):
        placed = _process_placement(directory, cfg, p, views, images[p], detections[p], pose, intr, references,
                                    shared_fit, "empty" if shared_fit is empty_fit else "placement 1", progress,
                                    (len(records), total))
        # The camera and the plate's axis stay where they are while the object is turned over, and the object
        # lying another way may hide more of the board: the first placement's fit poses the later ones.
        shared_fit = placed["fit"] if shared_fit is None else shared_fit
        records += placed["records"]
        frames += placed["frames"]
        sheet += placed["sheet"]
        placements.append(placed["info"])
    progress(Progress(0.95, "writing"))
    atomic_write_json(directory / "transforms.json",
                      transforms_json(intr.K, intr.dist, width, height, frames,
                                      [r.get("placement", 0) for r in records]))
    sources = [r["pose_source"] for r in records]
    first = placements[0]
    info = {"board": cfg.board.to_dict(), "intrinsics": intr.to_dict(), "intrinsics_source": cfg.intrinsics,
            "turntable_fit": first["turntable_fit"], "fit_on": first["fit_on"],
            "views": records, "empty_views": len(empty), "process_s": round(time.monotonic() - t0, 2)}
    if "sfm" in first:
        info["sfm"] = first["sfm"]
    if cfg.placements > 1:
        info["placements"] = placements
    atomic_write_json(directory / "capture.json", info)
    write_png(directory / "contact_sheet.png", contact_sheet(sheet, cols=min(6, len(sheet)), thumb_width=240))
    progress(Progress(1.0, "writing"))
    summary = {"views": len(records), "posed_from_axis": sources.count("axis"),
               "posed_from_board": sources.count("board"), "posed_from_servo": sources.count("servo"),
               "posed_from_colmap": sources.count("colmap"),
               "fit_rotation_residual_deg": first["fit_rotation_residual_deg"],
               "fit_translation_residual_mm": first["fit_translation_residual_mm"], "focal_px": intr.fx}
    return summary | ({"placements": cfg.placements} if cfg.placements > 1 else {})


def _T(board) -> np.ndarray | None:
    return board.T_cam_board if board else None


def _process_placement(directory: Path, cfg: CaptureConfig, placement: int, views: list[dict], images: list,
                       detections: list, pose, intr: Intrinsics, references: dict, given_fit, given_on: str,
                       progress: ProgressFn,
                       count: tuple[int, int]) -> dict:
    """Poses and masks of one placement's sweep: its records, transforms.json frames, contact-sheet thumbnails and
    its capture.json `placements[]` entry. `given_fit`: the turntable fit to pose it with (None: fit on its own
    views), fitted on `given_on`; `count`: (views of the placements before this one, views in all)."""
    poses = [pose(d) for d in detections]
    # A view's own pose: its board pose, or with colmap the board pose structure from motion gives it.
    own = [_T(p) for p in poses]
    sfm = None
    if cfg.pose_from == "colmap":
        sfm = sfm_poses(directory, [v["file"] for v in views], images, intr, own, cfg.sfm,
                        directory / (COLMAP_DIR if placement == 0 else f"{COLMAP_DIR}{placement + 1}"), progress)
        own = sfm.T_cam_board
    fit = given_fit
    if fit is None:
        angles = [v["angle_rad"] for v in views]  # None: an imported photo of unknown plate angle
        fit = fit_turntable(own, None if None in angles else angles)
    unplaced = [v.get("source", v["file"]) for v, T in zip(views, own) if T is None and v["angle_rad"] is None]
    if unplaced:
        raise CalibrationError(f"{len(unplaced)} view(s) have no board pose and no plate angle, so nothing can "
                               f"place them: {', '.join(unplaced)}",
                               "give the plate angle of every photo, or leave out those that hide the board")
    records, frames, sheet = [], [], []
    mask_dir = "masks" if placement == 0 else f"masks{placement + 1}"
    for i, (view, img) in enumerate(zip(views, images)):
        done, total = count[0] + i, count[1]
        progress(Progress(0.2 + 0.7 * done / total, "masking", message=f"view {done + 1}/{total}"))
        source = ("axis" if cfg.pose_from == "axis" and view["angle_rad"] is not None and fit.servo_usable
                  else "servo" if own[i] is None else "colmap" if sfm else "board")
        T_turntable_cam = camera_pose(fit, own[i] if source in ("board", "colmap") else None, view["angle_rad"])
        geometry = ViewGeometry(intr.K, inv_T(T_turntable_cam), cfg.board)
        ref = references.get(view["index"])
        mask = (foreground_mask(img, ref, geometry, cfg.masks) if ref is not None
                else foreground_mask_no_reference(img, geometry, cfg.masks))
        mask_file = f"{mask_dir}/{view['index']:04d}.png"
        write_mask(directory / mask_file, mask)
        frames.append((view["file"], mask_file, T_turntable_cam))
        records.append({"index": view["index"], "file": view["file"], "mask": mask_file,
                        "angle_rad": view["angle_rad"], "stamp_s": view["stamp_s"],
                        "pose_source": source,
                        "board_corners": len(detections[i]) if detections[i] is not None else 0,
                        "board_rms_px": poses[i].rms_px if poses[i] else None,
                        "mask_pixels": int(mask.sum()), "mask_method": "reference" if ref is not None else "geometry"}
                       | ({"placement": placement} if cfg.placements > 1 else {}))
        angle = view["angle_rad"]
        label = f"{math.degrees(angle):.0f} deg" if angle is not None else f"view {view['index']}"
        if cfg.placements > 1:
            label += f", placement {placement + 1}"
        sheet.append(overlay_view(img, mask, intr, inv_T(T_turntable_cam), label))
    inl = fit.inliers
    info = {"index": placement, "sweep": sweep_name(placement), "views": len(records),
            "turntable_fit": fit.to_dict(),
            "fit_on": "images" if given_fit is None else given_on,
            "fit_rotation_residual_deg": float(np.nanmedian(fit.rotation_residual_deg[inl])),
            "fit_translation_residual_mm": float(np.nanmedian(fit.translation_residual_mm[inl]))}
    if sfm is not None:
        info["sfm"] = sfm.to_dict()
    return {"records": records, "frames": frames, "sheet": sheet, "info": info, "fit": fit}


def overlay_view(rgb: np.ndarray, mask: np.ndarray, intr: Intrinsics, T_cam_turntable: np.ndarray,
             label: str) -> np.ndarray:
    """A view with its mask outline, the turntable axes (x red, y green, z blue, 5 cm) and a label."""
    out = draw_mask_outline(rgb, mask, (255, 255, 0), 2)
    rvec, _ = cv2.Rodrigues(T_cam_turntable[:3, :3])
    cv2.drawFrameAxes(out, intr.K, intr.dist, rvec, T_cam_turntable[:3, 3], 0.05, 2)
    cv2.putText(out, label, (8, out.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    return out
