"""The turntable frame from a sweep of board poses: rotation axis, plate centre, and per-view camera poses.

A fixed camera sees the board lying on the plate at servo angles theta_i. The board need not be
centred on the plate, nor aligned with the servo's zero. The model is

    T_cam_board_i = T_cam_turntable @ Rz(phi_i) @ T_plate_board,    phi_ref = 0,

with T_cam_turntable fixed (the plate frame of the reference view, the first view with a good
board pose), T_plate_board = inv(T_board_plate) constant, and phi_i the plate's turn since the
reference view. The turntable frame is: Z the rotation axis, pointing to the board's printed side;
origin where the axis meets the board's top plane; X the board's x axis in the reference view,
projected onto the plane normal to Z. Camera poses are given in the plate-attached frame, in which
the object on the plate stands still.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from n2d_capture.board import CalibrationError
from n2d_common.frames import inv_T, make_T, rot_z

SERVO_SCALE_TOLERANCE = 0.02
"""Largest |servo_scale - 1| for which servo angles stand in for missing board poses."""
MAX_REFITS = 10
"""Rounds of outlier rejection and refitting."""


@dataclass
class TurntableFit:
    """The turntable frame fitted to a sweep of board poses, with per-view residuals (NaN: no board)."""

    T_board_plate: np.ndarray
    """4x4 transform from the plate-attached turntable frame into the board frame (constant)."""
    T_cam_turntable: np.ndarray
    """4x4 transform from the turntable frame into the fixed camera: the plate frame of the reference view."""
    reference_view: int
    """Index of the view that defines X (the first view with a board pose that fits)."""
    plate_angles_rad: np.ndarray
    """(N,) turn of the plate since the reference view, measured from each view's board pose, radians."""
    rotation_residual_deg: np.ndarray
    """(N,) angle between each board pose and the model's (the part not explained by a turn about Z)."""
    translation_residual_mm: np.ndarray
    """(N,) distance between the plate centre seen through each board pose and the fitted origin, mm."""
    inliers: np.ndarray
    """(N,) bool: views used in the fit."""
    servo_offset_rad: float | None
    """Servo angle at which the plate stands as in the reference view (None without servo angles)."""
    servo_scale: float | None
    """Slope of plate turn over servo angle: 1 when the servo reports the plate angle (gear ratio and
    direction right), -1 when it turns the other way."""
    servo_residual_deg: np.ndarray | None
    """(N,) plate angle from the board minus the one from the servo angle, degrees."""
    board_tilt_deg: float
    """Angle between the rotation axis and the board's normal (0 for a flat board on a level plate)."""

    @property
    def servo_usable(self) -> bool:
        """Whether servo angles can place views: the fit had them and the plate followed them 1:1."""
        return self.servo_offset_rad is not None and abs(self.servo_scale - 1.0) <= SERVO_SCALE_TOLERANCE

    def to_dict(self) -> dict:
        """JSON-safe form for capture.json (NaN becomes None)."""
        def plain(a):
            if a is None:
                return None
            return [None if not np.isfinite(v) else float(v) for v in np.ravel(a)] if np.ndim(a) else float(a)
        return {"T_board_plate": self.T_board_plate.tolist(), "T_cam_turntable": self.T_cam_turntable.tolist(),
                "reference_view": self.reference_view, "plate_angles_rad": plain(self.plate_angles_rad),
                "rotation_residual_deg": plain(self.rotation_residual_deg),
                "translation_residual_mm": plain(self.translation_residual_mm),
                "inliers": [bool(v) for v in self.inliers], "servo_offset_rad": plain(self.servo_offset_rad),
                "servo_scale": plain(self.servo_scale), "servo_residual_deg": plain(self.servo_residual_deg),
                "board_tilt_deg": self.board_tilt_deg}

    @classmethod
    def from_dict(cls, data: dict) -> TurntableFit:
        """The fit written by `to_dict`."""
        def arr(key):
            v = data[key]
            return None if v is None else np.array([np.nan if x is None else x for x in v], dtype=float)
        return cls(T_board_plate=np.array(data["T_board_plate"], dtype=float),
                   T_cam_turntable=np.array(data["T_cam_turntable"], dtype=float),
                   reference_view=int(data["reference_view"]), plate_angles_rad=arr("plate_angles_rad"),
                   rotation_residual_deg=arr("rotation_residual_deg"),
                   translation_residual_mm=arr("translation_residual_mm"),
                   inliers=np.array(data["inliers"], dtype=bool), servo_offset_rad=data["servo_offset_rad"],
                   servo_scale=data["servo_scale"], servo_residual_deg=arr("servo_residual_deg"),
                   board_tilt_deg=float(data["board_tilt_deg"]))


def fit_turntable(T_cam_boards: Sequence[np.ndarray | None], plate_angles_rad: Sequence[float] | None = None, *,
                  max_rotation_deg: float = 0.5, max_translation_mm: float = 3.0, min_views: int = 3,
                  min_span_deg: float = 15.0) -> TurntableFit:
    """Fit the turntable frame to board poses of one sweep (None where a view has no board pose).

    Axis: every pair of views (i, j) gives the relative motion M_ij = T_j inv(T_i), a turn by
    phi_ij about the axis. Its rotation satisfies (R + R^T)/2 - cos(phi) I = (1 - cos(phi)) a a^T,
    so the axis a is the top eigenvector of the sum of these matrices over all pairs (pairs with
    larger turns weigh more). Centre: a point c on the axis is fixed by every motion,
    (I - R_ij) c = t_ij, solved by least squares over all pairs with R_ij the fitted turn about a.
    The origin is where the axis meets the board planes (averaged over views); T_board_plate is the
    chordal mean over views of the board pose turned back by its plate angle. Views whose residual
    exceeds max(max_rotation_deg, 5 x median) or max(max_translation_mm, 5 x median) are dropped
    and the fit repeated.

    Servo angles, when given, are checked against the plate angles measured from the board: their
    offset (circular mean) and scale (line fit in sweep order; consecutive views must be less than
    half a turn apart) let `camera_pose` place views without a board pose.

    Raises:
        CalibrationError: fewer than `min_views` good board poses, or the plate turned less than
            `min_span_deg` between them.
    """
    n = len(T_cam_boards)
    if plate_angles_rad is not None and len(plate_angles_rad) != n:
        raise ValueError(f"{len(plate_angles_rad)} plate angles for {n} board poses")
    valid = np.array([T is not None for T in T_cam_boards], dtype=bool)
    Ts = np.zeros((n, 4, 4))
    for i, T in enumerate(T_cam_boards):
        Ts[i] = np.eye(4) if T is None else np.asarray(T, dtype=float).reshape(4, 4)
    inliers = valid.copy()
    for attempt in range(MAX_REFITS + 1):
        _check_enough(Ts, inliers, valid, min_views, min_span_deg)
        model = _fit(Ts, inliers)
        rot, trans = _residuals(model, Ts, valid)
        rot_limit = max(max_rotation_deg, 5 * float(np.median(rot[inliers])))
        trans_limit = max(max_translation_mm, 5 * float(np.median(trans[inliers])))
        keep = valid & (rot <= rot_limit) & (trans <= trans_limit)
        if np.array_equal(keep, inliers) or attempt == MAX_REFITS:
            break
        inliers = keep

    A, B, ref = model
    phi = np.full(n, np.nan)
    phi[valid] = _plate_angles(A, Ts[valid])
    servo_offset = servo_scale = servo_residual = None
    if plate_angles_rad is not None:
        theta = np.asarray(plate_angles_rad, dtype=float)
        d = theta[inliers] - phi[inliers]
        servo_offset = float(theta[ref] + math.atan2(np.sin(d - theta[ref]).mean(), np.cos(d - theta[ref]).mean()))
        order = np.argsort(theta[inliers])
        if np.ptp(theta[inliers]) > 1e-9:
            servo_scale = float(np.polyfit(theta[inliers][order], np.unwrap(phi[inliers][order]), 1)[0])
        else:
            servo_scale = 0.0  # the plate turned while the servo angle stood still
        servo_residual = np.degrees(_wrap(phi - (theta - servo_offset)))
    tilt = math.degrees(math.acos(np.clip(-B[2, 2], -1.0, 1.0)))  # board z (into the board) against -Z
    return TurntableFit(T_board_plate=inv_T(B), T_cam_turntable=A, reference_view=ref, plate_angles_rad=phi,
                        rotation_residual_deg=rot, translation_residual_mm=trans, inliers=inliers,
                        servo_offset_rad=servo_offset, servo_scale=servo_scale, servo_residual_deg=servo_residual,
                        board_tilt_deg=tilt)


def T_cam_base(fit: TurntableFit) -> np.ndarray:
    """4x4 transform from the turntable base into the fixed camera: the plate frame at servo angle 0.

    The plate frame at servo angle theta is then `T_cam_base @ rot_z(theta)` (turntable_node's
    `base_frame` to `plate_frame`). Needs servo angles that follow the plate 1:1 (`servo_usable`); the
    origin is where the axis meets the board's top plane.
    """
    if not fit.servo_usable:
        raise CalibrationError("the turntable fit has no servo angles that follow the plate 1:1 "
                               f"(servo_scale {fit.servo_scale}), so the servo's zero is not placed in the camera",
                               "capture a sweep through turntable_node (or the turntable driver) with the right "
                               "gear_ratio")
    return fit.T_cam_turntable @ rot_z(-fit.servo_offset_rad)


def camera_pose(fit: TurntableFit, T_cam_board: np.ndarray | None = None,
                plate_angle_rad: float | None = None) -> np.ndarray:
    """4x4 pose of the camera in the plate-attached turntable frame (T_turntable_cam) for one view.

    From the view's board pose when given: inv(T_cam_board @ T_board_plate). Otherwise from the
    servo angle: inv(T_cam_turntable @ Rz(theta - servo_offset)).

    Raises:
        CalibrationError: only a servo angle is given, and the fit had no servo angles or found
            that they do not follow the plate (wrong gear ratio or direction).
    """
    if T_cam_board is not None:
        return inv_T(np.asarray(T_cam_board, dtype=float) @ fit.T_board_plate)
    if plate_angle_rad is None:
        raise ValueError("camera_pose needs the view's board pose or its plate angle")
    if fit.servo_offset_rad is None:
        raise CalibrationError("this turntable fit has no servo angles, so views without a board pose cannot "
                               "be placed", "pass the sweep's plate angles to fit_turntable")
    if abs(fit.servo_scale - 1.0) > SERVO_SCALE_TOLERANCE:
        raise CalibrationError(f"the plate turned {fit.servo_scale:.3f} degrees per servo degree in the sweep, "
                               "so servo angles cannot stand in for board poses",
                               "check the turntable's gear ratio and direction")
    return inv_T(fit.T_cam_turntable @ rot_z(plate_angle_rad - fit.servo_offset_rad))


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _rotation_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles of (..., 3, 3) matrices, degrees."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _check_enough(Ts: np.ndarray, inliers: np.ndarray, valid: np.ndarray, min_views: int, min_span_deg: float):
    count = int(inliers.sum())
    span = float(_rotation_deg(Ts[inliers][:, None, :3, :3] @ np.swapaxes(Ts[inliers][None, :, :3, :3], -1, -2))
                 .max()) if count else 0.0
    if count < max(2, min_views) or span < min_span_deg:
        raise CalibrationError(
            f"the turntable fit needs good board poses in at least {min_views} views over {min_span_deg:g}+ "
            f"degrees of plate turn; got {count} (of {len(Ts)} views, {int((~valid).sum())} without a board pose, "
            f"{int((valid & ~inliers).sum())} rejected as outliers) spanning {span:.1f} degrees",
            "capture more views around the turn with the board visible")


def turn_axis(Ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axis, a point on it), in the camera frame, of the turns between (V, 4, 4) poses T_cam_X of a frame X
    turning in front of a fixed camera (see `fit_turntable`); the axis is a unit vector of arbitrary sign."""
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    i, j = np.triu_indices(len(Ts), k=1)
    R_ij = R[j] @ np.swapaxes(R[i], -1, -2)
    t_ij = t[j] - (R_ij @ t[i][..., None])[..., 0]
    cos = (np.trace(R_ij, axis1=-2, axis2=-1) - 1) / 2
    S = ((R_ij + np.swapaxes(R_ij, -1, -2)) / 2 - cos[:, None, None] * np.eye(3)).sum(0)
    axis = np.linalg.eigh(S)[1][:, -1]

    # Fixed point of the pairs' motions, their rotations replaced by the fitted turn about the axis.
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    vee = np.stack([R_ij[:, 2, 1] - R_ij[:, 1, 2], R_ij[:, 0, 2] - R_ij[:, 2, 0], R_ij[:, 1, 0] - R_ij[:, 0, 1]], 1)
    phi = np.arctan2(vee @ axis / 2, cos)
    turn = (np.eye(3) + np.sin(phi)[:, None, None] * skew
            + (1 - np.cos(phi))[:, None, None] * (skew @ skew))
    M = np.eye(3) - turn
    centre = np.linalg.lstsq(np.einsum("pji,pjk->ik", M, M), np.einsum("pji,pj->i", M, t_ij), rcond=None)[0]
    return axis, centre


def _fit(Ts: np.ndarray, inliers: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(T_cam_turntable, T_plate_board, reference view) fitted to the inlier views."""
    idx = np.flatnonzero(inliers)
    R, t = Ts[idx, :3, :3], Ts[idx, :3, 3]
    axis, centre = turn_axis(Ts[idx])
    if axis @ -R[:, :, 2].mean(0) < 0:  # board z points into the board: up is -z
        axis = -axis
    # Where the axis meets each board plane (n . (c + s a - t) = 0), averaged over views.
    normals = R[:, :, 2]
    s = np.einsum("vi,vi->v", normals, t - centre) / (normals @ axis)
    origin = centre + s.mean() * axis

    ref = int(idx[0])
    x = Ts[ref, :3, 0] - (Ts[ref, :3, 0] @ axis) * axis
    x /= np.linalg.norm(x)
    A = make_T(np.stack([x, np.cross(axis, x), axis], axis=1), origin)
    psi = _plate_angles(A, Ts[idx])
    C = np.stack([rot_z(-p) for p in psi]) @ inv_T(A) @ Ts[idx]
    U, _, Vt = np.linalg.svd(C[:, :3, :3].sum(0))
    B = make_T(U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt, C[:, :3, 3].mean(0))
    return A, B, ref


def _plate_angles(A: np.ndarray, Ts: np.ndarray) -> np.ndarray:
    """Azimuth about Z of the board's x axis, turntable frame, in each of the (V, 4, 4) board poses."""
    x = (inv_T(A)[:3, :3] @ Ts[:, :3, 0].T).T
    return np.arctan2(x[:, 1], x[:, 0])


def _residuals(model, Ts: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-view (rotation deg, plate-centre translation mm) residuals against the model (NaN: no pose)."""
    A, B, _ = model
    rot, trans = np.full(len(Ts), np.nan), np.full(len(Ts), np.nan)
    if not valid.any():
        return rot, trans
    V = Ts[valid]
    psi = _plate_angles(A, V)
    predicted = A @ np.stack([rot_z(p) for p in psi]) @ B
    rot[valid] = _rotation_deg(np.swapaxes(predicted[:, :3, :3], -1, -2) @ V[:, :3, :3])
    centres = (V @ inv_T(B))[:, :3, 3]
    trans[valid] = 1000 * np.linalg.norm(centres - A[:3, 3], axis=1)
    return rot, trans
