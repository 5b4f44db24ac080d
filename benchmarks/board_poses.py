"""Benchmark of the ChArUco pipeline on simulated turntable views: detection, poses, calibration, turntable fit.

    python benchmarks/board_poses.py [--views 36] [--set object=bottle --set samples=8]

Renders `--views` noisy views around one turn (640x480 by default) and prints: corners per view,
board pose error against the simulator's ground truth, the focal length calibrated from the
sweep (principal point and aspect ratio fixed, no distortion: one plane fixes only the focal
length), the turntable fit's residuals and frame error, the error of the per-view camera poses
from the board and from the servo angle, and the time per detection and per pose.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from n2d_capture.board import board_pose, detect_board
from n2d_capture.calibration import calibrate
from n2d_capture.turntable_frame import camera_pose, fit_turntable
from n2d_common.config import apply_overrides, from_dict, to_dict
from n2d_common.formats.board import T_plate_board
from n2d_common.frames import inv_T
from n2d_sim import world
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig
from table import print_table


def _errors(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) between two 4x4 transforms."""
    R = T_a[:3, :3].T @ T_b[:3, :3]
    return (math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))),
            1000 * float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])))


def _median_max(values, unit: str, digits: int = 3) -> str:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return f"{np.median(v):.{digits}f} / {v.max():.{digits}f} {unit}" if len(v) else "-"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=36, help="views around one turn")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="SimWorldConfig override, e.g. object=bottle (repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="sensor noise seed")
    args = parser.parse_args(argv)
    cfg = from_dict(SimWorldConfig, apply_overrides(to_dict(SimWorldConfig()), args.overrides))
    K = world.K(cfg)
    angles = [2 * math.pi * i / args.views for i in range(args.views)]

    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    with SimCamera(cfg) as cam:
        images = [cam.noisy(cam.render(a).rgb, rng) for a in angles]
    render_s = time.perf_counter() - t0

    detections, poses, detect_s, pose_s = [], [], [], []
    for image in images:
        t0 = time.perf_counter()
        det = detect_board(image, cfg.board)
        detect_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        pose = board_pose(det, K) if det is not None else None
        pose_s.append(time.perf_counter() - t0)
        detections.append(det)
        poses.append(pose)
    counts = [len(d) if d is not None else 0 for d in detections]
    pose_err = np.array([_errors(world.T_cam_board(cfg, a), p.T_cam_board) if p else (np.nan, np.nan)
                         for a, p in zip(angles, poses)])

    intr = calibrate(detections, (cfg.width, cfg.height), fix_principal_point=True, fix_aspect_ratio=True,
                     zero_distortion=True)
    fit = fit_turntable([p.T_cam_board if p else None for p in poses], angles)
    A = world.T_cam_turntable(cfg)
    axis_deg = math.degrees(math.acos(np.clip(fit.T_cam_turntable[:3, 2] @ A[:3, 2], -1.0, 1.0)))
    frame_err = _errors(fit.T_cam_turntable, A @ world.T_turntable_plate(angles[fit.reference_view]))
    board_err = _errors(fit.T_board_plate, inv_T(T_plate_board(cfg.board)))
    truth = [inv_T(A @ world.T_turntable_plate(a)) for a in angles]
    via_board = np.array([_errors(camera_pose(fit, T_cam_board=p.T_cam_board), t) if p else (np.nan, np.nan)
                          for p, t in zip(poses, truth)])
    via_servo = np.array([_errors(camera_pose(fit, plate_angle_rad=a), t) for a, t in zip(angles, truth)])

    rows = [
        ("views, resolution, object", f"{args.views}, {cfg.width}x{cfg.height}, {cfg.object}"),
        ("samples / denoiser", f"{cfg.samples} / {cfg.denoiser}"),
        ("render (start + all views)", f"{render_s:.1f} s"),
        ("views with a board", f"{sum(d is not None for d in detections)} / {args.views}"),
        ("corners per view, min / median", f"{min(counts)} / {np.median(counts):.0f}"),
        ("board pose rotation error, median / max", _median_max(pose_err[:, 0], "deg")),
        ("board pose translation error, median / max", _median_max(pose_err[:, 1], "mm", 2)),
        ("pose reprojection rms, median / max", _median_max([p.rms_px for p in poses if p], "px")),
        ("calibrated focal (pp, aspect fixed) error", f"{100 * (intr.fx / cfg.focal_px - 1):+.3f} % "
                                                      f"(rms {intr.rms_px:.3f} px)"),
        ("turntable fit inliers", f"{int(fit.inliers.sum())} / {args.views}"),
        ("fit residual rotation, median / max", _median_max(fit.rotation_residual_deg, "deg")),
        ("fit residual translation, median / max", _median_max(fit.translation_residual_mm, "mm", 2)),
        ("axis error", f"{axis_deg:.3f} deg"),
        ("T_cam_turntable error", f"{frame_err[0]:.3f} deg, {frame_err[1]:.2f} mm"),
        ("T_board_plate error", f"{board_err[0]:.3f} deg, {board_err[1]:.2f} mm"),
        ("servo offset / scale", f"{math.degrees(fit.servo_offset_rad):+.3f} deg / {fit.servo_scale:.5f}"),
        ("camera pose via board, rotation median / max", _median_max(via_board[:, 0], "deg")),
        ("camera pose via board, position median / max", _median_max(via_board[:, 1], "mm", 2)),
        ("camera pose via servo, rotation median / max", _median_max(via_servo[:, 0], "deg")),
        ("camera pose via servo, position median / max", _median_max(via_servo[:, 1], "mm", 2)),
        ("detection time, median", f"{1000 * np.median(detect_s):.1f} ms"),
        ("pose time, median", f"{1000 * np.median(pose_s):.1f} ms"),
    ]
    print_table("ChArUco board benchmark (errors against the simulator's ground truth)", rows)


if __name__ == "__main__":
    main()
