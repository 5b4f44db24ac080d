"""Symmetries of an object model, found from its mesh (and texture), in BOP's models_info.json format.

A symmetry is a proper rigid motion S (4 x 4, rotation with det +1 and translation; BOP uses no reflections)
that maps the model's surface onto itself, and its texture onto itself where a texture is given. BOP lists
them per object in models_info.json:

- `symmetries_discrete`: a list of row-major 4 x 4 matrices (16 numbers), translation in millimetres, the
  identity left out;
- `symmetries_continuous`: a list of {"axis": [x, y, z], "offset": [x, y, z]}: the model is symmetric under
  every rotation about the line through `offset` (a point, millimetres) along `axis`. The discrete rotations
  about that line are implied and not listed; a cylinder (a can) lists its axis here and the half turn that
  swaps its two caps under `symmetries_discrete`.

Everything here is in metres and radians; only `to_models_info` / `from_models_info` speak millimetres.

Detection (`find_symmetries`). Every symmetry fixes the surface's area centroid c, so the candidates are
rotations about axes through c. Distinct principal moments of the surface allow only half turns about the
principal axes; two equal moments (a body of revolution, a square prism) put any higher or continuous turn
on the third principal axis and half turns perpendicular to it; three equal moments (a cube) leave the
axes open, and the directions from c to the convex hull's vertices and edge midpoints and the large
hull-facet and mesh-face normal clusters are tried too. Each axis is tried with turns of 2 pi / n
(n = 2 .. `max_order`); a possible axis of revolution first with turns by a few angles that are no simple
fraction of a turn. A candidate is scored on random area-weighted surface samples p_i: the distance of
S p_i and S^-1 p_i to the surface (exact, to the nearest triangle), the angle between the turned normal at
p_i and the normal where its image lands (face normals averaged over a patch of about 3 % of the diameter,
so that a reconstruction's noisy small triangles do not count), and with a texture the colour difference
between p_i and the surface point nearest its image (bilinear at its UV). Its score is the largest of

- mean distance / (`tolerance` * diameter),
- 99th percentile of the distances / (`tail_tolerance` * diameter): a handle, a spout, a small part the
  mean would average away,
- fraction of samples whose normal turned by more than `normal_tolerance_deg` / `normal_fraction`:
  faceted, nearly round bodies (a hexagonal prism) stay within a few % of the diameter of themselves
  under turns that are no symmetry, but their faces turn away,
- fraction of samples whose colour differs by more than `color_tolerance` / `color_fraction`.

A score <= 1 is a symmetry, > `ambiguous_band` (2) is none, and in between the mesh cannot tell:
`AmbiguousSymmetry` is raised, naming the rotation, so that a person sets the symmetries by hand or changes
the tolerance rather than a guess deciding which poses count as equal. An ambiguous turn that could not
join the symmetries found (together they would turn by less than 2 pi / `max_order`: a 6-fold turn of a
heptagonal prism, 8.6 degrees off its 7-fold one) is a near miss and raises nothing. Candidates just above
the threshold have their axis refined first (rotation-only ICP about c, snapped back to an exact
2 pi / n turn): axes taken from a reconstructed mesh's features are only approximately right. The accepted
turns are closed into a group (composed until no new element appears), and every element of that group
is scored as well.

Limits: a mesh whose surface is rough at the scale of its triangles beyond about 0.5 % of the diameter
(iid vertex noise) scatters its normals past the normal tolerance and loses its symmetries, or is
ambiguous; prisms with 10 or more sides sit between discrete and continuous at the default tolerance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.distance import cdist

from n2d_common.errors import ConfigError, ContractError

TOLERANCE = 0.01
"""Largest mean distance between the surface and its image under a symmetry, as a fraction of the diameter."""
TAIL_TOLERANCE = 0.02
"""Largest 99th-percentile distance between the surface and its image, as a fraction of the diameter."""
TAIL_QUANTILE = 0.99
"""The quantile of the distances that `TAIL_TOLERANCE` bounds: 1 % of the surface may stick out further."""
NORMAL_TOLERANCE_DEG = 20.0
"""A sample's normal and the surface normal at its image differ when more than this apart (degrees, unsigned)."""
NORMAL_FRACTION = 0.1
"""Largest fraction of samples whose normal may differ: a faceted body (a hexagonal prism, an icosahedron) is
round within a few % of its diameter under rotations that are no symmetry, but its faces turn away."""
COLOR_TOLERANCE = 0.15
"""Two colours differ when their RGB distance exceeds this (0..1 per channel; 0.15 is about 22/255 per channel)."""
COLOR_FRACTION = 0.05
"""Largest fraction of surface samples whose colour may differ from the colour at their image."""
AMBIGUOUS_BAND = 2.0
"""A score in (1, AMBIGUOUS_BAND] is neither clearly symmetric nor clearly not: `AmbiguousSymmetry`."""
MAX_ORDER = 12
"""Discrete rotations tried about each axis: 2 pi / n for n = 2 .. MAX_ORDER."""
SAMPLES = 2000
"""Surface samples a candidate is scored on (both S and S^-1, so twice as many distances)."""
BOP_MAX_SYM_DISC_STEP = 0.01
"""BOP's default for discretising a continuous symmetry: the point furthest from the axis moves at most this
fraction of the diameter between steps, i.e. ceil(pi / 0.01) = 315 steps per turn."""

_QUICK_SAMPLES = 400
"""Samples of the first, cheap look at a candidate; only candidates that pass it are scored on all samples."""
_QUICK_REJECT = 1.25
"""A quick score above _QUICK_REJECT * ambiguous_band rejects a candidate without the full scoring."""
_REFINE_ABOVE = 1.0
"""Candidates scoring between this and the quick-reject limit get their axis refined before the verdict."""
_REFINE_SAMPLES = 1000
_REFINE_ITERATIONS = 6
_NEIGHBOURS = 4
"""Triangles of this many nearest reference samples are searched for the closest surface point."""
_NORMAL_RADIUS = 0.03
"""Surface normals are averaged over faces within this fraction of the diameter."""
_NORMAL_NEIGHBOURS = 16
"""... over at most this many faces at a time, ..."""
_NORMAL_STEPS = 8
"""... repeated at most this many times (fine meshes, whose neighbours lie closer)."""
_REFERENCE_PER_SAMPLE = 4
"""Reference samples (for the nearest-triangle search) per scored sample, besides every face centroid."""
_DEGENERATE = 0.1
"""Principal second moments within this fraction of the largest count as equal (axes not unique)."""
_AXIS_MERGE_DEG = 3.0
"""Candidate axes closer than this are one axis."""
_SAME_ROTATION_DEG = 5.0
"""Two rotations closer than this are one group element (distinct elements of the groups tried differ by
at least 2 pi / MAX_ORDER = 30 degrees)."""
_NEAR_ELEMENT_DEG = 15.0
"""A candidate this close to an element of the group found so far is that element or no symmetry (the
element and it would differ by a turn of less than 30 degrees): it is not tried. Axes taken from a
voxelised mesh's hull can be a few degrees off."""
_AXES_PER_SOURCE = 16
_MAX_AXES = 48
_CONTINUOUS_ANGLES = (0.81, 1.58, 2.76, 3.12)
"""Turns (radians) a body of revolution must be symmetric under: for every n = 2 .. 12 one of them is at
least 0.9 of the way from a multiple of 2 pi / n to the midpoint between two, so an n-sided prism fails."""


class SymmetryError(ConfigError):
    """The model's symmetries cannot be found from its mesh or cannot be written in BOP's format."""


class AmbiguousSymmetry(SymmetryError):
    """A candidate rotation is neither clearly a symmetry nor clearly not one, at the given tolerance."""

    def __init__(self, message: str, hint: str = "", residual: dict | None = None):
        super().__init__(message, hint)
        self.residual = residual or {}


@dataclass
class Symmetries:
    """The symmetries of a model, metres, object frame."""

    discrete: list[np.ndarray] = field(default_factory=list)
    """4 x 4 transforms S (proper rotation, translation in metres) mapping the model onto itself; no identity."""
    continuous: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """(unit axis, point on the axis in metres): symmetric under every rotation about that line."""
    residuals: list[dict] = field(default_factory=list)
    """The candidates scored in full, for the report: kind ("discrete" / "continuous"), axis, angle_deg,
    mean and tail distance (fractions of the diameter), normal and color (fractions of the samples that
    differ; color None without a texture), score and verdict."""
    diameter: float | None = None
    """The model's diameter in metres, when known."""

    @property
    def group_order(self) -> float:
        """Discrete symmetries including the identity; math.inf with a continuous symmetry."""
        return math.inf if self.continuous else len(self.discrete) + 1


# --------------------------------------------------------------------------------------------------------
# Detection


@dataclass
class _Surface:
    """What scoring a candidate needs: the triangles, the samples and the nearest-triangle search."""

    triangles: np.ndarray
    centre: np.ndarray
    diameter: float
    points: np.ndarray
    sample_faces: np.ndarray
    face_normals: np.ndarray
    colors: np.ndarray | None
    tree: cKDTree
    reference_face: np.ndarray
    face_uvs: np.ndarray | None
    texture: np.ndarray | None


@dataclass
class _Limits:
    tolerance: float
    tail_tolerance: float
    normal_cos: float
    normal_fraction: float
    color_tolerance: float
    color_fraction: float
    ambiguous_band: float


def find_symmetries(vertices: np.ndarray, faces: np.ndarray, *, face_uvs: np.ndarray | None = None,
                    texture: np.ndarray | None = None, tolerance: float = TOLERANCE,
                    tail_tolerance: float = TAIL_TOLERANCE, normal_tolerance_deg: float = NORMAL_TOLERANCE_DEG,
                    normal_fraction: float = NORMAL_FRACTION, color_tolerance: float = COLOR_TOLERANCE,
                    color_fraction: float = COLOR_FRACTION, ambiguous_band: float = AMBIGUOUS_BAND,
                    max_order: int = MAX_ORDER, samples: int = SAMPLES, seed: int = 0) -> Symmetries:
    """The proper rotational symmetries of a mesh (V x 3 vertices in metres, object frame; F x 3 faces).

    With `face_uvs` (F x 3 x 2, per face corner, v up as in OBJ) and `texture` (H x W x 3 uint8 albedo) a
    shape symmetry counts only where it maps the texture onto itself too. Tolerances: see the module
    docstring and the constants of the same names. Deterministic for a given `seed`. Raises ContractError
    for an empty or non-finite mesh, AmbiguousSymmetry when a rotation falls between the verdicts, and
    SymmetryError for a sphere (symmetric under every rotation, which BOP's format cannot hold).
    """
    limits = _check_limits(tolerance, tail_tolerance, normal_tolerance_deg, normal_fraction, color_tolerance,
                           color_fraction, ambiguous_band)
    if int(max_order) < 2 or int(samples) < 100:
        raise ConfigError(f"max_order must be >= 2 and samples >= 100, got {max_order} and {samples}")
    V, F = _check_mesh(vertices, faces)
    if (face_uvs is None) != (texture is None):
        raise ConfigError("find_symmetries: face_uvs and texture go together", "give both, or neither")
    if texture is not None:
        face_uvs, texture = _check_texture(face_uvs, texture, len(F))

    triangles = V[F]
    areas = _triangle_areas(triangles)
    if not areas.sum() > 0:
        raise ContractError("the mesh has no surface: every face has zero area", "check the mesh export")
    keep = areas > 0
    triangles, areas = triangles[keep], areas[keep]
    if face_uvs is not None:
        face_uvs = face_uvs[keep]
    centre, moment = _moments(triangles, areas)
    hull_points = _hull(V)
    diameter = _diameter(hull_points.points[hull_points.vertices])
    if not diameter > 0:
        raise ContractError("the mesh is a single point", "check the mesh export")

    rng = np.random.default_rng(seed)
    face, bary = _sample(areas, int(samples), rng)
    points = np.einsum("nk,nkc->nc", bary, triangles[face])
    ref_face, ref_bary = _sample(areas, _REFERENCE_PER_SAMPLE * int(samples), rng)
    reference = np.vstack([np.einsum("nk,nkc->nc", ref_bary, triangles[ref_face]), triangles.mean(1)])
    colors = None
    if texture is not None:
        colors = _bilinear(texture, np.einsum("nk,nkc->nc", bary, face_uvs[face]))
    reference_face = np.concatenate([ref_face, np.arange(len(triangles))])
    tree = cKDTree(reference)
    normals = _smooth_normals(triangles, areas, _NORMAL_RADIUS * diameter)
    surf = _Surface(triangles, centre, diameter, points, face, normals, colors, tree, reference_face, face_uvs,
                    texture)

    result = Symmetries(diameter=diameter)
    axes = _candidate_axes(centre, moment, hull_points, triangles, areas, int(max_order))
    axis, pending_axes = _find_continuous(surf, limits, [a for a, _, continuous in axes if continuous], result)
    if axis is not None:
        if _continuous_residual(surf, limits, _perpendicular(axis))["score"] <= 1.0:
            raise SymmetryError("the model is symmetric under every rotation (a sphere): BOP's models_info "
                                "cannot express that", "set the symmetries by hand in the model's manifest, "
                                "e.g. one continuous axis, or give the model a texture")
        offset = centre - np.dot(centre, axis) * axis
        result.continuous.append((_canonical_sign(axis), offset))
        flip, res = _verdict(surf, limits, _axis_angle(_perpendicular(axis), math.pi), 2, result)
        if 1.0 < res["score"] <= limits.ambiguous_band:
            raise _ambiguous(f"the half turn about axis {_fmt(_axis_and_angle(flip)[0])}", res, limits)
        if res["score"] <= 1.0:
            # a refined flip axis is put back perpendicular to the continuous one, as the group needs
            flip_axis, _ = _axis_and_angle(flip)
            flip_axis = flip_axis - np.dot(flip_axis, axis) * axis
            result.discrete.append(_about(_axis_angle(flip_axis, math.pi), centre))
        return result

    group, generators, pending = _find_discrete(surf, limits, axes, result, int(max_order))
    # An ambiguous turn stands only where it could join the group found: one that cannot (their products
    # would turn by less than 2 pi / max_order) is a near miss of a symmetry, and so is an ambiguous
    # continuous axis that the group turns about with order >= 3 (a 12-sided prism).
    for R, res in pending:
        if _close(generators + [R], int(max_order)) is not None:
            axis, angle = _axis_and_angle(R)
            raise _ambiguous(f"the {math.degrees(angle):.1f} degree rotation about axis {_fmt(axis)}", res, limits)
    for axis, res in pending_axes:
        if _order_about(group, axis) < 3:
            raise _ambiguous(f"the continuous rotation about axis {_fmt(axis)}", res, limits)
    result.discrete = [_about(R, centre) for R in _sorted_group(group)[1:]]
    return result


def _check_limits(tolerance, tail_tolerance, normal_tolerance_deg, normal_fraction, color_tolerance, color_fraction,
                  ambiguous_band) -> _Limits:
    values = dict(tolerance=tolerance, tail_tolerance=tail_tolerance, normal_tolerance_deg=normal_tolerance_deg,
                  normal_fraction=normal_fraction, color_tolerance=color_tolerance, color_fraction=color_fraction)
    for name, value in values.items():
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ConfigError(f"find_symmetries: {name} must be a positive number, got {value!r}")
    if not (isinstance(ambiguous_band, int | float) and math.isfinite(ambiguous_band) and ambiguous_band >= 1):
        raise ConfigError(f"find_symmetries: ambiguous_band must be >= 1, got {ambiguous_band!r}",
                          "1 turns the ambiguity check off")
    if normal_tolerance_deg >= 90:
        raise ConfigError(f"find_symmetries: normal_tolerance_deg must be below 90, got {normal_tolerance_deg!r}")
    return _Limits(float(tolerance), float(tail_tolerance), math.cos(math.radians(normal_tolerance_deg)),
                   float(normal_fraction), float(color_tolerance), float(color_fraction), float(ambiguous_band))


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or not len(V):
        raise ContractError(f"mesh vertices must be V x 3 with V > 0, got shape {V.shape}", "check the mesh export")
    if F.size == 0:
        raise ContractError("the mesh has no faces", "symmetries are found from a surface; check the mesh export")
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise ContractError(f"mesh faces must be F x 3 vertex indices, got shape {F.shape} of {F.dtype}",
                            "triangulate the mesh")
    if F.min() < 0 or F.max() >= len(V):
        raise ContractError(f"mesh faces index vertices {F.min()}..{F.max()} of {len(V)}", "check the mesh export")
    if not np.isfinite(V).all():
        raise ContractError(f"{int((~np.isfinite(V).any(1)).sum())} mesh vertices are not finite",
                            "check the mesh export (NaN or inf coordinates)")
    return V, F.astype(np.int64)


def _check_texture(face_uvs, texture, n_faces) -> tuple[np.ndarray, np.ndarray]:
    uvs = np.asarray(face_uvs, dtype=np.float64)
    if uvs.shape != (n_faces, 3, 2) or not np.isfinite(uvs).all():
        raise ContractError(f"face_uvs must be finite F x 3 x 2 = {n_faces} x 3 x 2, got {uvs.shape}",
                            "one (u, v) per face corner, as the OBJ's vt of each face")
    tex = np.asarray(texture)
    if tex.ndim == 2:
        tex = np.repeat(tex[..., None], 3, axis=2)
    if tex.ndim != 3 or tex.shape[2] < 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
        raise ContractError(f"texture must be H x W x 3, got shape {tex.shape}", "an RGB albedo image")
    scale = 255.0 if tex.dtype == np.uint8 else 1.0
    return uvs, tex[..., :3].astype(np.float64) / scale


def _triangle_areas(triangles: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)


def _moments(triangles: np.ndarray, areas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area centroid and central second moment (3 x 3, per unit area) of the surface, exact per triangle:
    over a triangle a, b, c the mean of p p^T is (a a^T + b b^T + c c^T + s s^T) / 12 with s = a + b + c."""
    w = areas / areas.sum()
    s = triangles.sum(1)
    centre = (w[:, None] * s).sum(0) / 3.0
    second = np.einsum("f,fki,fkj->ij", w, triangles, triangles) + np.einsum("f,fi,fj->ij", w, s, s)
    return centre, second / 12.0 - np.outer(centre, centre)


def _hull(V: np.ndarray) -> ConvexHull:
    """Convex hull of the vertices, one per cell of a grid of 1/500 of the bounding-box diagonal (qhull takes
    seconds for the 10^4 hull vertices of a finely tessellated cylinder, milliseconds after the thinning;
    the hull shrinks by at most a cell). A flat mesh gets qhull's joggled hull."""
    cell = float(np.linalg.norm(np.ptp(V, axis=0))) / 500.0
    if cell > 0:
        _, first = np.unique(np.floor(V / cell).astype(np.int64), axis=0, return_index=True)
        V = V[np.sort(first)]
    try:
        return ConvexHull(V)
    except QhullError:
        try:
            return ConvexHull(V, qhull_options="QJ")
        except QhullError as exc:
            raise ContractError("the mesh spans no area (its vertices are collinear)", "check the mesh export") \
                from exc


def _diameter(points: np.ndarray) -> float:
    """Largest distance between two of the points, in chunks so memory stays bounded."""
    best = 0.0
    for i in range(0, len(points), 1024):
        best = max(best, float(cdist(points[i:i + 1024], points).max()))
    return best


def _sample(areas: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` area-weighted random surface samples: their faces and barycentric coordinates."""
    face = rng.choice(len(areas), size=count, p=areas / areas.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)
    return face, bary


def _smooth_normals(triangles: np.ndarray, areas: np.ndarray, radius: float) -> np.ndarray:
    """Unit, unsigned normal per face, averaged over the faces around it out to about `radius`.

    The face normals of a reconstructed mesh's small triangles scatter by tens of degrees; their mean over
    a patch does not. The axes n n^T of the faces whose centroids lie within `radius` (at most
    _NORMAL_NEIGHBOURS of them, weighted by area and (1 - (d / radius)^2)) are averaged, repeatedly where
    those neighbours lie much closer than `radius` (fine meshes), and each face takes the principal
    direction of its mean. The patches depend on the geometry only, so the images of a symmetry get the
    same normals, and axes need no consistent face orientation. Large faces (a box of 12 triangles) keep
    their own normals.
    """
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]) / (2 * areas)[:, None]
    k = min(_NORMAL_NEIGHBOURS, len(areas))
    d, idx = cKDTree(triangles.mean(1)).query(triangles.mean(1), k=k, distance_upper_bound=radius)
    d, idx = d.reshape(len(areas), k), idx.reshape(len(areas), k)
    inside = np.isfinite(d)
    idx = np.where(inside, idx, 0)
    w = np.where(inside, areas[idx] * (1 - (np.where(inside, d, 0) / radius) ** 2), 0.0)
    w /= w.sum(1, keepdims=True)
    reach = float(np.median(np.where(inside[:, -1], d[:, -1], radius)))
    steps = int(np.clip(np.ceil(2 * (radius / max(reach, 1e-12 * radius)) ** 2), 1, _NORMAL_STEPS))
    tensor = (normals[:, :, None] * normals[:, None, :]).reshape(-1, 9)
    if k > 1:
        for _ in range(steps):
            tensor = np.einsum("fk,fkc->fc", w, tensor[idx])
    return np.linalg.eigh(tensor.reshape(-1, 3, 3))[1][:, :, 2]


def _bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """N x 3 bilinear samples of an H x W x 3 float texture at (u, v), v up, clamped at the border; the
    convention of n2d_common.raster.sample_bilinear (which needs torch for the rasterizer, this does not)."""
    h, w = texture.shape[:2]
    x, y = uv[:, 0] * w - 0.5, (1.0 - uv[:, 1]) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xa, xb = np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1)
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    t = texture
    return (1 - fy) * ((1 - fx) * t[ya, xa] + fx * t[ya, xb]) + fy * ((1 - fx) * t[yb, xa] + fx * t[yb, xb])


def _closest(surf: _Surface, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point: its distance to the surface, the nearest triangle and the nearest surface point.

    Exact over the triangles of the point's nearest reference samples (every face has one at its centroid),
    which hold the nearest triangle whenever the point is near the surface, the only case a verdict hinges on.
    """
    n = len(points)
    _, idx = surf.tree.query(points, k=_NEIGHBOURS)
    faces = surf.reference_face[idx]
    closest = trimesh.triangles.closest_point(surf.triangles[faces.ravel()], np.repeat(points, _NEIGHBOURS, 0))
    closest = closest.reshape(n, _NEIGHBOURS, 3)
    dist = np.linalg.norm(closest - points[:, None], axis=2)
    best = dist.argmin(1)
    rows = np.arange(n)
    return dist[rows, best], faces[rows, best], closest[rows, best]


def _residual(surf: _Surface, limits: _Limits, R: np.ndarray, count: int) -> dict:
    """Score of the rotation R about the centre on the first `count` samples (see the module docstring)."""
    X = surf.points[:count] - surf.centre
    distances, turned, differs = [], [], []
    # a half turn is its own inverse: its one pass stands for both
    for Rk in (R,) if np.allclose(R, R.T, atol=1e-12) else (R, R.T):
        d, face, q = _closest(surf, X @ Rk.T + surf.centre)
        distances.append(d)
        own = surf.face_normals[surf.sample_faces[:count]]
        cos = np.abs(np.einsum("nc,nc->n", own @ Rk.T, surf.face_normals[face]))
        turned.append(cos < limits.normal_cos)
        if surf.colors is not None:
            bary = trimesh.triangles.points_to_barycentric(surf.triangles[face], q)
            color = _bilinear(surf.texture, np.einsum("nk,nkc->nc", bary, surf.face_uvs[face]))
            differs.append(np.linalg.norm(color - surf.colors[:count], axis=1) > limits.color_tolerance)
    d = np.concatenate(distances) / surf.diameter
    mean, tail = float(d.mean()), float(np.quantile(d, TAIL_QUANTILE))
    normal = float(np.concatenate(turned).mean())
    color = float(np.concatenate(differs).mean()) if differs else None
    score = max(mean / limits.tolerance, tail / limits.tail_tolerance, normal / limits.normal_fraction,
                (color or 0.0) / limits.color_fraction)
    return {"mean": mean, "tail": tail, "normal": normal, "color": color, "score": score}


def _verdict(surf: _Surface, limits: _Limits, R: np.ndarray, order: int, result: Symmetries) \
        -> tuple[np.ndarray, dict]:
    """(R, its residual) for the turn by 2 pi / order that R stands for, R with its axis refined where that
    scores better. Only candidates past the quick look are scored in full and recorded in `result`."""
    quick = _residual(surf, limits, R, _QUICK_SAMPLES)
    if quick["score"] > _QUICK_REJECT * limits.ambiguous_band:
        return R, quick
    res = _residual(surf, limits, R, len(surf.points))
    if _REFINE_ABOVE < res["score"] <= _QUICK_REJECT * limits.ambiguous_band:
        axis, _ = _axis_and_angle(R)
        refined_axis, _ = _axis_and_angle(_refine(surf, R))
        refined = _axis_angle(refined_axis if np.dot(refined_axis, axis) >= 0 else -refined_axis,
                              2 * math.pi / order)
        refined_res = _residual(surf, limits, refined, len(surf.points))
        if refined_res["score"] < res["score"]:
            R, res = refined, refined_res
    axis, angle = _axis_and_angle(R)
    _record(result, "discrete", axis, angle, res, limits)
    return R, res


def _refine(surf: _Surface, R: np.ndarray) -> np.ndarray:
    """Rotation about the centre nearest to R that best maps the samples onto the surface (ICP, Kabsch)."""
    X = surf.points[:_REFINE_SAMPLES] - surf.centre
    for _ in range(_REFINE_ITERATIONS):
        _, _, q = _closest(surf, X @ R.T + surf.centre)
        U, _, Vt = np.linalg.svd(X.T @ (q - surf.centre))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
    return R


def _continuous_residual(surf: _Surface, limits: _Limits, axis: np.ndarray) -> dict:
    """Worst residual over the turns of _CONTINUOUS_ANGLES about the axis (early out once clearly not)."""
    worst = {"score": 0.0}
    for angle in _CONTINUOUS_ANGLES:
        R = _axis_angle(axis, angle)
        quick = _residual(surf, limits, R, _QUICK_SAMPLES)
        if quick["score"] > _QUICK_REJECT * limits.ambiguous_band:
            return quick
        worst = max(worst, _residual(surf, limits, R, len(surf.points)), key=lambda r: r["score"])
    return worst


def _find_continuous(surf: _Surface, limits: _Limits, axes: list[np.ndarray], result: Symmetries) \
        -> tuple[np.ndarray | None, list[tuple[np.ndarray, dict]]]:
    """(the first candidate axis of a continuous symmetry, refined, or None; the ambiguous axes before it
    with their residuals)."""
    pending = []
    for axis in axes:
        res = _continuous_residual(surf, limits, axis)
        if res["score"] > _QUICK_REJECT * limits.ambiguous_band:
            continue
        if res["score"] > _REFINE_ABOVE:
            refined, _ = _axis_and_angle(_refine(surf, _axis_angle(axis, _CONTINUOUS_ANGLES[1])))
            refined = refined if np.dot(refined, axis) >= 0 else -refined
            refined_res = _continuous_residual(surf, limits, refined)
            if refined_res["score"] < res["score"]:
                axis, res = refined, refined_res
        _record(result, "continuous", axis, None, res, limits)
        if res["score"] <= 1.0:
            return axis, pending
        if res["score"] <= limits.ambiguous_band:
            pending.append((axis, res))
    return None, pending


def _find_discrete(surf: _Surface, limits: _Limits, axes: list[tuple[np.ndarray, list[int], bool]],
                   result: Symmetries, max_order: int) -> tuple[list[np.ndarray], list[np.ndarray],
                                                            list[tuple[np.ndarray, dict]]]:
    """(the group, 3 x 3 rotations about the centre, identity first; its generators; the ambiguous
    candidates with their residuals). Every group element that was not itself a candidate is scored too.

    Turns about an axis are tried by increasing order, and a turn of order n about an axis the group
    already turns about with order k only when lcm(k, n) <= max_order: otherwise the two together would
    turn by less than 2 pi / max_order, so n can only be a near miss of a symmetry (a 7-fold turn of a
    hexagonal prism is 8.6 degrees off its 6-fold one).
    """
    group, generators, verified, pending = [np.eye(3)], [], [np.eye(3)], []
    for axis, orders, _ in axes:
        for n in orders:
            R = _axis_angle(axis, 2 * math.pi / n)
            if _contains(group, R, _NEAR_ELEMENT_DEG) or math.lcm(_order_about(group, axis), n) > max_order:
                continue
            R, res = _verdict(surf, limits, R, n, result)
            if res["score"] > limits.ambiguous_band:
                continue
            if res["score"] > 1.0:
                pending.append((R, res))
                continue
            generators.append(R)
            verified.append(R)
            group = _close(generators, max_order)
            if group is None:
                raise AmbiguousSymmetry(
                    "the rotations accepted as symmetries generate no finite group of turns of order <= "
                    f"{max_order}", "the mesh is nearly symmetric under too many rotations: lower the tolerance, "
                    "or set the symmetries by hand in the model's manifest")
            for element in group:
                if _contains(verified, element):
                    continue
                verified.append(element)
                res = _residual(surf, limits, element, len(surf.points))
                axis_e, angle_e = _axis_and_angle(element)
                _record(result, "discrete", axis_e, angle_e, res, limits)
                if res["score"] > 1.0:
                    raise _ambiguous(f"the {math.degrees(angle_e):.1f} degree rotation about axis {_fmt(axis_e)}, "
                                     "a composition of accepted symmetries,", res, limits)
            if _maximal(group):
                return group, generators, pending
    return group, generators, pending


def _order_about(group: list[np.ndarray], axis: np.ndarray) -> int:
    """How many elements of the group turn about `axis` (the identity included): its cyclic order there."""
    cos = math.cos(math.radians(_AXIS_MERGE_DEG))
    count = 1
    for R in group:
        a, angle = _axis_and_angle(R)
        count += angle > math.radians(_SAME_ROTATION_DEG) and abs(np.dot(a, axis)) > cos
    return count


def _maximal(group: list[np.ndarray]) -> bool:
    """Whether no finite rotation group contains this one: the icosahedral (60) or octahedral group (24
    elements, 8 of them third turns; the dihedral group of order 24 has only 2)."""
    thirds = sum(abs(_axis_and_angle(R)[1] - 2 * math.pi / 3) < math.radians(_SAME_ROTATION_DEG) for R in group)
    return len(group) == 60 or (len(group) == 24 and thirds == 8)


def _close(generators: list[np.ndarray], max_order: int) -> list[np.ndarray] | None:
    """The group the rotations generate (products of generators until nothing new appears), or None when
    that is no rotation group of an object with turns of order <= max_order: a product turns by less than
    2 pi / max_order, or there are more elements than the largest such group (60, icosahedral, or the
    dihedral group of order 2 max_order)."""
    limit = max(60, 2 * max_order)
    smallest = 2 * math.pi / max_order - math.radians(1.0)
    group = [np.eye(3)]
    frontier = [np.eye(3)]
    while frontier:
        new = []
        for g in frontier:
            for s in generators:
                p = g @ s
                if _contains(group, p):
                    continue
                if _axis_and_angle(p)[1] < smallest or len(group) == limit:
                    return None
                group.append(p)
                new.append(p)
        frontier = new
    return group


def _candidate_axes(centre: np.ndarray, moment: np.ndarray, hull: ConvexHull, triangles: np.ndarray,
                    areas: np.ndarray, max_order: int) -> list[tuple[np.ndarray, list[int], bool]]:
    """(axis, turn orders to try, try continuous) for every candidate axis, most likely first.

    Distinct principal moments allow only half turns about the principal axes. Two equal moments put any
    turn of order > 2 and any continuous symmetry on the third principal axis, and half turns about axes
    perpendicular to it (a dihedral group's). Three equal moments (a cube, an icosahedron) allow anything
    about the hull's feature directions.
    """
    evals, evecs = np.linalg.eigh(moment)
    lam = evals / max(evals[-1], 1e-300)
    low, high = lam[1] - lam[0] < _DEGENERATE, lam[2] - lam[1] < _DEGENERATE
    principal = [evecs[:, i] for i in range(3)]
    all_orders = list(range(2, max_order + 1))
    if not (low or high):
        return [(a, [2], False) for a in principal]
    features = _feature_directions(centre, hull, triangles, areas)
    # Equal moments leave their eigenvectors arbitrary (LAPACK's choice, a degree off an exact axis on some
    # machines), so the hull's features, exact on an exact mesh, go before them.
    if low and high:
        return [(a, all_orders, True) for a in _merge(features + principal)]
    main = evecs[:, 2] if low else evecs[:, 0]
    plane = [d - np.dot(d, main) * main for d in features + principal]
    plane = [d / np.linalg.norm(d) for d in plane if np.linalg.norm(d) > 0.3]
    return [(main, all_orders, True)] + [(a, [2], False) for a in _merge(plane)]


def _feature_directions(centre: np.ndarray, hull: ConvexHull, triangles: np.ndarray, areas: np.ndarray) \
        -> list[np.ndarray]:
    """Unit directions from the centre to hull vertices (furthest first), hull edge midpoints (longest edges
    first), and large hull-facet and mesh-face normal clusters, interleaved source by source."""
    pts = hull.points
    vertex = pts[hull.vertices] - centre
    vertex = vertex[np.argsort(-np.linalg.norm(vertex, axis=1), kind="stable")]
    edges = np.unique(np.sort(np.concatenate([hull.simplices[:, [0, 1]], hull.simplices[:, [1, 2]],
                                              hull.simplices[:, [0, 2]]]), axis=1), axis=0)
    lengths = np.linalg.norm(pts[edges[:, 0]] - pts[edges[:, 1]], axis=1)
    edges = edges[np.argsort(-lengths, kind="stable")]
    midpoints = 0.5 * (pts[edges[:, 0]] + pts[edges[:, 1]]) - centre
    hull_tri = pts[hull.simplices]
    hull_areas = _triangle_areas(hull_tri)
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    sources = [_unit_rows(vertex), _unit_rows(midpoints), _normal_clusters(hull.equations[:, :3], hull_areas),
               _normal_clusters(normals / (2 * areas[:, None]), areas)]
    sources = [_merge(list(s[:4 * _AXES_PER_SOURCE]))[:_AXES_PER_SOURCE] for s in sources]
    out = []
    for i in range(_AXES_PER_SOURCE):
        out += [s[i] for s in sources if i < len(s)]
    return out


def _normal_clusters(normals: np.ndarray, weights: np.ndarray, min_fraction: float = 0.01) -> np.ndarray:
    """Area-weighted mean normals of the direction bins (about 6 degrees wide) holding at least
    `min_fraction` of the area, largest first."""
    keys = np.round(normals * 10).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    total = np.bincount(inverse, weights=weights)
    mean = np.stack([np.bincount(inverse, weights=weights * normals[:, k]) for k in range(3)], 1)
    order = np.argsort(-total, kind="stable")
    order = order[total[order] >= min_fraction * weights.sum()]
    return _unit_rows(mean[order])


def _unit_rows(d: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(d, axis=1)
    return d[n > 1e-12] / n[n > 1e-12, None]


def _merge(directions: list[np.ndarray]) -> list[np.ndarray]:
    """The directions with near-duplicates and opposites dropped (an axis has no sign), first kept, capped."""
    out: list[np.ndarray] = []
    cos = math.cos(math.radians(_AXIS_MERGE_DEG))
    for d in directions:
        if all(abs(np.dot(d, o)) < cos for o in out):
            out.append(d)
            if len(out) == _MAX_AXES:
                break
    return out


# --------------------------------------------------------------------------------------------------------
# Rotations


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """3 x 3 rotation by `angle` (right hand) about the unit `axis` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _axis_and_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit axis, angle in [0, pi]) of a rotation; for a half turn the axis sign follows _canonical_sign."""
    angle = math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    w, v = np.linalg.eigh((R + R.T) / 2)
    axis = v[:, np.argmax(w)]
    skew = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.linalg.norm(skew) > 1e-6:
        axis = axis if np.dot(axis, skew) >= 0 else -axis
    else:
        axis = _canonical_sign(axis)
    return axis, angle


def _canonical_sign(axis: np.ndarray) -> np.ndarray:
    """The axis with its largest component positive (BOP writes [0, 0, 1], not [0, 0, -1])."""
    axis = np.asarray(axis, dtype=np.float64)
    return axis if axis[np.argmax(np.abs(axis))] >= 0 else -axis


def _perpendicular(axis: np.ndarray) -> np.ndarray:
    """A unit axis perpendicular to `axis`: the object-frame axis least aligned with it, projected."""
    e = np.eye(3)[int(np.argmin(np.abs(axis)))]
    p = e - np.dot(e, axis) * axis
    return p / np.linalg.norm(p)


def _angle_between(A: np.ndarray, B: np.ndarray) -> float:
    return math.acos(float(np.clip((np.trace(A.T @ B) - 1) / 2, -1.0, 1.0)))


def _contains(rotations: list[np.ndarray], R: np.ndarray, within_deg: float = _SAME_ROTATION_DEG) -> bool:
    return any(_angle_between(G, R) < math.radians(within_deg) for G in rotations)


def _sorted_group(group: list[np.ndarray]) -> list[np.ndarray]:
    """Group elements by angle, then axis: a stable order (identity first)."""
    def key(R):
        axis, angle = _axis_and_angle(R)
        return (round(angle, 6), *(-round(float(c), 6) for c in axis))
    return sorted(group, key=key)


def _about(R: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """4 x 4 rotation by R about the point `centre`: p -> R (p - c) + c."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T


def _fmt(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:+.3f}" for x in v) + "]"


def _record(result: Symmetries, kind: str, axis: np.ndarray, angle: float | None, res: dict, limits: _Limits):
    verdict = ("symmetric" if res["score"] <= 1.0 else
               "ambiguous" if res["score"] <= limits.ambiguous_band else "not symmetric")
    result.residuals.append({"kind": kind, "axis": [round(float(a), 6) for a in axis],
                             "angle_deg": None if angle is None else round(math.degrees(angle), 3),
                             "mean": res["mean"], "tail": res["tail"], "normal": res["normal"], "color": res["color"],
                             "score": res["score"], "verdict": verdict})


def _ambiguous(what: str, res: dict, limits: _Limits) -> AmbiguousSymmetry:
    color = f", colours differ at {100 * res['color']:.1f} % of the samples" if res["color"] is not None else ""
    return AmbiguousSymmetry(
        f"cannot tell whether {what} is a symmetry: mean surface distance {100 * res['mean']:.2f} % and "
        f"{100 * TAIL_QUANTILE:.0f}th percentile {100 * res['tail']:.2f} % of the diameter, normals turned away "
        f"at {100 * res['normal']:.1f} % of the samples{color}; score "
        f"{res['score']:.2f} lies between 1 (symmetric) and {limits.ambiguous_band:g} (not)",
        "set the symmetries by hand in the model's manifest (BOP's symmetries_discrete / symmetries_continuous), "
        "or change the tolerance", res)


# --------------------------------------------------------------------------------------------------------
# BOP's models_info.json, poses


def to_models_info(sym: Symmetries) -> dict:
    """BOP's `symmetries_discrete` / `symmetries_continuous` fields (millimetres), the empty ones omitted."""
    out: dict = {}
    if sym.discrete:
        rows = []
        for S in sym.discrete:
            M = np.array(S, dtype=np.float64)
            M[:3, 3] *= 1000.0
            rows.append([_clean(x, 8 if i % 4 < 3 and i < 12 else 6) for i, x in enumerate(M.ravel())])
        out["symmetries_discrete"] = rows
    if sym.continuous:
        out["symmetries_continuous"] = [{"axis": [_clean(x, 8) for x in axis],
                                         "offset": [_clean(1000.0 * x, 6) for x in offset]}
                                        for axis, offset in sym.continuous]
    return out


def _clean(x: float, digits: int) -> float:
    """Rounded, with -0.0 written as 0.0."""
    return round(float(x), digits) + 0.0


def from_models_info(entry: dict) -> Symmetries:
    """Symmetries (metres) of a BOP models_info entry; other fields are ignored, `diameter` is kept.

    Raises ContractError for malformed fields: a discrete symmetry must be 16 finite numbers whose 3 x 3
    part is a rotation (det +1, within 1e-3: BOP files round) and whose last row is 0 0 0 1; a continuous
    one needs a non-zero 3-vector `axis` and a 3-vector `offset`.
    """
    hint = "BOP's models_info: symmetries_discrete is a list of 16-number row-major 4x4 matrices (mm), " \
           "symmetries_continuous a list of {\"axis\": [x, y, z], \"offset\": [x, y, z]} (mm)"
    if not isinstance(entry, dict):
        raise ContractError(f"a models_info entry must be a mapping, got {type(entry).__name__}", hint)
    if entry and all(isinstance(k, str) and k.isdigit() and isinstance(v, dict) for k, v in entry.items()):
        raise ContractError("from_models_info takes one object's entry, got the whole models_info.json "
                            f"(objects {', '.join(entry)})", "pass models_info[obj_id]")
    sym = Symmetries()
    if "diameter" in entry:
        sym.diameter = _number(entry["diameter"], "diameter", hint) / 1000.0
    discrete = entry.get("symmetries_discrete", [])
    if not isinstance(discrete, list):
        raise ContractError("models_info: symmetries_discrete must be a list", hint)
    for i, s in enumerate(discrete):
        M = _numbers(s, 16, f"symmetries_discrete[{i}]", hint).reshape(4, 4)
        R = M[:3, :3]
        if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6) or not np.allclose(R.T @ R, np.eye(3), atol=1e-3) \
                or np.linalg.det(R) < 0:
            raise ContractError(f"models_info: symmetries_discrete[{i}] is not a proper rigid transform "
                                "(3x3 rotation with det +1, last row 0 0 0 1)", hint)
        U, _, Vt = np.linalg.svd(R)
        M[:3, :3] = U @ Vt
        M[:3, 3] /= 1000.0
        sym.discrete.append(M)
    continuous = entry.get("symmetries_continuous", [])
    if not isinstance(continuous, list):
        raise ContractError("models_info: symmetries_continuous must be a list", hint)
    for i, c in enumerate(continuous):
        if not isinstance(c, dict) or "axis" not in c or "offset" not in c:
            raise ContractError(f"models_info: symmetries_continuous[{i}] needs 'axis' and 'offset'", hint)
        axis = _numbers(c["axis"], 3, f"symmetries_continuous[{i}].axis", hint)
        if not np.linalg.norm(axis) > 1e-9:
            raise ContractError(f"models_info: symmetries_continuous[{i}].axis is zero", hint)
        offset = _numbers(c["offset"], 3, f"symmetries_continuous[{i}].offset", hint)
        sym.continuous.append((axis / np.linalg.norm(axis), offset / 1000.0))
    return sym


def _numbers(value, count: int, where: str, hint: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ContractError(f"models_info: {where} must be {count} numbers, got {value!r}", hint) from None
    if a.shape != (count,) or not np.isfinite(a).all():
        raise ContractError(f"models_info: {where} must be {count} finite numbers, got {value!r}", hint)
    return a


def _number(value, where: str, hint: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ContractError(f"models_info: {where} must be a positive number, got {value!r}", hint)
    return float(value)


def symmetric_poses(sym: Symmetries, max_sym_disc_step: float = BOP_MAX_SYM_DISC_STEP,
                    continuous_steps: int | None = None) -> list[np.ndarray]:
    """4 x 4 model-frame transforms S (identity first) the model is symmetric under, as BOP's
    misc.get_symmetry_transformations: each continuous symmetry discretised into `continuous_steps` turns
    (default ceil(pi / max_sym_disc_step)), composed with each discrete one (continuous after discrete)."""
    discrete = [np.eye(4)] + [np.asarray(S, dtype=np.float64) for S in sym.discrete]
    if not sym.continuous:
        return discrete
    steps = int(continuous_steps) if continuous_steps is not None else int(math.ceil(math.pi / max_sym_disc_step))
    if steps < 1:
        raise ConfigError(f"symmetric_poses: continuous_steps must be >= 1, got {steps}")
    turns = [_about(_axis_angle(axis, 2 * math.pi * i / steps), offset)
             for axis, offset in sym.continuous for i in range(steps)]
    return [C @ D for D in discrete for C in turns]


def canonical_pose(T_cam_obj: np.ndarray, sym_poses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(T_cam_obj @ S, S) for the symmetric pose S that brings the object's axes closest to the camera's
    (smallest Frobenius distance of R_cam_obj S_R to the identity), so that a label does not depend on
    which of the poses the model cannot tell apart a scene used.

    The same result for T and T @ S_k for every S_k of a group (as `symmetric_poses` gives). Ties (within
    1e-9) go to the lexicographically smallest rotation. A 3 x 3 `T_cam_obj` gives a 3 x 3 rotation back
    (with S still 4 x 4).
    """
    T = np.asarray(T_cam_obj, dtype=np.float64)
    if T.shape not in ((3, 3), (4, 4)):
        raise ConfigError(f"canonical_pose: expected a 3x3 rotation or 4x4 transform, got {T.shape}")
    S = np.asarray(sym_poses, dtype=np.float64).reshape(-1, 4, 4)
    if not len(S):
        raise ConfigError("canonical_pose: no symmetric poses", "give at least the identity")
    R = T[:3, :3] @ S[:, :3, :3]
    trace = np.trace(R, axis1=1, axis2=2)
    ties = np.flatnonzero(trace >= trace.max() - 1e-9)
    k = ties[0] if len(ties) == 1 else min(ties, key=lambda i: tuple(np.round(R[i].ravel(), 6)))
    if T.shape == (3, 3):
        return R[k], S[k]
    return T @ S[k], S[k]
