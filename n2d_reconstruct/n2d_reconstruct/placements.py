"""Sessions of several placements: where each placement's turntable frame lies in the first's, found from the
masks alone, checked, and the views fused into the first placement's frame.

The object is swept, turned over and swept again; each sweep is posed in its own turntable frame. Each
placement's visual hull (the silhouette cones of its views above its own plate) contains the object, so the
right registration T (placement k's frame into the first's) keeps the object inside both hulls, and every mask
ray of every view still meets their intersection. The search: a global one over rotations (a Fibonacci sphere
of up axes times turns about each, plus the 24 axis-aligned turns; the translation from the hulls' centroids)
scored by the hulls' overlap, the best distinct candidates refined by soft overlap, then by the mask rays (each
ray must meet the fused hull); the best is checked view by view (each view's mask rays must meet the fused hull)
and refused, naming the views, when it fails, or when the object was not turned over at all.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, optimize
from scipy.spatial.transform import Rotation

from n2d_common.errors import ContractError
from n2d_common.frames import inv_T, make_T, transform_points
from n2d_reconstruct.data import SessionData, Views
from n2d_reconstruct.hull import HullConfig, VisualHull, search_box
from n2d_reconstruct.mesh import locate, sample_narrow_band

OUTSIDE_M = 0.05
"""Signed distance given to points outside a placement's grid (far outside its hull), metres."""


@dataclass
class PlacementsConfig:
    """Registration of a session's placements to the first (sessions of one placement skip it)."""

    voxel_m: float = 0.0015
    """Spacing of the grids each placement's hull is sampled on for the search, metres."""
    up_directions: int = 200
    """Up axes of a placement tried in the first placement's frame (a Fibonacci sphere), with the 24 axis-aligned
    turns of the object."""
    yaw_steps: int = 36
    """Turns about each up axis tried."""
    search_points: int = 3000
    """Points inside each hull scoring the overlap of the global search."""
    starts: int = 6
    """Best distinct rotations of the global search refined by the hulls' soft overlap."""
    refined: int = 4
    """Of those, the ones best covering the masks refined by the mask rays; where several distinct ones fit the
    masks alike (a shape symmetric under a turn), the photos' agreement on the fused surface decides."""
    distinct_deg: float = 15.0
    """Rotations closer than this count as one start."""
    rays_per_view: int = 150
    """Mask pixels per view whose rays refine and check the registration."""
    hit_tol_px: float = 1.0
    """A mask ray meets the fused hull when it passes within this many pixels of it (at the object's distance)."""
    min_view_coverage: float = 0.95
    """A view disagrees with the registration when fewer of its mask rays than this meet the fused hull."""
    min_turn_deg: float = 30.0
    """A placement whose up axis lies closer than this to the first's does not show the underside: refused."""

    def __post_init__(self):
        if self.voxel_m <= 0 or self.up_directions < 1 or self.yaw_steps < 1 or self.starts < 1:
            raise ValueError("placements: voxel_m must be > 0 and up_directions, yaw_steps, starts >= 1")
        if not 0 < self.min_view_coverage <= 1:
            raise ValueError("placements.min_view_coverage must be in (0, 1]")


@dataclass
class Registration:
    """Where each placement's turntable frame lies in the first's, and how well the views agree with it."""

    T_first: list[np.ndarray]
    """Per placement, the 4x4 pose of its turntable frame in the first placement's (identity for the first)."""
    report: dict = field(default_factory=dict)
    """Scores of the search and the per-view check, for report.json."""

    def plates(self) -> np.ndarray:
        """P x 4 plate planes (n, d) in the first placement's frame: placement k's object stands at n . p + d >= 0."""
        out = []
        for T in self.T_first:
            n = T[:3, 2]
            out.append([*n, -float(n @ T[:3, 3])])
        return np.array(out)


class _Grid:
    """A placement's hull field sampled on a grid (exact near the surface), interpolated trilinearly."""

    def __init__(self, hull: VisualHull, box: np.ndarray, voxel: float):
        self.origin, self.voxel = box[0], voxel
        self.values = sample_narrow_band(hull, box, voxel, 4).astype(np.float32)
        self.inside = self.origin + voxel * np.argwhere(self.values < 0)
        self.volume = len(self.inside) * voxel ** 3

    def __call__(self, points: np.ndarray, order: int = 1) -> np.ndarray:
        idx = ((points - self.origin) / self.voxel).T
        return ndimage.map_coordinates(self.values, idx, order=order, mode="constant", cval=OUTSIDE_M)

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """Whether each point's nearest node is inside (the global search's cheap lookup)."""
        idx = np.rint((points - self.origin) / self.voxel).astype(np.int64)
        ok = ((idx >= 0) & (idx < self.values.shape)).all(-1)
        out = np.zeros(idx.shape[:-1], dtype=bool)
        i = idx[ok]
        out[ok] = self.values[i[:, 0], i[:, 1], i[:, 2]] < 0
        return out


@dataclass
class _Rays:
    """Mask rays of one placement's views, sampled where they pass through or near its own hull."""

    points: np.ndarray
    """M x 3 samples along the rays, the placement's own frame."""
    own: np.ndarray
    """M signed distances to the placement's own hull."""
    starts: np.ndarray
    """Index of each ray's first sample (samples are grouped by ray)."""
    view: np.ndarray
    """The view of each ray."""
    names: list[str]


def _rays(views: Views, grid: _Grid, box: np.ndarray, count: int, rng: np.random.Generator) -> _Rays:
    points, own, starts, view = [], [], [], []
    Kinv = np.linalg.inv(views.K)
    step = grid.voxel
    n = 0
    for v in range(len(views)):
        rows, cols = np.nonzero(views.masks[v])
        pick = rng.choice(len(rows), size=min(count, len(rows)), replace=False)
        d = np.stack([cols[pick], rows[pick], np.ones(len(pick))], 1) @ Kinv.T @ views.T_turntable_cam[v, :3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = views.T_turntable_cam[v, :3, 3]
        # the ray's stretch through the grid's box (slab intersection)
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (box[0] - o) / d, (box[1] - o) / d
        near = np.nanmax(np.minimum(t0, t1), axis=1)
        far = np.nanmin(np.maximum(t0, t1), axis=1)
        ok = far > near
        if not ok.any():
            continue
        d, near, far = d[ok], near[ok], far[ok]
        t = near[:, None] + step * np.arange(int(np.ceil((far - near).max() / step)) + 1)         # R x S
        p = o + t[..., None] * d[:, None]
        s = grid(p.reshape(-1, 3)).reshape(t.shape)
        keep = (s < 3 * step) & (t <= far[:, None])
        for r in np.nonzero(keep.any(1))[0]:
            starts.append(n)
            view.append(v)
            points.append(p[r][keep[r]])
            own.append(s[r][keep[r]])
            n += int(keep[r].sum())
    return _Rays(np.concatenate(points), np.concatenate(own), np.array(starts), np.array(view), views.names)


def _fibonacci(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _candidates(cfg: PlacementsConfig) -> np.ndarray:
    """Rotations (maps a placement's frame into the first's): up axis on a sphere times a turn about it, plus the
    24 axis-aligned ones."""
    ups = _fibonacci(cfg.up_directions)
    z = np.array([0.0, 0.0, 1.0])
    align = []
    for u in ups:
        axis = np.cross(z, u)
        s, c = np.linalg.norm(axis), float(z @ u)
        rv = axis / s * np.arctan2(s, c) if s > 1e-9 else (np.zeros(3) if c > 0 else np.array([np.pi, 0, 0]))
        align.append(Rotation.from_rotvec(rv).as_matrix())
    yaw = Rotation.from_rotvec(np.outer(np.arange(cfg.yaw_steps) * 2 * np.pi / cfg.yaw_steps, [0, 0, 1])).as_matrix()
    R = np.einsum("aij,bjk->abik", np.array(align), yaw).reshape(-1, 3, 3)
    axis_aligned = Rotation.create_group("O").as_matrix()
    return np.concatenate([axis_aligned, R])


def _global_search(g1: _Grid, g2: _Grid, cfg: PlacementsConfig, rng) -> list[tuple[float, np.ndarray]]:
    """The best distinct rotations by hull overlap (intersection over union of the two hulls), as (score, T)."""
    P1 = g1.inside[rng.choice(len(g1.inside), min(cfg.search_points, len(g1.inside)), replace=False)]
    P2 = g2.inside[rng.choice(len(g2.inside), min(cfg.search_points, len(g2.inside)), replace=False)]
    c1, c2 = g1.inside.mean(0), g2.inside.mean(0)
    Rs = _candidates(cfg)
    scores = np.empty(len(Rs))
    for s in range(0, len(Rs), 64):
        R = Rs[s:s + 64]
        t = c1 - R @ c2
        in2 = g2.occupied(np.einsum("mji,mnj->mni", R, P1[None] - t[:, None])).mean(1)   # R^T (p - t)
        in1 = g1.occupied(np.einsum("mij,nj->mni", R, P2) + t[:, None]).mean(1)
        inter = 0.5 * (in2 * g1.volume + in1 * g2.volume)
        scores[s:s + 64] = inter / (g1.volume + g2.volume - inter)
    picked: list[tuple[float, np.ndarray]] = []
    for i in np.argsort(-scores):
        R = Rs[i]
        if all(_angle_deg(R, T[:3, :3]) > cfg.distinct_deg for _, T in picked):
            picked.append((float(scores[i]), make_T(R, c1 - R @ c2)))
        if len(picked) == cfg.starts:
            break
    return picked


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def _perturbed(T0: np.ndarray, x: np.ndarray, centre: np.ndarray, rot_unit: float, t_unit: float) -> np.ndarray:
    """T0 turned by x[:3] * rot_unit (a rotation vector, radians) about `centre` and moved by x[3:] * t_unit."""
    R = Rotation.from_rotvec(x[:3] * rot_unit).as_matrix()
    return make_T(R, centre - R @ centre + x[3:] * t_unit) @ T0


def _soft_overlap(g1: _Grid, g2: _Grid, T0: np.ndarray) -> np.ndarray:
    """T0 refined to the largest soft overlap of the hulls (Nelder-Mead)."""
    tau = 2 * g1.voxel
    band = g1.inside[::max(1, len(g1.inside) // 20000)]
    w1 = 1 / (1 + np.exp(g1(band) / tau))
    centre = band.mean(0)

    def cost(x):
        T = _perturbed(T0, x, centre, 0.02, 0.002)
        w2 = 1 / (1 + np.exp(g2(transform_points(inv_T(T), band)) / tau))
        return -float((w1 * w2).sum())

    res = optimize.minimize(cost, np.zeros(6), method="Nelder-Mead",
                            options={"xatol": 0.02, "fatol": 1e-3, "maxiter": 600})
    return _perturbed(T0, res.x, centre, 0.02, 0.002)


def _ray_misses(rays: _Rays, other: _Grid, T_other_own: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ray, how far (metres) it passes outside the fused hull, and outside its own hull alone."""
    fused = np.maximum(rays.own, other(transform_points(T_other_own, rays.points)))
    return np.minimum.reduceat(fused, rays.starts), np.minimum.reduceat(rays.own, rays.starts)


def _refine_rays(rays1: _Rays, rays2: _Rays, g1: _Grid, g2: _Grid, T0: np.ndarray, slack: float
                 ) -> tuple[np.ndarray, float]:
    """T0 refined so that every mask ray of both placements meets the fused hull (least squares over the rays
    that miss it by more than their own hull does); returns T and the final cost."""
    centre = g1.inside.mean(0)

    def residuals(x):
        T = _perturbed(T0, x, centre, 0.005, 0.0005)
        out = []
        for rays, other, M in ((rays1, g2, inv_T(T)), (rays2, g1, T)):
            fused, own = _ray_misses(rays, other, M)
            out.append(np.maximum(fused + slack, 0) - np.maximum(own + slack, 0))
        return np.concatenate(out) / slack

    res = optimize.least_squares(residuals, np.zeros(6), diff_step=0.2, x_scale=1.0, max_nfev=40, ftol=1e-4)
    return _perturbed(T0, res.x, centre, 0.005, 0.0005), float(res.cost)


def _coverage(rays: _Rays, other: _Grid, T_other_own: np.ndarray, tol: float, views: int) -> np.ndarray:
    """Per view, the fraction of its mask rays (among those its own hull meets) that meet the fused hull."""
    fused, own = _ray_misses(rays, other, T_other_own)
    seen = own <= tol
    hits = np.bincount(rays.view[seen & (fused <= tol)], minlength=views)
    total = np.bincount(rays.view[seen], minlength=views)
    return np.where(total > 0, hits / np.maximum(total, 1), 1.0)


def _colours(views: Views, T_first: np.ndarray, points: np.ndarray, normals: np.ndarray) -> tuple:
    """Per point, the grey level of the views facing it (weighted by how squarely), and the weight; the views'
    poses mapped by T_first into the points' frame. Occlusion is not modelled (the score only breaks ties)."""
    grey, weight = np.zeros(len(points)), np.zeros(len(points))
    poses = T_first @ views.T_turntable_cam
    moved = Views(views.rgb, views.masks, views.K, poses, views.names)
    for v in range(len(views)):
        eye = poses[v, :3, 3] - points
        facing = np.einsum("ij,ij->i", normals, eye / np.linalg.norm(eye, axis=1, keepdims=True))
        uv, _ = moved.project(v, points)
        px, ok = moved.pixels(uv)
        w = np.where(ok, np.clip(facing - 0.5, 0, None), 0.0)
        px = np.where(ok[:, None], px, 0)
        ok &= views.masks[v][px[:, 1], px[:, 0]]
        w = np.where(ok, w, 0.0)
        grey += w * views.rgb[v][px[:, 1], px[:, 0]].mean(1)
        weight += w
    return grey / np.maximum(weight, 1e-9), weight


def _photo_difference(first: Views, other: Views, g1: _Grid, g2: _Grid, T: np.ndarray, rng) -> float:
    """1 - the correlation of the grey levels the two placements' photos give the fused hull's surface under T."""
    idx = np.argwhere(np.abs(g1.values) < 2 * g1.voxel)
    nodes = g1.origin + g1.voxel * idx
    nodes = nodes[rng.choice(len(nodes), min(len(nodes), 40000), replace=False)]
    T_inv = inv_T(T)

    def fused(p):
        return np.maximum(g1(p), g2(transform_points(T_inv, p)))

    points = nodes[np.abs(fused(nodes)) < 0.5 * g1.voxel]
    h = 0.5 * g1.voxel
    normals = np.stack([fused(points + h * e) - fused(points - h * e) for e in np.eye(3)], 1)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    a, wa = _colours(first, np.eye(4), points, normals)
    b, wb = _colours(other, T, points, normals)
    both = (wa > 0.2) & (wb > 0.2)
    if both.sum() < 50:
        return 1.0
    return float(1 - np.corrcoef(a[both], b[both])[0, 1])


def register(views: Views, plate_radius_m: float, cfg: PlacementsConfig, hull_cfg: HullConfig,
             locate_voxel_m: float = 0.004, seed: int = 0) -> Registration:
    """Each placement's turntable frame in the first's, from the masks alone; raises ContractError (naming the
    check that failed and the views that disagree) rather than return a registration the views refute."""
    rng = np.random.default_rng(seed)
    first = views.of_placement(0)
    hull1 = VisualHull(first, hull_cfg)
    box1 = locate(hull1, search_box(plate_radius_m, hull_cfg), locate_voxel_m)
    g1 = _Grid(hull1, box1, cfg.voxel_m)
    rays1 = _rays(first, g1, box1, cfg.rays_per_view, rng)
    tol = cfg.hit_tol_px * views.pixel_m
    T_first, report = [np.eye(4)], {"placements": views.placements, "registered": []}
    for k in range(1, views.placements):
        other = views.of_placement(k)
        hull2 = VisualHull(other, hull_cfg)
        box2 = locate(hull2, search_box(plate_radius_m, hull_cfg), locate_voxel_m)
        g2 = _Grid(hull2, box2, cfg.voxel_m)
        rays2 = _rays(other, g2, box2, cfg.rays_per_view, rng)
        start, timings = time.monotonic(), {}
        timings["search"] = time.monotonic() - start
        starts = []
        for overlap, T in _global_search(g1, g2, cfg, rng):
            T = _soft_overlap(g1, g2, T)
            cover = np.concatenate([_coverage(rays1, g2, inv_T(T), tol, len(first)),
                                    _coverage(rays2, g1, T, tol, len(other))])
            starts.append((float(cover.mean()), overlap, T))
        timings["overlap"] = time.monotonic() - start - timings["search"]
        refined = []
        for _, overlap, T in sorted(starts, key=lambda s: -s[0])[:cfg.refined]:
            T, cost = _refine_rays(rays1, rays2, g1, g2, T, 0.5 * views.pixel_m)
            cover = np.concatenate([_coverage(rays1, g2, inv_T(T), tol, len(first)),
                                    _coverage(rays2, g1, T, tol, len(other))])
            refined.append((T, cost, cover, overlap))
        best = max(refined, key=lambda r: (round(float(r[2].mean()), 3), -r[1]))
        # Shapes symmetric under a turn (a box) fit the masks as well in each symmetric pose: the photos decide.
        fitting: list = []
        for r in sorted((r for r in refined if r[2].mean() >= best[2].mean() - 0.005), key=lambda r: r[1]):
            if all(_angle_deg(r[0][:3, :3], q[0][:3, :3]) > cfg.distinct_deg for q in fitting):
                fitting.append(r)
        photo = None
        if len(fitting) > 1:
            photo = [_photo_difference(first, other, g1, g2, r[0], rng) for r in fitting]
            best = fitting[int(np.argmin(photo))]
        timings["rays"] = time.monotonic() - start - timings["search"] - timings["overlap"]
        T, cost, cover, overlap = best
        names = first.names + other.names
        turn = float(np.degrees(np.arccos(np.clip(T[2, 2], -1, 1))))
        entry = {"placement": k, "T_first_placement": np.round(T, 9).tolist(), "turned_deg": round(turn, 2),
                 "hull_overlap": round(overlap, 4), "ray_cost": round(cost, 4),
                 "min_view_coverage": round(float(cover.min()), 4), "mean_view_coverage": round(float(cover.mean()), 4),
                 "fit_by_shape": max(1, len(fitting)),
                 "photo_difference": None if photo is None else [round(float(x), 4) for x in photo],
                 "timings_s": {k: round(v, 2) for k, v in timings.items()}}
        report["registered"].append(entry)
        bad = [(names[i], cover[i]) for i in np.argsort(cover) if cover[i] < cfg.min_view_coverage]
        if bad:
            listed = ", ".join(f"{n} {100 * c:.0f} %" for n, c in bad[:8]) + (" .." if len(bad) > 8 else "")
            raise ContractError(
                f"placement {k + 1} does not fit placement 1 (silhouette check): {len(bad)} of {len(names)} views "
                f"disagree with the best registration, their masks not covered by the fused hull ({listed}; "
                f"at least {100 * cfg.min_view_coverage:.0f} % needed); nothing is fused",
                "is the same object on the plate in both placements, and did it stay still during each sweep? "
                "re-capture the placement, or reconstruct each placement on its own")
        if turn < cfg.min_turn_deg:
            raise ContractError(
                f"placement {k + 1} stands as placement 1 did (turn check): its up axis is {turn:.1f} degrees from "
                f"placement 1's (at least {cfg.min_turn_deg:g} needed), so the underside stays unseen; nothing is "
                "fused", "turn the object over (on its side or upside down) before sweeping the second placement")
        T_first.append(T)
    return Registration(T_first, report)


def fuse(data: SessionData, registration: Registration) -> SessionData:
    """The session with every view posed in the first placement's turntable frame and one plate per placement."""
    def moved(views: Views) -> Views:
        T = np.asarray(registration.T_first)[views.placement] @ views.T_turntable_cam
        return Views(views.rgb, views.masks, views.K, T, views.names, views.truth, views.placement)

    return SessionData(data.directory, moved(data.train), moved(data.heldout), data.plate_radius_m,
                       registration.plates(), registration.report)
