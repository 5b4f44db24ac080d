"""Camera intrinsics: calibration from ChArUco detections, and (de)serialisation for capture.json and CameraInfo.

The camera model is OpenCV's pinhole with plumb-bob distortion (k1, k2, p1, p2, k3), the model ROS
calls `plumb_bob`. Views of the board lying on the turntable all see one physical plane, which fixes
only the focal length (Zhang's method needs planes at different tilts): calibrate them with the
principal point and aspect ratio fixed, or add views of the board held at other tilts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from n2d_capture.board import MIN_CORNERS, BoardDetection, CalibrationError, corners_well_spread
from n2d_common.errors import ConfigError

SINGLE_PLANE_DEG = 5.0
"""Views whose board normals all lie within this angle of their mean see parallel planes (a turntable sweep),
which fix the focal length only."""
_DIST_LENGTHS = (4, 5, 8, 12, 14)
_ZERO_DISTORTION = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST


@dataclass
class Intrinsics:
    """A calibrated pinhole camera: K, distortion, image size and how well the calibration fitted."""

    K: np.ndarray
    """3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels, OpenCV pixel-centre convention."""
    dist: np.ndarray
    """OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]); zeros for an ideal lens."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""
    rms_px: float | None = None
    """Root-mean-square reprojection error of the calibration, pixels (None when not calibrated here)."""
    views: int = 0
    """Views the calibration used (0 when not calibrated here)."""

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if len(self.dist) == 0:
            self.dist = np.zeros(5)
        if len(self.dist) not in _DIST_LENGTHS:
            raise ConfigError(f"distortion has {len(self.dist)} coefficients; OpenCV takes "
                              f"{', '.join(map(str, _DIST_LENGTHS))}")
        if not (self.K[0, 0] > 0 and self.K[1, 1] > 0) or not np.isfinite(self.K).all():
            raise ConfigError(f"camera matrix needs positive finite focal lengths, got fx={self.K[0, 0]}, "
                              f"fy={self.K[1, 1]}", "is the camera calibrated? (CameraInfo K is all zeros when not)")
        if self.width < 1 or self.height < 1:
            raise ConfigError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def distortion_model(self) -> str:
        """ROS's name of the distortion model: plumb_bob (up to 5 coefficients) or rational_polynomial."""
        return "plumb_bob" if len(self.dist) <= 5 else "rational_polynomial"

    def to_dict(self) -> dict:
        """JSON-safe form, e.g. for capture.json."""
        return {"width": self.width, "height": self.height, "K": self.K.tolist(), "dist": self.dist.tolist(),
                "distortion_model": self.distortion_model, "rms_px": self.rms_px, "views": self.views}

    @classmethod
    def from_dict(cls, data: Mapping) -> Intrinsics:
        """The intrinsics written by `to_dict`; a missing or malformed entry raises ConfigError."""
        try:
            return cls(K=np.asarray(data["K"], dtype=float), dist=np.asarray(data.get("dist", []), dtype=float),
                       width=int(data["width"]), height=int(data["height"]),
                       rms_px=None if data.get("rms_px") is None else float(data["rms_px"]),
                       views=int(data.get("views", 0)))
        except KeyError as exc:
            raise ConfigError(f"intrinsics: missing {exc.args[0]!r}", "expected K, dist, width, height") from None
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"intrinsics: {exc}", "expected K as 3x3 numbers, dist as a list") from None

    @classmethod
    def from_camera_info(cls, info: Any) -> Intrinsics:
        """Intrinsics of a ROS CameraInfo message, or of a mapping with the same fields.

        Reads `k` (9 numbers, row-major), `d`, `width`, `height` and `distortion_model`; the ROS 1
        spellings `K` and `D` work too. ROS is not imported: any object with these attributes will do.
        """
        def get(*names: str, default: Any = None) -> Any:
            for name in names:
                value = info.get(name) if isinstance(info, Mapping) else getattr(info, name, None)
                if value is not None:
                    return value
            return default

        model = get("distortion_model", default="") or "plumb_bob"
        if model not in ("plumb_bob", "rational_polynomial"):
            raise ConfigError(f"CameraInfo distortion model {model!r} is not supported",
                              "n2d handles plumb_bob and rational_polynomial (OpenCV's pinhole models)")
        k = get("k", "K")
        if k is None or len(k) != 9:
            raise ConfigError("CameraInfo has no 3x3 camera matrix k", "is the camera driver publishing one?")
        return cls(K=np.asarray(k, dtype=float).reshape(3, 3), dist=np.asarray(get("d", "D", default=[]), float),
                   width=int(get("width", default=0)), height=int(get("height", default=0)))

    def to_camera_info(self) -> dict:
        """The CameraInfo fields (ROS 2 spelling) of this camera, unrectified: r = identity, p = [K | 0]."""
        P = np.hstack([self.K, np.zeros((3, 1))])
        return {"width": self.width, "height": self.height, "distortion_model": self.distortion_model,
                "k": self.K.ravel().tolist(), "d": self.dist.tolist(), "r": np.eye(3).ravel().tolist(),
                "p": P.ravel().tolist()}


def calibrate(detections: Sequence[BoardDetection | None], image_size: tuple[int, int], *,
              fix_principal_point: bool = False, fix_aspect_ratio: bool = False, zero_distortion: bool = False,
              min_views: int = 3) -> Intrinsics:
    """Intrinsics from board detections (None entries are views without a board), via cv2.calibrateCamera.

    Args:
        detections: one per view; views with fewer than MIN_CORNERS or nearly collinear corners are skipped.
        image_size: (width, height) of the images, pixels.
        fix_principal_point: keep (cx, cy) at the image centre ((W-1)/2, (H-1)/2).
        fix_aspect_ratio: square pixels, fx = fy.
        zero_distortion: an ideal lens, all distortion coefficients 0. Otherwise k1, k2, p1, p2 are
            fitted and k3 stays 0 (views of a flat board rarely determine it).
        min_views: fewest usable views.

    Raises:
        CalibrationError: too few usable views, or all views see the board in parallel planes (a
            turntable sweep) while more than the focal length is free.
    """
    width, height = (int(v) for v in image_size)
    usable = [d for d in detections if d is not None and len(d) >= MIN_CORNERS and corners_well_spread(d.object_points)]
    for d in usable:
        if tuple(d.image_size) != (width, height):
            raise CalibrationError(f"a detection comes from a {d.image_size[0]}x{d.image_size[1]} image, "
                                   f"calibrating {width}x{height}", "calibrate views of one camera mode at a time")
    if len(usable) < max(1, min_views):
        missing = sum(d is None for d in detections)
        raise CalibrationError(
            f"calibration needs at least {min_views} views with {MIN_CORNERS}+ well-spread board corners, got "
            f"{len(usable)} of {len(detections)} ({missing} without a board, "
            f"{len(detections) - missing - len(usable)} with too few or collinear corners)",
            "show the whole board at several tilts and distances, filling different parts of the image")

    object_points = [d.object_points.astype(np.float32) for d in usable]
    image_points = [d.corners_px.astype(np.float32).reshape(-1, 1, 2) for d in usable]
    focal_only = cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO | _ZERO_DISTORTION
    if not (fix_principal_point and fix_aspect_ratio):
        # Board tilts from the well-posed focal-only fit: a degenerate full fit can return any tilts.
        rvecs = _calibrate(object_points, image_points, (width, height), focal_only)[3]
        if _normal_spread_deg([cv2.Rodrigues(r)[0][:, 2] for r in rvecs]) < SINGLE_PLANE_DEG:
            raise CalibrationError(
                f"all {len(usable)} views see the board in parallel planes (e.g. lying on the turntable): they "
                "fix the focal length only",
                "pass fix_principal_point=True and fix_aspect_ratio=True, or add views of the board held at other "
                "tilts")
    flags = cv2.CALIB_FIX_K3
    if fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT  # calibrateCamera's initial guess puts it at ((W-1)/2, (H-1)/2)
    if fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO  # the ratio comes from the input matrix: 1
    if zero_distortion:
        flags |= _ZERO_DISTORTION
    rms, K, dist, _, _ = _calibrate(object_points, image_points, (width, height), flags)
    return Intrinsics(K=K, dist=dist.ravel()[:5], width=width, height=height, rms_px=float(rms), views=len(usable))


def _calibrate(object_points, image_points, size, flags):
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    return cv2.calibrateCamera(object_points, image_points, size, np.eye(3), np.zeros(5), flags=flags,
                               criteria=criteria)


def _normal_spread_deg(normals: list[np.ndarray]) -> float:
    """Largest angle between a board normal and the mean normal, degrees."""
    n = np.asarray(normals)
    mean = n.mean(0) / np.linalg.norm(n.mean(0))
    return math.degrees(float(np.arccos(np.clip(n @ mean, -1.0, 1.0)).max()))
