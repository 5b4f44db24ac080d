"""Foreground masks of turntable views: the object against the empty plate, refined by GrabCut.

With a reference (`foreground_mask`), the recommended way: the capture sweeps the plate once without
the object, so each view has an empty-plate image taken at the same plate angle, where board, plate
and surroundings look the same and only the object and its shadows differ.
  1. Seed: pixels that differ from the reference in colour (Lab a*b*), that are brighter, that are
     darker than any shadow, or where an edge of the reference is gone from the view (the object
     hides the board's pattern; a shadow keeps it). A pixel only darker on the plate is a shadow.
  2. Clean-up: opening, closing, large components, holes filled.
  3. GrabCut from the seed decides a band along its outline and the object's parts that look like
     what they hide (a white label over a white square, a dark base over the dark plate). Pixels of the
     band that show the reference's own pattern, only darker, are the plate in shadow and held as
     background: left to GrabCut, a shadow beside a dark object joins it (the price: GrabCut's colour
     model then also holds shadowed white lines, so a white face seen edge-on over them loses a few
     pixels).
  4. Edge: each pixel near the outline is the object when more than half of its colour is the
     object's, I = a F + (1 - a) B in linear light, B the reference there (shadowed and tinted like
     the view just outside, per channel: light bounced off the object tints the plate beside it) and
     F the object colour nearby that explains I best; this is what an exact mask of pixel centres
     holds.

Without a reference (`foreground_mask_no_reference`): the board's printed pattern, predicted from its
pose, marks the visible board as background and the board hidden by the object as object; GrabCut
starts from a cylinder about the axis as wide as the hidden board says. Markedly worse: use it
only when no empty sweep exists.

Geometry (`ViewGeometry`: K, plate pose, board spec) is optional with a reference and limits the
object to the projected cylinder above the plate, so the plate, the board and the turntable below
never become foreground whatever the difference says, and darkening off the plate is not taken
for a shadow. Masks are bool arrays; `write_mask` stores them as 0/255 PNGs.

benchmarks/masks.py measures both (IoU against the simulator's exact masks; benchmarks/RESULTS.md). Without
a reference the masks fail where clutter right behind the object is taken for its top. With one, the
remaining error is a fraction of a pixel along the outline, so IoU falls with the image size; a
reference taken a fraction of a degree off the view's plate angle costs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from n2d_common.formats.board import BoardSpec, T_plate_board, board_image
from n2d_common.frames import rot_z
from n2d_common.images import write_png

REFERENCE_WIDTH_PX = 640
"""Image width the pixel sizes in MaskConfig are given for; they scale with the actual width."""

EXPECTED_IOU = {"reference": 0.98, "no_reference": 0.60}
"""Lowest mean IoU against the exact mask per sample object that tests/test_masks.py accepts (sim,
480x360, sensor noise on view and reference); benchmarks/masks.py measures the values."""


@dataclass
class MaskConfig:
    """Foreground segmentation of one view. Pixel sizes are for a 640-pixel-wide image and scale with
    the image width; colour thresholds are CIE Lab units (L* 0-100)."""

    blur_sigma_px: float = 1.0
    """Gaussian blur of view and reference before they are compared (suppresses sensor noise)."""
    chroma_threshold: float = 9.0
    """Lab a*b* distance from the reference above which a pixel seeds the object (shadows keep the hue)."""
    brighter_threshold: float = 8.0
    """L* rise over the reference above which a pixel seeds the object (a shadow never brightens)."""
    darker_threshold: float = 10.0
    """L* drop below the reference above which a pixel off the plate seeds the object; on the plate
    a drop must also be darker than the darkest shadow (`shadow_ratio_min`)."""
    shadow_ratio_min: float = 0.45
    """Darkest shadow on the plate, as L* of the view over L* of the reference: a pixel darkened
    further is the object."""
    hidden_edge_gradient: float = 8.0
    """L* per pixel (Sobel, after the blur) above which the reference has an edge the view must keep."""
    hidden_edge_ratio: float = 0.4
    """A reference edge the view keeps less than this fraction of is hidden by the object; a shadow
    keeps it (its L* contrast falls about as the cube root of the light)."""
    max_object_height_m: float = 0.35
    """Height of the cylinder the object must stand in, metres above the plate (generous)."""
    object_radius_m: float = 0.0
    """Radius of that cylinder about the turntable axis, metres (0: the plate's radius)."""
    region_margin_px: float = 6.0
    """Margin around the projected cylinder (calibration error, blur)."""
    open_px: float = 2.0
    """Radius of the opening that removes isolated specks from the seed."""
    close_px: float = 8.0
    """Radius of the closing that bridges gaps in the seed (where the object looks like what it hides)."""
    shadow_pattern_ncc: float = 0.9
    """A pixel outside the seed whose neighbourhood correlates with the reference's this well, no brighter and
    with the contrast a shadow leaves (`shadow_ratio_min` to 1.1 of the reference's), shows the plate's own
    pattern in shadow: it is background for GrabCut, whose colour model would otherwise take a shadow next to a
    dark object for the object (0: off)."""
    shadow_pattern_px: float = 5.0
    """Side of the window of that correlation."""
    shadow_pattern_min_std: float = 4.0
    """L* standard deviation the reference must have in that window: plain plate carries no pattern to keep."""
    min_component_fraction: float = 0.05
    """Foreground components smaller than this fraction of the largest are dropped."""
    fill_holes: bool = True
    """Fill holes in the mask (objects without through-holes)."""
    sure_erode_px: float = 2.0
    """The seed's own pixels (before the closing), eroded by this, are the object for GrabCut: a strong
    difference is the object, only its blurred rim is in doubt."""
    band_px: float = 6.0
    """Width of the band on either side of the seed's outline that GrabCut decides."""
    grabcut_iterations: int = 3
    """GrabCut iterations (0: skip GrabCut)."""
    edge_px: float = 3.0
    """Half-width of the band along the outline whose pixels are decided by their colour mix (0: off;
    needs a reference)."""
    edge_min_contrast: float = 0.04
    """Linear-RGB distance between object and background colour below which the mix is too uncertain
    to decide a pixel, and GrabCut's answer stands."""
    edge_smooth_px: float = 0.7
    """Gaussian smoothing of the object shares along the outline before they are cut at one half, image
    pixels (not scaled): the outline is smooth, the shares are noisy."""
    no_reference_iterations: int = 5
    """GrabCut iterations without a reference (it starts from far less)."""
    board_window_px: float = 9.0
    """Without a reference: side of the window in which the view is correlated with the predicted
    board pattern."""
    board_match_ncc: float = 0.6
    """Without a reference: correlation above which a window shows the board itself (background)."""
    board_hidden_ncc: float = 0.2
    """Without a reference: correlation below which a window of patterned board is hidden (object)."""
    no_reference_margin_m: float = 0.01
    """Without a reference: margin added to the object's half-width measured from the hidden board, metres."""

    def __post_init__(self):
        for name in ("chroma_threshold", "brighter_threshold", "darker_threshold", "hidden_edge_gradient",
                     "max_object_height_m"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("shadow_pattern_ncc", "shadow_pattern_px", "shadow_pattern_min_std", "blur_sigma_px",
                     "object_radius_m", "region_margin_px", "open_px", "close_px",
                     "sure_erode_px", "band_px", "grabcut_iterations", "edge_px", "edge_min_contrast", "edge_smooth_px",
                     "no_reference_iterations", "no_reference_margin_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("shadow_ratio_min", "hidden_edge_ratio"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")
        if not 0 <= self.min_component_fraction <= 1:
            raise ValueError(f"min_component_fraction must be in [0, 1], got {self.min_component_fraction}")
        if self.shadow_pattern_ncc > 1:
            raise ValueError(f"shadow_pattern_ncc must be <= 1, got {self.shadow_pattern_ncc}")
        if not -1 < self.board_hidden_ncc < self.board_match_ncc < 1:
            raise ValueError(f"need -1 < board_hidden_ncc < board_match_ncc < 1, got "
                             f"{self.board_hidden_ncc}, {self.board_match_ncc}")
        if self.board_window_px < 3:
            raise ValueError(f"board_window_px must be >= 3, got {self.board_window_px}")


@dataclass
class ViewGeometry:
    """Where the plate is in one view: intrinsics and plate pose (the plate frame turns with the plate)."""

    K: np.ndarray
    """3x3 camera intrinsics (no distortion: undistort the image first)."""
    T_cam_plate: np.ndarray
    """4x4 transform from the plate frame into the camera frame, T_cam_turntable @ Rz(plate angle)."""
    board: BoardSpec
    """The board on the plate; its plate_diameter_m gives the plate."""

    @classmethod
    def from_turntable(cls, K: np.ndarray, T_cam_turntable: np.ndarray, angle_rad: float,
                       board: BoardSpec) -> ViewGeometry:
        """The geometry of the view at plate angle `angle_rad`."""
        return cls(np.asarray(K, float), np.asarray(T_cam_turntable, float) @ rot_z(angle_rad), board)

    def project(self, pts_plate: np.ndarray) -> np.ndarray | None:
        """Nx2 pixel coordinates of Nx3 plate-frame points; None when one lies behind the camera."""
        p = pts_plate @ self.T_cam_plate[:3, :3].T + self.T_cam_plate[:3, 3]
        if (p[:, 2] <= 1e-6).any():
            return None
        uv = p @ self.K.T
        return uv[:, :2] / uv[:, 2:3]


# ---------------------------------------------------------------------------------------------
# Regions from geometry


def _scale(px: float, width: int) -> float:
    return px * width / REFERENCE_WIDTH_PX


def _disk(radius_px: float) -> np.ndarray:
    r = max(1, round(radius_px))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _circle(radius_m: float, z_m: float, n: int = 72) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius_m * np.cos(a), radius_m * np.sin(a), np.full(n, z_m)], axis=1)


def _fill_convex(shape: tuple[int, int], uv: np.ndarray | None) -> np.ndarray:
    """HxW bool: the convex hull of pixel points `uv` (all True when they are unknown)."""
    if uv is None:
        return np.ones(shape, bool)
    out = np.zeros(shape, np.uint8)
    hull = cv2.convexHull(np.round(uv * 16).astype(np.int32))
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def object_region(shape: tuple[int, int], geometry: ViewGeometry, cfg: MaskConfig) -> np.ndarray:
    """HxW bool: where the object can be seen, the projected cylinder standing on the plate, plus margin."""
    radius = cfg.object_radius_m or geometry.board.plate_diameter_m / 2
    uv = geometry.project(np.concatenate([_circle(radius, 0.0), _circle(radius, cfg.max_object_height_m)]))
    region = _fill_convex(shape, uv).astype(np.uint8)
    return cv2.dilate(region, _disk(_scale(cfg.region_margin_px, shape[1]))).astype(bool)


def plate_region(shape: tuple[int, int], geometry: ViewGeometry) -> np.ndarray:
    """HxW bool: the plate's top surface as the camera sees it (object or not)."""
    return _fill_convex(shape, geometry.project(_circle(geometry.board.plate_diameter_m / 2, 0.0)))


def predicted_board(shape: tuple[int, int], geometry: ViewGeometry) -> tuple[np.ndarray, np.ndarray]:
    """The printed sheet as the camera would see it without the object: HxW float32 pattern (0 black,
    1 white paper; no lighting) and HxW bool sheet area."""
    spec = geometry.board
    # Two board pixels per image pixel at the plate centre: fine enough for bilinear sampling.
    uv = geometry.project(np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]]))
    if uv is None:
        return np.zeros(shape, np.float32), np.zeros(shape, bool)
    px_per_m = 2 * max(np.linalg.norm(uv[1] - uv[0]), np.linalg.norm(uv[2] - uv[0])) / 0.01
    squares = board_image(spec, px_per_m)
    s = squares.shape[1] / spec.size_m[0]
    m = round(spec.margin_m * s)
    sheet = cv2.copyMakeBorder(squares, m, m, m, m, cv2.BORDER_CONSTANT, value=255).astype(np.float32) / 255
    # Sheet pixel (u, v) -> board point ((u - m + 0.5) / s, (v - m + 0.5) / s, 0) -> image.
    A = np.array([[1 / s, 0, (0.5 - m) / s], [0, 1 / s, (0.5 - m) / s], [0, 0, 1]])
    T = geometry.T_cam_plate @ T_plate_board(spec)
    H = geometry.K @ T[:3][:, [0, 1, 3]] @ A
    size = (shape[1], shape[0])
    pattern = cv2.warpPerspective(sheet, H, size, flags=cv2.INTER_LINEAR)
    area = cv2.warpPerspective(np.ones_like(sheet), H, size, flags=cv2.INTER_LINEAR) > 0.5
    return pattern, area


# ---------------------------------------------------------------------------------------------
# Image operations


def _lab(rgb: np.ndarray, sigma_px: float) -> np.ndarray:
    x = rgb.astype(np.float32) * np.float32(1 / 255)
    if sigma_px > 0:
        x = cv2.GaussianBlur(x, (0, 0), sigma_px)
    return cv2.cvtColor(x, cv2.COLOR_RGB2Lab)


def _gradient(channel: np.ndarray) -> np.ndarray:
    """Gradient magnitude per pixel (Sobel normalised to a unit step)."""
    return np.hypot(cv2.Sobel(channel, cv2.CV_32F, 1, 0, scale=0.125),
                    cv2.Sobel(channel, cv2.CV_32F, 0, 1, scale=0.125))


def _window_stats(a: np.ndarray, b: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
    """Over k x k windows: the normalised cross-correlation of `a` and `b`, the means of `a` and `b` and their
    standard deviations."""
    def mean(x: np.ndarray) -> np.ndarray:
        return cv2.blur(x, (k, k))

    ma, mb = mean(a), mean(b)
    va = np.maximum(mean(a * a) - ma * ma, 0)
    vb = np.maximum(mean(b * b) - mb * mb, 0)
    return (mean(a * b) - ma * mb) / np.sqrt(va * vb + 1e-8), ma, mb, np.sqrt(va), np.sqrt(vb)


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """`mask` with every background area that does not reach the image border filled."""
    padded = np.pad(mask.astype(np.uint8), 1)
    flood = np.zeros((padded.shape[0] + 2, padded.shape[1] + 2), np.uint8)
    cv2.floodFill(padded, flood, (0, 0), 2)
    return (padded != 2)[1:-1, 1:-1]


def _clean(mask: np.ndarray, cfg: MaskConfig) -> np.ndarray:
    """Keep the large components of `mask` (and fill their holes)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(mask.shape, bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.zeros(n, bool)
    keep[1:] = areas >= cfg.min_component_fraction * areas.max()
    out = keep[labels]
    return _fill_holes(out) if cfg.fill_holes else out


def _check_image(name: str, rgb: np.ndarray) -> None:
    if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3):
        raise ValueError(f"{name} must be an HxWx3 uint8 RGB image, got "
                         f"{getattr(rgb, 'dtype', type(rgb))} {getattr(rgb, 'shape', '')}")


def _check_pair(rgb: np.ndarray, reference: np.ndarray) -> None:
    """A view and its empty-plate reference: both HxWx3 uint8 RGB images of one size."""
    _check_image("rgb", rgb)
    _check_image("reference", reference)
    if rgb.shape != reference.shape:
        raise ValueError(f"the view is {rgb.shape[1]}x{rgb.shape[0]} but the reference is "
                         f"{reference.shape[1]}x{reference.shape[0]}: both must come from the same camera")


def _grabcut(rgb: np.ndarray, labels: np.ndarray, iterations: int) -> np.ndarray:
    """Object pixels after GrabCut from `labels` (cv2.GC_*), run on the box around the undecided ones."""
    fg = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    undecided = (labels == cv2.GC_PR_FGD) | (labels == cv2.GC_PR_BGD)
    if iterations == 0 or not undecided.any():
        return fg
    ys, xs = np.nonzero(undecided)
    pad = round(_scale(16, rgb.shape[1]))  # some sure background around, for its colour model
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, rgb.shape[0])
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, rgb.shape[1])
    crop = labels[y0:y1, x0:x1].copy()
    is_fg = (crop == cv2.GC_FGD) | (crop == cv2.GC_PR_FGD)
    if is_fg.all() or not is_fg.any():
        return fg  # GrabCut needs samples of both
    cv2.setRNGSeed(0)  # GrabCut's k-means draws from OpenCV's RNG: the same input gives the same mask
    cv2.grabCut(np.ascontiguousarray(rgb[y0:y1, x0:x1]), crop, None, np.zeros((1, 65)), np.zeros((1, 65)),
                iterations, cv2.GC_INIT_WITH_MASK)
    out = fg.copy()
    out[y0:y1, x0:x1] = (crop == cv2.GC_FGD) | (crop == cv2.GC_PR_FGD)
    return out


# ---------------------------------------------------------------------------------------------
# With a reference


def difference_seed(rgb: np.ndarray, reference: np.ndarray, geometry: ViewGeometry | None = None,
                    cfg: MaskConfig | None = None) -> np.ndarray:
    """HxW bool: pixels that differ from the empty-plate reference more than a shadow would (raw).

    Args:
        rgb: HxWx3 uint8 view with the object.
        reference: HxWx3 uint8 view of the empty plate at the same plate angle.
        geometry: where the plate is; without it, darkening is taken for a shadow everywhere.
        cfg: thresholds.
    """
    _check_pair(rgb, reference)
    cfg = cfg or MaskConfig()
    sigma = _scale(cfg.blur_sigma_px, rgb.shape[1])
    view, ref = _lab(rgb, sigma), _lab(reference, sigma)
    d = view - ref
    darker = -d[..., 0] > cfg.darker_threshold
    # L* + 5: the ratio of two dark, noisy pixels would fire on noise alone.
    beyond_shadow = darker & (view[..., 0] + 5 < cfg.shadow_ratio_min * (ref[..., 0] + 5))
    if geometry is not None:
        beyond_shadow |= darker & ~plate_region(rgb.shape[:2], geometry)
    ref_edge = _gradient(ref[..., 0])
    hidden_edge = (ref_edge > cfg.hidden_edge_gradient) & (_gradient(view[..., 0]) < cfg.hidden_edge_ratio * ref_edge)
    return ((np.hypot(d[..., 1], d[..., 2]) > cfg.chroma_threshold) | (d[..., 0] > cfg.brighter_threshold)
            | beyond_shadow | hidden_edge)


def shadowed_pattern(rgb: np.ndarray, reference: np.ndarray, cfg: MaskConfig | None = None) -> np.ndarray:
    """HxW bool: pixels whose neighbourhood shows the reference's own pattern, only darker, as a shadow leaves
    it (correlated, no brighter, its contrast scaled by `shadow_ratio_min` to 1.1); all False when
    `shadow_pattern_ncc` is 0. An object rarely repeats the pattern it hides at the same place and contrast."""
    _check_pair(rgb, reference)
    cfg = cfg or MaskConfig()
    if cfg.shadow_pattern_ncc <= 0:
        return np.zeros(rgb.shape[:2], bool)
    width = rgb.shape[1]
    sigma = _scale(cfg.blur_sigma_px, width)
    k = max(3, round(_scale(cfg.shadow_pattern_px, width)) | 1)
    ncc, mv, mr, sv, sr = _window_stats(_lab(rgb, sigma)[..., 0], _lab(reference, sigma)[..., 0], k)
    gain = ncc * sv / np.maximum(sr, 1e-6)  # the least-squares slope of the view on the reference
    return ((ncc > cfg.shadow_pattern_ncc) & (sr > cfg.shadow_pattern_min_std) & (gain > cfg.shadow_ratio_min)
            & (gain < 1.1) & (mv < mr + 2))


_SRGB_TO_LINEAR = np.where((x := np.arange(256) / 255) <= 0.04045, x / 12.92,
                           ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _local_mean(values: np.ndarray, where: np.ndarray) -> np.ndarray:
    """3x3 mean of HxW(xC) `values` over the pixels of bool `where` (noise down, texture kept)."""
    w = where.astype(np.float32)
    den = np.maximum(cv2.blur(w, (3, 3)), 1e-6)
    if values.ndim == 3:
        return cv2.blur(values * w[..., None], (3, 3)) / den[..., None]
    return cv2.blur(values * w, (3, 3)) / den


def _refine_edge(rgb: np.ndarray, reference: np.ndarray, mask: np.ndarray, cfg: MaskConfig) -> np.ndarray:
    """Decide the pixels within `edge_px` of the outline of `mask` by the share of the object in their colour.

    In linear light a pixel on the outline is I = a F + (1 - a) B. B is the reference there, times
    the gain of each colour channel (the view over the reference just outside; the smallest nearby, as a
    contact shadow darkens towards the object and light bounced off it tints the plate in its colour
    towards it). F is taken among the object colours inside within reach, the one that explains I best
    (texture, and the darkening of a curved surface towards its silhouette, make the nearest one a poor
    guess). The pixel is the object when a >= 0.5, after a slight smoothing of a along the outline.
    """
    r = max(2, round(_scale(cfg.edge_px, rgb.shape[1])))
    m8 = mask.astype(np.uint8)
    inner = cv2.erode(m8, _disk(r)).astype(bool)
    outer = ~cv2.dilate(m8, _disk(r)).astype(bool)
    band = ~inner & ~outer
    if not inner.any() or not outer.any():
        return mask
    ys, xs = np.nonzero(band)
    reach = r + 2
    pad = reach + r + 2
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, rgb.shape[0])
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, rgb.shape[1])
    inner, outer, band = inner[y0:y1, x0:x1], outer[y0:y1, x0:x1], band[y0:y1, x0:x1]
    view = _SRGB_TO_LINEAR[rgb[y0:y1, x0:x1]]
    ref = _SRGB_TO_LINEAR[reference[y0:y1, x0:x1]]

    gain = _local_mean(view, outer) / np.maximum(_local_mean(ref, outer), 1e-3)
    gain = cv2.erode(np.where(outer[..., None], gain, np.float32(np.inf)), _disk(r))
    _, nearest = cv2.distanceTransformWithLabels((~outer).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
    gain = gain.reshape(-1, 3)[np.flatnonzero(outer)[nearest - 1]]  # labels number `outer` in raster order

    by, bx = np.nonzero(band)
    oy, ox = np.mgrid[-reach:reach + 1, -reach:reach + 1].reshape(2, -1)
    keep = oy**2 + ox**2 <= reach**2
    cy = np.clip(by[:, None] + oy[keep], 0, band.shape[0] - 1)
    cx = np.clip(bx[:, None] + ox[keep], 0, band.shape[1] - 1)
    F = _local_mean(view, inner)[cy, cx]  # N x candidates x 3
    B = (ref[by, bx] * gain[by, bx])[:, None]
    d = F - B
    contrast2 = (d * d).sum(-1)
    IB = view[by, bx][:, None] - B
    alpha = np.clip((IB * d).sum(-1) / np.maximum(contrast2, 1e-12), 0, 1)
    residual = ((IB - alpha[..., None] * d) ** 2).sum(-1)
    residual[~inner[cy, cx] | (contrast2 < cfg.edge_min_contrast**2)] = np.inf
    best = residual.argmin(axis=1)
    n = np.arange(len(by))
    decided = np.isfinite(residual[n, best])
    field = mask[y0:y1, x0:x1].astype(np.float32)
    field[by[decided], bx[decided]] = alpha[n, best][decided]
    if cfg.edge_smooth_px > 0:
        field = cv2.GaussianBlur(field, (0, 0), cfg.edge_smooth_px)
    out = mask.copy()
    out[by + y0, bx + x0] = field[by, bx] >= 0.5
    return out


def foreground_mask(rgb: np.ndarray, reference: np.ndarray, geometry: ViewGeometry | None = None,
                    cfg: MaskConfig | None = None) -> np.ndarray:
    """HxW bool mask of the object in one view, from the view of the empty plate at the same angle.

    All False when nothing differs from the reference beyond shadows and noise (no object on the
    plate, or the reference is the view itself): callers that need an object check `mask.any()`.

    Args:
        rgb: HxWx3 uint8 RGB view with the object.
        reference: HxWx3 uint8 RGB view of the empty plate at the same plate angle (same camera and
            exposure).
        geometry: where the plate is. Recommended: it limits the object to the projected cylinder
            above the plate and tells shadows on the plate from dark objects in front of the room.
        cfg: thresholds and clean-up.

    Raises:
        ValueError: images of another type or of different sizes.
    """
    cfg = cfg or MaskConfig()
    _check_pair(rgb, reference)
    shape, width = rgb.shape[:2], rgb.shape[1]
    region = object_region(shape, geometry, cfg) if geometry is not None else np.ones(shape, bool)
    raw = difference_seed(rgb, reference, geometry, cfg) & region
    raw = cv2.morphologyEx(raw.astype(np.uint8), cv2.MORPH_OPEN, _disk(_scale(cfg.open_px, width)))
    seed = cv2.morphologyEx(raw, cv2.MORPH_CLOSE, _disk(_scale(cfg.close_px, width))).astype(bool)
    seed = _clean(seed & region, cfg)
    if not seed.any():
        return seed
    band = _disk(_scale(cfg.band_px, width))
    seed8 = seed.astype(np.uint8)
    labels = np.full(shape, cv2.GC_BGD, np.uint8)
    labels[cv2.dilate(seed8, band).astype(bool) & region] = cv2.GC_PR_BGD
    labels[seed] = cv2.GC_PR_FGD
    labels[(cv2.erode(raw, _disk(_scale(cfg.sure_erode_px, width))).astype(bool) & seed)
           | cv2.erode(seed8, band).astype(bool)] = cv2.GC_FGD
    labels[shadowed_pattern(rgb, reference, cfg) & ~seed & ~raw.astype(bool)] = cv2.GC_BGD
    mask = _clean(_grabcut(rgb, labels, cfg.grabcut_iterations) & region, cfg)
    if cfg.edge_px > 0 and mask.any():
        mask = _clean(_refine_edge(rgb, reference, mask, cfg) & region, cfg)
    return mask


# ---------------------------------------------------------------------------------------------
# Without a reference


def _lateral_extent_m(pixels_yx: np.ndarray, geometry: ViewGeometry) -> float:
    """Largest distance from the turntable axis, across the line of sight, of the plate points seen at
    pixels (N x 2, row and column): for the board hidden by an object standing on the plate, the
    object's half-width as the camera sees it."""
    R, t = geometry.T_cam_plate[:3, :3], geometry.T_cam_plate[:3, 3]
    centre = -R.T @ t
    rays = np.column_stack([pixels_yx[:, 1], pixels_yx[:, 0], np.ones(len(pixels_yx))]) @ np.linalg.inv(
        geometry.K).T @ R  # rows: R.T @ K^-1 @ (u, v, 1)
    points = centre + rays * (-centre[2] / rays[:, 2:3])
    across = np.array([centre[1], -centre[0]]) / np.linalg.norm(centre[:2])
    return float(np.percentile(np.abs(points[:, :2] @ across), 98))


def foreground_mask_no_reference(rgb: np.ndarray, geometry: ViewGeometry,
                                 cfg: MaskConfig | None = None) -> np.ndarray:
    """HxW bool mask of the object in one view without an empty-plate reference (lower quality).

    The board's printed pattern, predicted from its pose, is correlated with the view: windows that
    match are visible board (background), patterned windows that do not are board hidden by the
    object (object). How far the hidden board reaches across the line of sight gives the object's
    width, so it stands in a cylinder that wide about the axis (outside it: background). In that
    cylinder the plate around the sheet is probably background and the rest probably the object;
    GrabCut decides. Expect the mean IoU in EXPECTED_IOU["no_reference"]: the object must stand near
    the plate centre on the board, and clutter behind it that looks like it goes wrong.

    Args:
        rgb: HxWx3 uint8 RGB view.
        geometry: where the plate and the board are (required).
        cfg: settings.
    """
    cfg = cfg or MaskConfig()
    _check_image("rgb", rgb)
    shape, width = rgb.shape[:2], rgb.shape[1]
    pattern, sheet = predicted_board(shape, geometry)
    sigma = _scale(cfg.blur_sigma_px, width)
    gray = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255, (0, 0), sigma)
    k = max(3, round(_scale(cfg.board_window_px, width)) | 1)
    ncc, _, _, _, texture = _window_stats(gray, cv2.GaussianBlur(pattern, (0, 0), sigma), k)
    patterned = sheet & (texture > 0.15)
    # A window straddling the object's outline says little about its centre: shrink both by half a window.
    half = _disk(k / 2)
    board = cv2.erode((patterned & (ncc > cfg.board_match_ncc)).astype(np.uint8), half).astype(bool)
    hidden = cv2.erode((patterned & (ncc < cfg.board_hidden_ncc)).astype(np.uint8), half).astype(bool)
    if not hidden.any():
        return np.zeros(shape, bool)
    radius = min(_lateral_extent_m(np.argwhere(hidden), geometry) + cfg.no_reference_margin_m,
                 cfg.object_radius_m or geometry.board.plate_diameter_m / 2)
    region = object_region(shape, geometry, replace(cfg, object_radius_m=radius))
    labels = np.full(shape, cv2.GC_BGD, np.uint8)
    plate = plate_region(shape, geometry)
    labels[region] = cv2.GC_PR_FGD
    labels[region & plate & ~sheet] = cv2.GC_PR_BGD
    labels[region & hidden] = cv2.GC_FGD
    labels[board] = cv2.GC_BGD
    mask = _grabcut(rgb, labels, cfg.no_reference_iterations) & region
    _, components = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    touching = np.unique(components[hidden & mask])
    return _clean(np.isin(components, touching[touching > 0]), cfg)


# ---------------------------------------------------------------------------------------------
# Output


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    """Atomically write a bool mask as a single-channel PNG (0 background, 255 object)."""
    write_png(path, np.asarray(mask, bool).astype(np.uint8) * 255)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
