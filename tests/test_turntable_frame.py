"""The turntable frame fitted to board poses: numerically composed sweeps, then rendered ones.

Composed sweeps (no render) put the board off-centre and turned on the plate, offset the servo's
zero, add pose noise, an outlier view and a view without a board. Twelve 640x480 renders of the
simulator (one SimCamera for the module; the bottle, a higher camera than test_board's) check
the fit and the per-view camera poses against the simulator's ground truth.
"""

import json
import math

import cv2
import numpy as np
import pytest

from n2d_capture.board import CalibrationError, board_pose, detect_board
from n2d_capture.turntable_frame import T_cam_base, TurntableFit, camera_pose, fit_turntable
from n2d_common.formats.board import T_plate_board
from n2d_common.frames import inv_T, make_T, rot_z
from n2d_sim import world
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

CFG = SimWorldConfig()
A_SIM = world.T_cam_turntable(CFG)


def _errors(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) between two 4x4 transforms."""
    R = T_a[:3, :3].T @ T_b[:3, :3]
    return (math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))),
            1000 * float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])))


def _sweep(T_plate_board_true: np.ndarray, alphas: np.ndarray, rot_noise_deg=0.05, trans_noise_mm=0.3, seed=0):
    """Board poses of a sweep: camera fixed at the simulator's pose, plate at angles `alphas`, noisy."""
    rng = np.random.default_rng(seed)
    poses = []
    for a in alphas:
        T = A_SIM @ rot_z(a) @ T_plate_board_true
        noise = cv2.Rodrigues(rng.normal(0, math.radians(rot_noise_deg), 3))[0]
        poses.append(make_T(noise @ T[:3, :3], T[:3, 3] + rng.normal(0, trans_noise_mm / 1000, 3)))
    return poses


def test_off_centre_turned_board_with_a_servo_offset_outlier_and_missing_view():
    delta, offset, servo_zero, a0 = math.radians(30), (0.03, -0.02), math.radians(10), math.radians(15)
    board_on_plate = rot_z(delta) @ make_T(np.eye(3), [*offset, 0.0]) @ T_plate_board(CFG.board)
    alphas = a0 + np.radians(np.arange(0, 360, 15.0))
    poses = _sweep(board_on_plate, alphas)
    poses[5] = poses[5] @ make_T(cv2.Rodrigues(np.radians([3.0, 0, 0]))[0], [0.0, 0.01, 0.0])
    poses[7] = None
    fit = fit_turntable(poses, alphas + servo_zero)

    assert fit.reference_view == 0 and fit.inliers.sum() == len(alphas) - 2
    assert not fit.inliers[5] and not fit.inliers[7] and np.isnan(fit.rotation_residual_deg[7])
    assert fit.rotation_residual_deg[5] > 1.0
    # The turntable frame: origin on the axis at the board surface, X along the board's x in view 0.
    rot, trans = _errors(fit.T_cam_turntable, A_SIM @ rot_z(a0 + delta))
    assert rot < 0.1 and trans < 1.0
    rot, trans = _errors(fit.T_board_plate, inv_T(rot_z(-delta) @ board_on_plate))
    assert rot < 0.1 and trans < 1.0
    np.testing.assert_allclose(fit.plate_angles_rad[[0, 1, 2]], alphas[:3] - a0, atol=math.radians(0.1))
    assert fit.servo_offset_rad == pytest.approx(a0 + servo_zero, abs=math.radians(0.05))
    assert fit.servo_scale == pytest.approx(1.0, abs=1e-3) and fit.board_tilt_deg < 0.05
    assert np.abs(fit.servo_residual_deg[fit.inliers]).max() < 0.2

    for a, T in zip(alphas, poses):
        truth = inv_T(A_SIM @ rot_z(a + delta))  # the camera in the plate-attached turntable frame
        rot, trans = _errors(camera_pose(fit, plate_angle_rad=a + servo_zero), truth)
        assert rot < 0.1 and trans < 1.0
        if T is not None and T is not poses[5]:
            rot, trans = _errors(camera_pose(fit, T_cam_board=T), truth)
            assert rot < 0.3 and trans < 3.0


def test_a_tilted_board_is_reported_and_does_not_move_the_axis():
    tilt = cv2.Rodrigues(np.radians([1.0, 0.0, 0.0]))[0]
    board_on_plate = make_T(tilt, [0, 0, 0]) @ T_plate_board(CFG.board)
    fit = fit_turntable(_sweep(board_on_plate, np.radians(np.arange(0, 360, 20.0)), 0.02, 0.1))
    assert fit.board_tilt_deg == pytest.approx(1.0, abs=0.05)
    axis_error = math.degrees(math.acos(np.clip(fit.T_cam_turntable[:3, 2] @ A_SIM[:3, 2], -1, 1)))
    assert axis_error < 0.05 and fit.servo_offset_rad is None


def test_degenerate_sweeps_are_refused_with_a_reason():
    poses = _sweep(T_plate_board(CFG.board), np.radians([0.0, 30.0, 60.0]))
    with pytest.raises(CalibrationError, match=r"at least 3 views.*got 1 \(of 3 views, 2 without a board pose"):
        fit_turntable([poses[0], None, None])
    with pytest.raises(CalibrationError, match="got 0"):
        fit_turntable([])
    small = _sweep(T_plate_board(CFG.board), np.radians([0.0, 2.0, 4.0, 6.0]))
    with pytest.raises(CalibrationError, match=r"spanning 6\.\d degrees") as info:
        fit_turntable(small)
    assert "capture more views" in info.value.hint
    with pytest.raises(ValueError, match="2 plate angles for 3"):
        fit_turntable(poses, [0.0, 1.0])


def test_servo_fallback_refuses_a_servo_that_does_not_follow_the_plate():
    alphas = np.radians(np.arange(0, 360, 30.0))
    poses = _sweep(T_plate_board(CFG.board), alphas)
    reversed_fit = fit_turntable(poses, -alphas)
    assert reversed_fit.servo_scale == pytest.approx(-1.0, abs=1e-3)
    with pytest.raises(CalibrationError, match="gear ratio and direction"):
        camera_pose(reversed_fit, plate_angle_rad=0.5)
    camera_pose(reversed_fit, T_cam_board=poses[3])  # board poses still place the camera
    no_servo = fit_turntable(poses)
    with pytest.raises(CalibrationError, match="no servo angles"):
        camera_pose(no_servo, plate_angle_rad=0.5)
    with pytest.raises(ValueError, match="board pose or its plate angle"):
        camera_pose(no_servo)


def test_the_turntable_base_in_the_camera_turned_by_the_servo_angle_is_the_plate_frame():
    delta, servo_zero, a0 = math.radians(30), math.radians(10), math.radians(15)
    board_on_plate = rot_z(delta) @ make_T(np.eye(3), [0.03, -0.02, 0.0]) @ T_plate_board(CFG.board)
    alphas = a0 + np.radians(np.arange(0, 360, 30.0))
    fit = fit_turntable(_sweep(board_on_plate, alphas), alphas + servo_zero)
    for a in alphas:  # turntable_node's base_frame to plate_frame at the servo's angle a + servo_zero
        rot, trans = _errors(T_cam_base(fit) @ rot_z(a + servo_zero), A_SIM @ rot_z(a + delta))
        assert rot < 0.1 and trans < 1.0
    with pytest.raises(CalibrationError, match="servo"):
        T_cam_base(fit_turntable(_sweep(board_on_plate, alphas)))


def test_fit_round_trips_through_json():
    alphas = np.radians(np.arange(0, 360, 45.0))
    poses = _sweep(T_plate_board(CFG.board), alphas)
    poses[2] = None
    fit = fit_turntable(poses, alphas)
    again = TurntableFit.from_dict(json.loads(json.dumps(fit.to_dict(), allow_nan=False)))
    np.testing.assert_array_equal(again.T_cam_turntable, fit.T_cam_turntable)
    np.testing.assert_array_equal(again.inliers, fit.inliers)
    np.testing.assert_array_equal(again.rotation_residual_deg, fit.rotation_residual_deg)  # NaN where no board
    assert again.servo_offset_rad == fit.servo_offset_rad and again.reference_view == 0


# ---------------------------------------------------------------------------------------------
# Rendered sweep

REFERENCE_ANGLE = 0.3
SERVO_ZERO = 0.2
"""Servo angle minus plate angle: the servo's zero is not the board's."""


@pytest.fixture(scope="module")
def rendered_sweep():
    """Board poses from twelve noisy 640x480 renders, 30 degrees apart from REFERENCE_ANGLE."""
    cfg = SimWorldConfig(object="bottle", camera_elevation_deg=55.0)
    alphas = REFERENCE_ANGLE + np.radians(np.arange(0, 360, 30.0))
    rng = np.random.default_rng(1)
    K = world.K(cfg)
    with SimCamera(cfg) as cam:
        images = [cam.noisy(cam.render(a).rgb, rng) for a in alphas]
    poses = [board_pose(detect_board(image, cfg.board), K) for image in images]
    assert all(p is not None for p in poses)
    return cfg, alphas, [p.T_cam_board for p in poses]


def test_rendered_sweep_recovers_the_turntable_frame(rendered_sweep):
    cfg, alphas, poses = rendered_sweep
    fit = fit_turntable(poses, alphas + SERVO_ZERO)
    assert fit.inliers.all()
    assert np.median(fit.rotation_residual_deg) < 0.1 and np.median(fit.translation_residual_mm) < 1.0
    A = world.T_cam_turntable(cfg)
    axis_error = math.degrees(math.acos(np.clip(fit.T_cam_turntable[:3, 2] @ A[:3, 2], -1, 1)))
    assert axis_error < 0.1
    rot, trans = _errors(fit.T_cam_turntable, A @ world.T_turntable_plate(REFERENCE_ANGLE))
    assert rot < 0.1 and trans < 1.0
    rot, trans = _errors(fit.T_board_plate, inv_T(T_plate_board(cfg.board)))
    assert rot < 0.1 and trans < 1.0
    assert fit.servo_offset_rad == pytest.approx(REFERENCE_ANGLE + SERVO_ZERO, abs=math.radians(0.1))
    assert fit.servo_scale == pytest.approx(1.0, abs=2e-3)

    for a, T in zip(alphas, poses):
        truth = inv_T(A @ world.T_turntable_plate(a))
        rot, trans = _errors(camera_pose(fit, plate_angle_rad=a + SERVO_ZERO), truth)
        assert rot < 0.2 and trans < 2.0
        rot, trans = _errors(camera_pose(fit, T_cam_board=T), truth)
        assert rot < 0.3 and trans < 3.0
