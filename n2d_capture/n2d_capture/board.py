"""Finding the ChArUco board on the turntable plate in an image, and its pose (the board itself, its frame and
its place on the plate: `n2d_common.formats.board`).

Detection refines every ChArUco corner with cornerSubPix: OpenCV 4.11's detector reports corners
+0.5 px off in x and y (opencv issue 25539), which doubles the pose error on rendered views. Views
with few or nearly collinear corners give wildly wrong poses and are refused.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass
from functools import lru_cache

import cv2
import numpy as np

from n2d_common.errors import N2DError
from n2d_common.formats.board import BoardSpec
from n2d_common.frames import inv_T, make_T


class CalibrationError(N2DError):
    """Board observations cannot determine what was asked: too few views or corners, degenerate motion."""


MIN_CORNERS = 6
"""Fewest ChArUco corners a detection or pose may rest on: 4-5 corners have produced 80-degree-wrong poses."""
MIN_SPREAD = 0.3
"""Narrowest spread (standard deviation) of the corners, in corner spacings: below it they are nearly collinear."""
MAX_REFINE_SHIFT_PX = 1.5
"""A corner that refinement moves further than this from OpenCV's estimate has locked onto another edge
(or is partly hidden) and is dropped."""
SYMMETRY_SMOOTHING_PX = 1.0
"""Gaussian sigma applied before the symmetric corner refinement, pixels."""
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)


@dataclass
class BoardDetection:
    """ChArUco corners found in one image, matched to their positions on the board."""

    ids: np.ndarray
    """(N,) int ChArUco corner ids."""
    corners_px: np.ndarray
    """Nx2 float64 refined pixel positions, OpenCV pixel-centre convention (pixel (0, 0) spans -0.5..0.5)."""
    object_points: np.ndarray
    """Nx3 float64 positions of the same corners in the board frame, metres (z = 0)."""
    image_size: tuple[int, int]
    """(width, height) of the image, pixels."""

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class BoardPose:
    """The board's pose in the camera, fitted to one detection."""

    T_cam_board: np.ndarray
    """4x4 transform from the board frame into the camera frame."""
    rms_px: float
    """Root-mean-square reprojection error of the corners, pixels."""
    n_corners: int
    """Corners the pose was fitted to."""


@lru_cache(maxsize=8)
def _detector(spec_fields: tuple) -> tuple[cv2.aruco.CharucoDetector, np.ndarray]:
    board = BoardSpec(*spec_fields).cv_board()
    return cv2.aruco.CharucoDetector(board), board.getChessboardCorners().astype(np.float64)


def corners_well_spread(object_points: np.ndarray) -> bool:
    """True when board points span at least about two rows and two columns of corners (not collinear).

    The spread is the standard deviation of the points along their narrowest direction, compared with
    the corner spacing (the median distance from a point to its nearest neighbour).
    """
    xy = np.asarray(object_points, dtype=float)[:, :2]
    if len(xy) < MIN_CORNERS:
        return False
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))
    spread = np.linalg.svd(xy - xy.mean(0), compute_uv=False)[-1] / math.sqrt(len(xy))
    return bool(spread >= MIN_SPREAD * spacing)


def _square_side_px(corners_px: np.ndarray, object_points: np.ndarray, square_m: float) -> float:
    """Shortest side of a chessboard square seen at any detected corner, pixels (via the board homography)."""
    H, _ = cv2.findHomography(object_points[:, :2], corners_px, 0)
    if H is None:
        return 12.0
    xy = object_points[None, :, :2]
    at = cv2.perspectiveTransform(xy, H)[0]
    return float(min(np.linalg.norm(cv2.perspectiveTransform(xy + step, H)[0] - at, axis=1).min()
                     for step in ((square_m, 0.0), (0.0, square_m))))


def _symmetric_fraction(spec: BoardSpec) -> float:
    """How far from a corner, in squares, the image stays point-symmetric: up to the markers' inner bits.

    The two markers diagonal to a corner sit centred in their squares and start with a black border
    one bit wide; what lies inside differs between them.
    """
    bits = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary)).markerSize
    return ((spec.square_m - spec.marker_m) / 2 + spec.marker_m / (bits + 2)) / spec.square_m


def _bilinear(patches: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Values of (N, P, P) patches at (N, M, 2) positions (x, y in patch pixels), bilinear, exact.

    cv2.remap would quantise the positions to 1/32 px, which shows as a 0.03 px corner error.
    """
    size = patches.shape[-1]
    x0 = np.clip(np.floor(xy[..., 0]).astype(int), 0, size - 2)
    y0 = np.clip(np.floor(xy[..., 1]).astype(int), 0, size - 2)
    fx, fy = xy[..., 0] - x0, xy[..., 1] - y0
    n = np.arange(len(patches))[:, None]
    top = patches[n, y0, x0] * (1 - fx) + patches[n, y0, x0 + 1] * fx
    bottom = patches[n, y0 + 1, x0] * (1 - fx) + patches[n, y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def refine_corners_symmetric(gray: np.ndarray, corners_px: np.ndarray, radius: int,
                             iterations: int = 15) -> np.ndarray:
    """Move each X-corner to the centre of point symmetry of the image around it (Gauss-Newton).

    Around a chessboard corner q the image is point-symmetric, I(q + d) = I(q - d), and stays so
    under any affine (locally, perspective) view. Minimising sum_d w(d) (I(q + d) - I(q - d))^2
    over a Gaussian-weighted window of `radius` px uses every pixel's intensity, where cornerSubPix
    uses only gradient directions: on rendered views it halves the corner error, and it does not
    lock onto pixel positions. `radius` must keep the window inside the symmetric part around a
    corner (clear of the markers' inner bits). Returns Nx2 float64; corners it cannot refine are NaN.
    """
    margin = radius + 4  # window, the corner's own motion (<= 1.5 px) and central differences
    size = 2 * margin + 1
    # A little smoothing keeps bilinear interpolation from pulling corners towards whole pixels on
    # very sharp images; real optics blur more than this anyway.
    smooth = cv2.GaussianBlur(np.asarray(gray, dtype=np.float32), (0, 0), SYMMETRY_SMOOTHING_PX)
    padded = np.pad(smooth, margin + 1, mode="edge")
    q = np.asarray(corners_px, dtype=np.float64).copy()
    base = np.floor(q).astype(int) - margin  # patch origin in image pixels
    grid = np.arange(size)
    rows = (base[:, 1, None] + margin + 1 + grid)[:, :, None]
    cols = (base[:, 0, None] + margin + 1 + grid)[:, None, :]
    patches = padded[rows, cols].astype(np.float64)
    gx, gy = np.zeros_like(patches), np.zeros_like(patches)
    gx[:, :, 1:-1] = (patches[:, :, 2:] - patches[:, :, :-2]) / 2
    gy[:, 1:-1] = (patches[:, 2:] - patches[:, :-2]) / 2
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    half = (dy > 0) | ((dy == 0) & (dx > 0))  # each pair (d, -d) once
    d = np.stack([dx[half], dy[half]], axis=1).astype(np.float64)
    w = np.exp(-(d ** 2).sum(1) / (2.0 * radius ** 2))
    local = q - base
    for _ in range(iterations):
        plus, minus = local[:, None] + d, local[:, None] - d
        r = _bilinear(patches, plus) - _bilinear(patches, minus)
        J = np.stack([_bilinear(gx, plus) - _bilinear(gx, minus), _bilinear(gy, plus) - _bilinear(gy, minus)], -1)
        JTJ = np.einsum("m,nmi,nmj->nij", w, J, J) + 1e-9 * np.eye(2)
        step = -np.linalg.solve(JTJ, np.einsum("m,nmi,nm->ni", w, J, r)[..., None])[..., 0]
        local += np.clip(step, -0.5, 0.5)
        if np.abs(step).max() < 1e-4:
            break
    out = local + base
    out[np.abs(local - margin).max(axis=1) > margin - radius - 1] = np.nan  # walked out of its patch
    return out


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"detect_board needs a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ValueError(f"detect_board needs an HxW or HxWx3 image, got shape {image.shape}")


def detect_board(image: np.ndarray, spec: BoardSpec) -> BoardDetection | None:
    """The board's ChArUco corners in `image` (HxWx3 RGB or HxW grey, uint8), refined to subpixel.

    Returns None when no board is found, or when fewer than MIN_CORNERS corners remain or they are
    nearly collinear (such views give unreliable poses and calibrations).
    """
    gray = _gray(image)
    detector, chessboard_corners = _detector(astuple(spec))
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    ids = ids.ravel().astype(int)
    raw = corners.reshape(-1, 2).astype(np.float32)
    object_points = chessboard_corners[ids]
    side = _square_side_px(raw.astype(np.float64), object_points, spec.square_m)
    # cornerSubPix removes OpenCV 4.11's +0.5 px bias; its window (a sixth of a square) avoids the markers.
    half = int(np.clip(side // 6, 2, 5))
    coarse = cv2.cornerSubPix(gray, raw.reshape(-1, 1, 2).copy(), (half, half), (-1, -1),
                              _SUBPIX_CRITERIA).reshape(-1, 2).astype(np.float64)
    refined = refine_corners_symmetric(gray, coarse, radius=int(np.clip(_symmetric_fraction(spec) * side, 2, 8)))
    keep = np.linalg.norm(refined - raw, axis=1) <= MAX_REFINE_SHIFT_PX
    if not corners_well_spread(object_points[keep]):
        return None
    return BoardDetection(ids=ids[keep], corners_px=refined[keep],
                          object_points=object_points[keep], image_size=(gray.shape[1], gray.shape[0]))


def board_pose(detection: BoardDetection, K: np.ndarray, dist: np.ndarray | None = None, *,
               max_rms_px: float = 2.0) -> BoardPose | None:
    """The board pose of one detection: IPPE (the better of its two planar solutions), then Levenberg-Marquardt.

    Returns None for a degenerate view: fewer than MIN_CORNERS corners, nearly collinear corners, a
    reprojection error above `max_rms_px`, or a board seen from behind (the camera must be on the
    printed side, where board z is negative).
    """
    if len(detection) < MIN_CORNERS or not corners_well_spread(detection.object_points):
        return None
    K = np.asarray(K, dtype=np.float64)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
    obj, img = detection.object_points, detection.corners_px
    n, rvecs, tvecs, errors = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not n:
        return None
    best = int(np.argmin(np.ravel(errors)))
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[best].copy(), tvecs[best].copy())
    projected = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=1))))
    T = make_T(cv2.Rodrigues(rvec)[0], tvec)
    if rms > max_rms_px or inv_T(T)[2, 3] >= 0:
        return None
    return BoardPose(T_cam_board=T, rms_px=rms, n_corners=len(detection))
