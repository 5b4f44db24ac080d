"""Region-based pose refinement: align the model's silhouette with the image, and say whether a pose is believable.

The method is the one of Stoiber et al.'s SRT3D (IJCV 2022), on the sparse viewpoint model of `region_model`:

1. Colour statistics. Along a line across the projected contour at each contour point, the pixels inside are
   foreground samples and those outside background samples: two RGB histograms (`bins` per channel) give each
   pixel a foreground posterior P_f.
2. Where the contour is. Each line is cut into segments of `scale` pixels; for each candidate contour position d
   along the line, the segments' posteriors are scored against a smoothed step (foreground inside, background
   outside): a discrete distribution over d, whose mean and variance say where the image puts the contour and
   how sure it is.
3. The pose. A Gauss-Newton step moves the projected contour points along their normals towards those means,
   each weighted by the inverse variance, damped in proportion to each diagonal entry; rotations about the
   object's centre. Coarse-to-fine over `scales`, the lines, histograms and nearest sparse view taken again
   each iteration.

Whether a pose is believable (`believable`) takes two measures: the silhouette score, the mean agreement of the
pixels near the contour with the step at d = 0 (1: every pixel inside is foreground and every pixel outside
background, 0.5: chance), and the texture agreement (`texture_agreement`: local normalised cross-correlation of
the image with the model's albedo rendered at the pose), which a pose turned about an axis the object is not
symmetric about fails even where its silhouette fits. Region statistics cannot tell an object from a background
of its own colours: there a pose can slip, and the texture check is what catches it.
`refine_detection` refines a detector's pose (and, optionally, its cuboid's half turns) and measures both; when
the refined pose fails them it measures the detector's own pose and keeps that one if it passes.

A silhouette holds a pose only through its outline: a box seen face on can slide and tilt with little change of
it. `align_texture` adds the model's texture, render-and-compare: the albedo rendered at the pose, pasted over the
image, its corners (Shi-Tomasi) lifted onto the model through a depth render and followed into the image by
pyramidal Lucas-Kanade flow (both images locally normalised, so the light on each face matters little; a point
flow does not bring back is dropped); the pose the pairs alone give (PnP) and that pose refined again with them
as a reprojection term beside the contour compete with the silhouette's by texture agreement.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from n2d_common.frames import make_T, transform_points
from n2d_common.raster import render_textured
from n2d_common.torch_utils import torch_threads
from n2d_dope.config import FlowConfig, RefineConfig
from n2d_dope.flow import FlowPoints
from n2d_dope.region_model import REGION_MODEL, RegionModel, build_region_model

_ALPHA = 0.43
"""Amplitude of the smoothed step: its foreground probability runs from 0.93 inside to 0.07 outside."""
_SLOPE = 0.5
"""Slope of the smoothed step, in segments."""
MIN_CONTRAST = 2.0
"""Mean local standard deviation of the rendered albedo (grey levels) below which the texture cannot be compared."""


@dataclass
class Refined:
    """The outcome of refining one pose."""

    T_cam_obj: np.ndarray
    """4 x 4 refined pose: object frame -> OpenCV camera frame, metres."""
    score: float
    """Agreement of the image with the pose's silhouette in 0..1 (0.5: chance); see the module docstring."""
    lines: int
    """Contour lines inside the image at the last iteration."""
    texture: float = float("nan")
    """Normalised cross-correlation of the image with the rendered albedo (NaN when not computed)."""


@dataclass
class TexturedModel:
    """What the texture check renders: object-frame mesh (metres), per-corner UVs and the albedo (uint8)."""

    vertices: np.ndarray
    faces: np.ndarray
    face_uvs: np.ndarray
    albedo: np.ndarray


def _rodrigues(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


class _Image:
    """An image's pixels as histogram bin indices, computed where lines sample them."""

    def __init__(self, rgb: np.ndarray, bins: int):
        self.h, self.w = rgb.shape[:2]
        self.rgb = rgb
        self.bins = bins
        self._shift = int(np.log2(256 // bins)) if 256 % bins == 0 and (256 // bins) & (256 // bins - 1) == 0 else -1

    def sample(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bin indices at (..., 2) pixel positions (nearest pixel) and whether each is inside the image."""
        x, y = np.rint(xy[..., 0]).astype(np.int64), np.rint(xy[..., 1]).astype(np.int64)
        ok = (x >= 0) & (x < self.w) & (y >= 0) & (y < self.h)
        px = self.rgb[np.clip(y, 0, self.h - 1), np.clip(x, 0, self.w - 1)].astype(np.int64)
        q = px >> self._shift if self._shift >= 0 else (px * self.bins) // 256
        return (q[..., 0] * self.bins + q[..., 1]) * self.bins + q[..., 2], ok


def _contour(T: np.ndarray, K: np.ndarray, region: RegionModel) -> tuple[np.ndarray, ...]:
    """Camera-frame contour points (P x 3), their pixels (P x 2) and 2D unit normals (P x 2) at pose T."""
    pts, nrm = region.view(T)
    X = transform_points(T, pts)
    uv = X @ K.T
    c = uv[:, :2] / uv[:, 2:3]
    n = (nrm @ T[:3, :3].T)[:, :2]
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    return X, c, n


def _posteriors(img: _Image, c: np.ndarray, n: np.ndarray, length: int, gap: int = 1
                ) -> tuple[np.ndarray, np.ndarray]:
    """Foreground posterior of each bin from the pixels gap..length px inside (foreground) and outside
    (background) the contour along the lines; and whether both histograms had samples."""
    s = np.arange(gap, length + 1, dtype=float)
    fg, ok_f = img.sample(c[:, None] - s[None, :, None] * n[:, None])
    bg, ok_b = img.sample(c[:, None] + s[None, :, None] * n[:, None])
    size = img.bins ** 3
    h_f = np.bincount(fg[ok_f], minlength=size).astype(float)
    h_b = np.bincount(bg[ok_b], minlength=size).astype(float)
    h_f /= max(h_f.sum(), 1.0)
    h_b /= max(h_b.sum(), 1.0)
    eps = 1e-6
    return (h_f + eps) / (h_f + h_b + 2 * eps), np.array(ok_f.any() and ok_b.any())


def _segments(img: _Image, post: np.ndarray, c: np.ndarray, n: np.ndarray, scale: int, count: int):
    """Foreground probability of `count` segments of `scale` pixels along each line, centred on the contour
    (P x count; segment m covers (m - count / 2) * scale .. (m + 1 - count / 2) * scale px along the normal),
    and which lines lie wholly inside the image."""
    offsets = (np.arange(count * scale) - count * scale / 2 + 0.5)
    xy = c[:, None] + offsets[None, :, None] * n[:, None]
    b, ok = img.sample(xy)
    p = np.clip(post[b], 1e-4, 1 - 1e-4).reshape(len(c), count, scale)
    log_f = np.log(p).sum(2)
    log_b = np.log1p(-p).sum(2)
    seg = 1.0 / (1.0 + np.exp(np.clip(log_b - log_f, -50, 50)))
    return seg, ok.all(1)


def _step(x: np.ndarray) -> np.ndarray:
    """Foreground probability of the smoothed step at x segments outside the contour."""
    return 0.5 - _ALPHA * np.tanh(x / (2 * _SLOPE))


def contour_distributions(seg: np.ndarray, J: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance (in segments, outwards positive) of where each line's contour lies, from its 2 (J + W)
    segment probabilities; candidate positions -J..J, each scored over the 2 W segments around it."""
    m = np.arange(2 * W)
    hf = _step(m - W + 0.5)
    idx = np.arange(2 * J + 1)[:, None] + m[None]  # (2J + 1) x 2W segment indices per candidate
    p = seg[:, idx]  # P x (2J + 1) x 2W
    logp = np.log(hf * p + (1 - hf) * (1 - p) + 1e-12).sum(2)
    logp -= logp.max(1, keepdims=True)
    prob = np.exp(logp)
    prob /= prob.sum(1, keepdims=True)
    d = np.arange(-J, J + 1, dtype=float)
    mean = prob @ d
    var = prob @ (d * d) - mean ** 2
    return mean, var


def _jacobian(X: np.ndarray, n: np.ndarray, K: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """P x 6 derivative of each contour point's displacement along its normal (pixels) with respect to a rotation
    about the object's centre (rad, camera axes) and a translation (m, camera axes)."""
    x, y, z = X.T
    fx, fy = K[0, 0], K[1, 1]
    a = np.stack([n[:, 0] * fx / z, n[:, 1] * fy / z, -(n[:, 0] * fx * x + n[:, 1] * fy * y) / z ** 2], 1)
    return np.c_[np.cross(X - centre, a), a]


def _point_terms(points: tuple[np.ndarray, np.ndarray], T: np.ndarray, K: np.ndarray, sigma_px: float,
                 scale: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton matrix and vector (6 x 6, 6) of 2D-3D correspondences (object-frame points, observed pixels)
    at pose T: reprojection residuals weighed by 1 / sigma^2, robustly (Huber at 2 sigma, or a segment at a
    coarse scale)."""
    X = transform_points(T, points[0])
    front = X[:, 2] > 1e-3
    X, observed = X[front], points[1][front]
    uvw = X @ K.T
    residual = observed - uvw[:, :2] / uvw[:, 2:3]
    ones, zeros = np.ones(len(X)), np.zeros(len(X))
    Jac = np.r_[_jacobian(X, np.c_[ones, zeros], K, T[:3, 3]), _jacobian(X, np.c_[zeros, ones], K, T[:3, 3])]
    r = np.r_[residual[:, 0], residual[:, 1]]
    k = max(2.0 * sigma_px, float(scale))
    w = np.tile(np.minimum(1.0, k / (np.linalg.norm(residual, axis=1) + 1e-12)), 2) / sigma_px ** 2
    return (Jac * w[:, None]).T @ Jac, (Jac * w[:, None]).T @ r


def refine_pose(rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, region: RegionModel,
                cfg: RefineConfig | None = None, points: tuple[np.ndarray, np.ndarray] | None = None,
                point_sigma_px: float = 1.0) -> Refined:
    """Refine a pose (object -> camera, metres) of the object in an RGB uint8 image taken with intrinsics K.

    `points`: (object-frame points N x 3, where the image shows them N x 2 pixels), e.g. texture points followed
    by optical flow (`n2d_dope.flow`): a reprojection term beside the contour lines, each point's pixel with
    standard deviation `point_sigma_px`."""
    cfg = cfg or RefineConfig()
    K = np.asarray(K, float)
    img = _Image(rgb, cfg.bins)
    T = np.array(T_cam_obj, float)
    lines = 0
    J, W = cfg.search_segments, cfg.window_segments
    for scale in cfg.scales:
        for _ in range(cfg.iterations):
            X, c, n = _contour(T, K, region)
            if X[:, 2].min() <= 1e-3:
                return Refined(T, 0.0, 0)
            post, ok = _posteriors(img, c, n, cfg.histogram_px, cfg.histogram_gap_px)
            if not ok:
                return Refined(T, 0.0, 0)
            seg, inside = _segments(img, post, c, n, scale, 2 * (J + W))
            lines = int(inside.sum())
            if lines < cfg.min_lines:
                return Refined(T, 0.0, lines)
            mean, var = contour_distributions(seg[inside], J, W)
            mean_px = mean * scale
            var_px = np.maximum(var, cfg.min_variance) * scale ** 2
            Jac = _jacobian(X[inside], n[inside], K, T[:3, 3])
            w = 1.0 / var_px
            H = (Jac * w[:, None]).T @ Jac
            b = (Jac * w[:, None]).T @ mean_px
            if points is not None and len(points[0]):
                H_points, b_points = _point_terms(points, T, K, point_sigma_px, scale)
                H, b = H + H_points, b + b_points
            H[np.diag_indices(6)] += cfg.damping * np.diag(H) + 1e-9
            step = cv2.solve(H, b.reshape(6, 1), flags=cv2.DECOMP_CHOLESKY)[1][:, 0]  # numpy's LAPACK call
            # costs 100x more here when BLAS threads contend
            R = _rodrigues(step[:3])
            T = make_T(R @ T[:3, :3], T[:3, 3] + step[3:])
    score, lines = pose_score(rgb, K, T, region, cfg, img)
    return Refined(T, score, lines)


def pose_score(rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, region: RegionModel,
               cfg: RefineConfig | None = None, img: _Image | None = None) -> tuple[float, int]:
    """How well the image agrees with the silhouette of a pose: the mean over contour lines of the pixels'
    agreement with the step (foreground inside, background outside, `score_px` each side), in 0..1, and the
    number of lines inside the image."""
    cfg = cfg or RefineConfig()
    img = img or _Image(rgb, cfg.bins)
    X, c, n = _contour(np.asarray(T_cam_obj, float), np.asarray(K, float), region)
    if X[:, 2].min() <= 1e-3:
        return 0.0, 0
    post, ok = _posteriors(img, c, n, cfg.histogram_px)
    if not ok:
        return 0.0, 0
    L = cfg.score_px
    offsets = np.arange(2 * L) - L + 0.5
    b, inside = img.sample(c[:, None] + offsets[None, :, None] * n[:, None])
    keep = inside.all(1)
    if keep.sum() < cfg.min_lines:
        return 0.0, int(keep.sum())
    p = post[b[keep]]
    agree = np.where(offsets < 0, p, 1 - p)
    return float(agree.mean()), int(keep.sum())


def _roi(K: np.ndarray, T_cam_obj: np.ndarray, vertices: np.ndarray, shape: tuple, margin_px: int):
    """((x0, y0, x1, y1) inclusive pixel box of the projected model grown by `margin_px` and clipped to the image,
    the intrinsics of that box), or None when the model is behind the camera or covers under 8 px a side."""
    h, w = shape[:2]
    uv = transform_points(T_cam_obj, vertices) @ K.T
    if (uv[:, 2] <= 1e-3).any():
        return None
    uv = uv[:, :2] / uv[:, 2:3]
    x0, y0 = np.maximum(np.floor(uv.min(0)).astype(int) - margin_px, 0)
    x1, y1 = np.minimum(np.ceil(uv.max(0)).astype(int) + margin_px, [w - 1, h - 1])
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    K_roi = K.copy()
    K_roi[0, 2] -= x0
    K_roi[1, 2] -= y0
    return (int(x0), int(y0), int(x1), int(y1)), K_roi


def texture_agreement(rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, model: TexturedModel,
                      window_px: int = 15, margin_px: int = 4) -> float:
    """How well the image's grey levels match the model's albedo rendered at a pose (-1..1; NaN when the model
    covers fewer than 50 pixels or its albedo there is nearly plain): normalised cross-correlation in `window_px`
    windows over the pixels the model covers (eroded by 2 px), averaged with the albedo's local contrast as weight,
    so that the light falling differently on each face changes it little and plain regions count little."""
    K = np.asarray(K, float)
    roi = _roi(K, T_cam_obj, model.vertices, rgb.shape, margin_px)
    if roi is None:
        return float("nan")
    (x0, y0, x1, y1), K_roi = roi
    with torch_threads(1):  # a small render: more threads only contend with the network's
        rendered, mask = render_textured(model.vertices, model.faces, model.face_uvs, model.albedo, K_roi,
                                         T_cam_obj, x1 - x0 + 1, y1 - y0 + 1)
    mask = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(np.float32)
    if mask.sum() < 50:
        return float("nan")
    a = cv2.cvtColor(rendered, cv2.COLOR_RGB2GRAY).astype(np.float32)
    b = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1 + 1, x0:x1 + 1]), cv2.COLOR_RGB2GRAY).astype(np.float32)

    def local_mean(x):  # mean over the window's masked pixels
        return cv2.boxFilter(x * mask, -1, (window_px, window_px), normalize=False) / np.maximum(n, 1.0)

    n = cv2.boxFilter(mask, -1, (window_px, window_px), normalize=False)
    ma, mb = local_mean(a), local_mean(b)
    va, vb = local_mean(a * a) - ma * ma, local_mean(b * b) - mb * mb
    cov = local_mean(a * b) - ma * mb
    ncc = cov / np.sqrt(np.maximum(va * vb, 1e-6))
    weight = mask * np.sqrt(np.maximum(va, 0.0)) * (n >= window_px * window_px / 2)
    if weight.sum() < MIN_CONTRAST * mask.sum():  # a plain model (or a plain side of it): nothing to compare
        return float("nan")
    return float((np.clip(ncc, -1, 1) * weight).sum() / weight.sum())


def cuboid_turns(symmetries: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """The half turns about the object's axes (the bounding box's own symmetries, which DOPE's cuboid keypoints
    cannot tell apart), less those the model is symmetric under; identity first."""
    turns = [np.eye(4)] + [make_T(np.diag(d), np.zeros(3)) for d in ((1, -1, -1), (-1, 1, -1), (-1, -1, 1))]
    symmetries = symmetries or []
    return turns[:1] + [T for T in turns[1:] if not any(np.allclose(T[:3, :3], S[:3, :3], atol=1e-6)
                                                         for S in symmetries)]


ALIGN_FLOW = FlowConfig(points=120, window_px=21, levels=3, fb_px=1.5)
"""Texture points of `align_texture`: more, and followed further than between video frames (a detector's pose
is off by up to a few tens of pixels)."""


def _normalised(gray: np.ndarray, sigma_px: float = 4.0) -> np.ndarray:
    """A grey image with its local mean taken out and its local contrast scaled to one (uint8 about 128): an
    unlit albedo and a lit photo of it look alike."""
    x = gray.astype(np.float32)
    centred = x - cv2.GaussianBlur(x, (0, 0), sigma_px)
    spread = np.sqrt(cv2.GaussianBlur(centred * centred, (0, 0), sigma_px)) + 4.0
    return np.clip(128 + 40 * centred / spread, 0, 255).astype(np.uint8)


def texture_points(rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, model: TexturedModel,
                   flow: FlowPoints) -> tuple[np.ndarray, np.ndarray] | None:
    """(object-frame points N x 3, where the image shows them N x 2 pixels): corners of the albedo rendered at a
    pose, followed into the image (see the module docstring); None when too few are followed."""
    K = np.asarray(K, float)
    roi = _roi(K, T_cam_obj, model.vertices, rgb.shape, 0)
    if roi is None:
        return None
    (x0, y0, x1, y1), K_roi = roi
    with torch_threads(1):  # a small render: more threads only contend with the network's
        rendered, mask = render_textured(model.vertices, model.faces, model.face_uvs, model.albedo, K_roi,
                                         T_cam_obj, x1 - x0 + 1, y1 - y0 + 1)
    if mask.sum() < 50:
        return None
    image = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    pasted = image.copy()
    window = pasted[y0:y1 + 1, x0:x1 + 1]
    window[mask] = cv2.cvtColor(rendered, cv2.COLOR_RGB2GRAY)[mask]
    if flow.select(_normalised(pasted), K, T_cam_obj) < flow.cfg.min_points:
        return None
    return flow.follow(_normalised(image))


def align_texture(rgb: np.ndarray, K: np.ndarray, refined: Refined, region: RegionModel, cfg: RefineConfig,
                  model: TexturedModel, flow: FlowPoints) -> Refined:
    """`refined` after up to `cfg.texture_rounds` rounds of render-and-compare, each kept while the texture agrees
    better with the image (its silhouette score taken again)."""
    best = refined
    if not np.isfinite(best.texture):
        best.texture = texture_agreement(rgb, K, best.T_cam_obj, model)
    if not np.isfinite(best.texture):  # a plain model (or too small a view of it): no texture to align
        return best
    for _ in range(cfg.texture_rounds):
        points = texture_points(rgb, K, best.T_cam_obj, model, flow)
        if points is None:
            break
        moved = []
        fitted = _points_pose(points, K, best.T_cam_obj)
        if fitted is not None:  # the points alone (the outline can pull a face-on pose off them), then both
            moved.append(Refined(fitted, *pose_score(rgb, K, fitted, region, cfg)))
        moved.append(refine_pose(rgb, K, moved[0].T_cam_obj if moved else best.T_cam_obj, region, cfg, points,
                                 flow.cfg.sigma_px))
        for m in moved:
            m.texture = texture_agreement(rgb, K, m.T_cam_obj, model)
        top = max((m for m in moved if m.score >= cfg.min_score and m.texture > best.texture),
                  key=lambda m: m.texture, default=None)
        if top is None:
            break
        best = top
    return best


def _points_pose(points: tuple[np.ndarray, np.ndarray], K: np.ndarray, T_cam_obj: np.ndarray,
                 inlier_px: float = 2.0) -> np.ndarray | None:
    """The pose that projects the object-frame points onto their pixels (RANSAC, started at `T_cam_obj`), or None
    when PnP fails or keeps fewer than half of them."""
    X, px = (np.ascontiguousarray(a, np.float64) for a in points)
    rvec = cv2.Rodrigues(np.asarray(T_cam_obj, float)[:3, :3])[0]
    tvec = np.asarray(T_cam_obj, float)[:3, 3].reshape(3, 1).copy()
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(X, px, np.asarray(K, float), None, rvec, tvec,
                                                     useExtrinsicGuess=True, iterationsCount=100,
                                                     reprojectionError=inlier_px, flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:  # degenerate points (all on one line): no pose from them
        return None
    if not ok or inliers is None or len(inliers) < len(X) / 2 or tvec[2, 0] <= 0:
        return None
    return make_T(cv2.Rodrigues(rvec)[0], tvec[:, 0])


def refine_detection(rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, region: RegionModel,
                     cfg: RefineConfig | None = None, textured: TexturedModel | None = None,
                     turns: list[np.ndarray] | None = None, flow: FlowPoints | None = None) -> Refined:
    """Refine a detector's pose; with a textured model also measure its texture agreement, and with
    `cfg.texture_turns` refine the half turns the detector may confuse it with too (`turns`, default
    `cuboid_turns()`) and keep the one whose texture agrees best with the image; with `cfg.texture_rounds` (and
    the model's `flow` points) align the texture (`align_texture`). With `cfg.keep_start`, a refined pose that is
    not `believable` gives way to the detector's own pose when that one is (aligned as well)."""
    cfg = cfg or RefineConfig()
    T0 = np.asarray(T_cam_obj, float)
    starts = (turns or cuboid_turns()) if cfg.texture_turns and textured is not None else [np.eye(4)]
    candidates = [refine_pose(rgb, K, T0 @ S, region, cfg) for S in starts]
    if textured is None:
        return candidates[0]
    top = max(c.score for c in candidates)
    for c in candidates:
        if c.score >= top - cfg.turn_score_margin:
            c.texture = texture_agreement(rgb, K, c.T_cam_obj, textured)
    textured_ones = [c for c in candidates if np.isfinite(c.texture)]
    best = max(textured_ones, key=lambda c: c.texture) if len(textured_ones) > 1 else candidates[0]
    aligned = cfg.texture_rounds > 0 and flow is not None
    if aligned:
        best = align_texture(rgb, K, best, region, cfg, textured, flow)
    if cfg.keep_start and not believable(best, cfg):
        score, lines = pose_score(rgb, K, T0, region, cfg)
        start = Refined(T0.copy(), score, lines, texture_agreement(rgb, K, T0, textured))
        if aligned:
            start = align_texture(rgb, K, start, region, cfg, textured, flow)
        if believable(start, cfg):
            return start
    return best


def believable(refined: Refined, cfg: RefineConfig) -> bool:
    """Whether a refined pose passes the score thresholds (the texture one only where the texture could be
    compared)."""
    return refined.score >= cfg.min_score and not (np.isfinite(refined.texture) and refined.texture < cfg.min_texture)


class Refiner:
    """Everything refinement needs of one object, loaded once: the sparse viewpoint model (built on first use and
    kept as `region_model.npz` in `cache_dir` when given), the textured mesh and the model's symmetries."""

    def __init__(self, object_dir: str | Path, cfg: RefineConfig | None = None, cache_dir: str | Path | None = None):
        from n2d_common.formats.model import read_textured_model
        from n2d_common.symmetry import from_models_info, symmetric_poses

        self.cfg = cfg or RefineConfig()
        object_dir = Path(object_dir)
        V, F, face_uvs, albedo = read_textured_model(object_dir)
        self.textured = TexturedModel(V, F, face_uvs, albedo)
        self.flow = FlowPoints(V, F, ALIGN_FLOW)
        info = json.loads((object_dir / "models_info.json").read_text())
        entry = next(iter(info.values())) if "diameter" not in info else info
        self.turns = cuboid_turns(symmetric_poses(from_models_info(entry)))
        key = hashlib.sha1(np.ascontiguousarray(V, np.float64).tobytes() + F.astype(np.int64).tobytes()).hexdigest()
        cache = Path(cache_dir) / REGION_MODEL if cache_dir is not None else None
        self.region = None
        if cache is not None and cache.is_file():
            try:
                region = RegionModel.load(cache)
                self.region = region if region.key == key else None
            except (OSError, ValueError, KeyError):
                self.region = None  # an unreadable cache is built again
        if self.region is None:
            self.region = build_region_model(V, F)
            self.region.key = key
            if cache is not None:
                try:
                    self.region.save(cache)
                except OSError:
                    pass  # a read-only model directory: build it again next time

    def __call__(self, rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, cfg: RefineConfig | None = None
                 ) -> Refined:
        """Refine a detector's pose (see `refine_detection`)."""
        return refine_detection(rgb, K, T_cam_obj, self.region, cfg or self.cfg, self.textured, self.turns, self.flow)
