"""The object suite: procedurally generated, textured, metric model directories of many kinds, for tuning and
benchmarks, so that the pipeline is not tuned on one box.

The suite is the two shipped samples (n2d_sim.objects: a printed box and a glossy bottle) plus a mug, a plain
cube, a tin can, an L-bracket, a remote control, a spray bottle, a gear, a book and a rubber duck. Together they
cover textureless, dark, glossy, metallic, thin, concave, fine, symmetric, flat, tall and organic objects.

Every object is a model directory in the samples' contract: `mesh.obj` (metres, object frame at the
bounding-box centre, Z up as it stands, a UV and a normal at every face corner) + `mesh.mtl` + `albedo.png`
(at most 1024 px) + `models_info.json` (BOP, millimetres, with BOP symmetries where the object has any) + an
`n2d.json` manifest marking it as ground truth. Each surface is closed and wound outwards. Generation is
deterministic (fixed seeds); sharp parts are built from exact cells, polar rings and surfaces of revolution,
rounded and organic parts as signed distance fields meshed by marching cubes and decimated.

`suite_object_dir(name)` generates an object on first use into a cache and returns it (the samples come from
the package). The cache is `~/.cache/n2d/suite/<version>/<name>`, or `$N2D_SUITE_DIR/<version>/<name>`; the
version changes with this module's code, so a stale object is never reused. The CLI:

    python -m n2d_sim.suite --out DIR [names]      # write the objects into DIR/<name>
    python -m n2d_sim.suite --sheet docs/suite.jpg # a contact sheet of the suite, two views per object
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import fast_simplification
import numpy as np
from skimage.measure import marching_cubes

from n2d_common.contracts import read_manifest
from n2d_common.errors import ConfigError, ContractError
from n2d_sim.objects import (
    _MAKERS,
    FONT,
    FONT_BOLD,
    FONT_SMALL,
    _barcode,
    _logo,
    _MeshBuilder,
    _text,
    _text_fit,
    _text_lines,
    sample_object_dir,
    write_object,
)

SUITE_VERSION = 1
"""Bump when an object changes on purpose; the cache key also hashes this module's source."""

# ---------------------------------------------------------------------------------------------
# Symmetries


def _cube_rotations() -> np.ndarray:
    """The 24 proper rotations of a cube centred at the origin (signed permutation matrices, det +1),
    the identity first."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            R = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs)):
                R[row, col] = -1.0 if s else 1.0
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.array(out)


@dataclass(frozen=True)
class Symmetry:
    """The proper rotations about the object frame's origin that map an object, shape and texture, onto itself.

    `order` is the size of the finite group of rotations (1: the identity only; 24: a cube's); with
    `continuous_axis` set, the object also turns freely about that axis and `order` counts the rotations
    besides those (2 for a plain cylinder: the identity and a half turn about a horizontal axis).
    """

    order: int = 1
    continuous_axis: tuple[float, float, float] | None = None

    @property
    def label(self) -> str:
        if self.continuous_axis is not None:
            axis = "xyz"[int(np.argmax(np.abs(self.continuous_axis)))]
            return f"continuous about {axis}" + (f" + {self.order}-fold flip" if self.order > 1 else "")
        return "none" if self.order == 1 else f"discrete {self.order}"

    def rotations(self) -> np.ndarray:
        """order x 3 x 3: the finite group (identity first); with a continuous axis, the rotations that are
        not about that axis (composed with any turn about it, they are symmetries too)."""
        if self.order == 1:
            return np.eye(3)[None]
        if self.order == 24 and self.continuous_axis is None:
            return _cube_rotations()
        if self.order == 2 and self.continuous_axis == (0.0, 0.0, 1.0):
            return np.array([np.eye(3), np.diag([1.0, -1.0, -1.0])])
        raise NotImplementedError(f"no rotations for {self}")

    def bop(self) -> dict:
        """The BOP models_info keys of this symmetry (transforms in millimetres, row-major 4 x 4; none if none)."""
        out = {}
        if self.continuous_axis is not None:
            out["symmetries_continuous"] = [{"axis": list(self.continuous_axis), "offset": [0.0, 0.0, 0.0]}]
        discrete = []
        for R in self.rotations()[1:]:
            T = np.eye(4)
            T[:3, :3] = R
            discrete.append([float(v) + 0.0 for v in T.ravel()])
        if discrete:
            out["symmetries_discrete"] = discrete
        return out


NO_SYMMETRY = Symmetry()

# ---------------------------------------------------------------------------------------------
# Surfaces grouped by texture chart, and their bake into a mesh and an atlas


@dataclass
class _Chart:
    color: tuple[int, int, int]
    """Base colour (sRGB) the chart's canvas is filled with."""
    paint: Callable | None = None
    """paint(canvas, to_px, px_per_m): draws on the filled canvas; to_px maps chart coordinates (metres) to
    canvas pixels (x right, y down)."""


class _Surface:
    """Triangles with per-corner positions, chart coordinates (metres, v up) and normals, grouped by chart."""

    def __init__(self):
        self.charts: dict[str, _Chart] = {}
        self.tris: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []

    def chart(self, name: str, color, paint: Callable | None = None) -> str:
        if name not in self.charts:
            self.charts[name] = _Chart(tuple(int(c) for c in color), paint)
        return name

    def add(self, chart: str, P, Q, N) -> None:
        P = np.asarray(P, dtype=float).reshape(-1, 3, 3)
        if len(P):
            Q = np.asarray(Q, dtype=float).reshape(-1, 3, 2)
            N = np.broadcast_to(np.asarray(N, dtype=float), P.shape)
            self.tris.append((chart, P, Q, N / np.linalg.norm(N, axis=-1, keepdims=True)))

    def add_oriented(self, chart: str, P, Q, n) -> None:
        """Add flat triangles, each turned so that its winding agrees with the outward normal `n` (3 or F x 3)."""
        P = np.asarray(P, dtype=float).reshape(-1, 3, 3)
        Q = np.asarray(Q, dtype=float).reshape(-1, 3, 2)
        n = np.broadcast_to(np.asarray(n, dtype=float), (len(P), 3))
        flip = np.einsum("fc,fc->f", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), n) < 0
        P, Q = P.copy(), Q.copy()
        P[flip] = P[flip][:, ::-1]
        Q[flip] = Q[flip][:, ::-1]
        self.add(chart, P, Q, np.repeat(n[:, None], 3, axis=1))


class _Builder(_MeshBuilder):
    """_MeshBuilder with a vectorised bulk insert: the same tables, filled in the same corner order."""

    def add(self, P: np.ndarray, UV: np.ndarray, N: np.ndarray) -> None:
        def index(table: dict, values: np.ndarray, decimals: int) -> list[int]:
            rows = (np.round(values.reshape(-1, values.shape[-1]), decimals) + 0.0).tolist()
            return [table.setdefault(tuple(r), len(table)) for r in rows]

        v, t, n = index(self.v, P, 7), index(self.vt, UV, 6), index(self.vn, N, 5)
        corners = list(zip(v, t, n))
        self.faces.extend(zip(corners[0::3], corners[1::3], corners[2::3]))


def _pack(sizes: dict[str, tuple[int, int]], limit: int, gap: int) -> tuple[dict, int, int] | None:
    """Shelf packing of (w, h) pixel rectangles, tallest first: {name: (x, y)}, width, height; None if it does
    not fit in limit x limit."""
    order = sorted(sizes, key=lambda k: (-sizes[k][1], -sizes[k][0], list(sizes).index(k)))
    rects, x, y, row, width = {}, gap, gap, 0, 0
    for name in order:
        w, h = sizes[name]
        if w + 2 * gap > limit:
            return None
        if x + w + gap > limit:
            x, y, row = gap, y + row + gap, 0
        rects[name] = (x, y)
        x += w + gap
        row = max(row, h)
        width = max(width, x)
    height = y + row + gap
    return (rects, width, height) if height <= limit else None


def _bake(surf: _Surface, px_per_mm: float, max_px: int = 1024, bleed: int = 2,
          gap: int = 2) -> tuple[_Builder, np.ndarray]:
    """Centre the surface on its bounding box, lay its charts out in one atlas (at most max_px, at most
    px_per_mm), paint them and return the mesh and the albedo (RGB uint8)."""
    corners = np.concatenate([P.reshape(-1, 3) for _, P, _, _ in surf.tris])
    centre = (corners.min(0) + corners.max(0)) / 2
    names = list(dict.fromkeys(chart for chart, _, _, _ in surf.tris))
    lo = {n: np.min([Q.reshape(-1, 2).min(0) for c, _, Q, _ in surf.tris if c == n], axis=0) for n in names}
    hi = {n: np.max([Q.reshape(-1, 2).max(0) for c, _, Q, _ in surf.tris if c == n], axis=0) for n in names}
    s = px_per_mm * 1000.0
    while True:
        sizes = {n: tuple(int(math.ceil(e * s)) + 2 * bleed for e in hi[n] - lo[n]) for n in names}
        packed = _pack(sizes, max_px, gap)
        if packed is not None:
            break
        s *= 0.95
    rects, W, H = packed
    atlas = np.full((H, W, 3), 128, np.uint8)
    for n in names:
        chart, (x0, y0), (w, h) = surf.charts[n], rects[n], sizes[n]
        canvas = np.full((h, w, 3), chart.color, np.uint8)
        if chart.paint is not None:
            def to_px(u, v, n=n):
                return bleed + (np.asarray(u) - lo[n][0]) * s, bleed + (hi[n][1] - np.asarray(v)) * s
            chart.paint(canvas, to_px, s)
        atlas[y0:y0 + h, x0:x0 + w] = canvas
    mesh = _Builder()
    for n, P, Q, N in surf.tris:
        x0, y0 = rects[n]
        uv = np.stack([(x0 + bleed + (Q[..., 0] - lo[n][0]) * s) / W,
                       1.0 - (y0 + bleed + (hi[n][1] - Q[..., 1]) * s) / H], axis=-1)
        mesh.add(P - centre, uv, N)
    return mesh, atlas


# ---------------------------------------------------------------------------------------------
# Painting helpers (chart canvases are RGB uint8)


def _px(to_px, u, v) -> tuple[int, int]:
    x, y = to_px(u, v)
    return round(float(x)), round(float(y))


def _rect(img, to_px, u0, v0, u1, v1, color, thickness=-1):
    """A rectangle given by two chart-coordinate corners."""
    cv2.rectangle(img, _px(to_px, u0, v0), _px(to_px, u1, v1), color, thickness, cv2.LINE_AA)


def _circle(img, to_px, u, v, r, s, color, thickness=-1):
    cv2.circle(img, _px(to_px, u, v), max(1, round(r * s)), color, thickness, cv2.LINE_AA)


def _text_box(img, to_px, text, u0, v0, u1, v1, color, thickness=1, font=FONT_BOLD):
    """`text` as large as fits in the chart-coordinate box (u0, v0) - (u1, v1), centred."""
    (x0, y0), (x1, y1) = _px(to_px, u0, v1), _px(to_px, u1, v0)
    _text_fit(img, text, x0, y0, x1 - x0, y1 - y0, color, thickness, font)


def _text_rotated(img, text, centre_px, height_px, angle_deg, color, thickness=1, font=FONT_BOLD):
    """`text` of cap height `height_px` centred at `centre_px`, turned by `angle_deg` (counterclockwise on the
    image), blended with antialiasing."""
    (tw, th), base = cv2.getTextSize(text, font, 1.0, thickness)
    scale = height_px / th
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    side = int(math.hypot(tw, th + base)) + 4
    mask = np.zeros((side, side), np.uint8)
    cv2.putText(mask, text, (int((side - tw) / 2), int((side + th - base) / 2)), font, scale, 255, thickness,
                cv2.LINE_AA)
    M = cv2.getRotationMatrix2D((side / 2, side / 2), angle_deg, 1.0)
    M[:, 2] += np.array(centre_px) - side / 2
    alpha = cv2.warpAffine(mask, M, (img.shape[1], img.shape[0])).astype(np.float32)[..., None] / 255
    img[:] = np.round(img * (1 - alpha) + np.array(color, np.float32) * alpha).astype(np.uint8)


def _noise(img, rng, amplitude):
    """Add a little per-texel noise (a printed or moulded surface is never one flat colour)."""
    img[:] = np.clip(img.astype(np.int16) + rng.integers(-amplitude, amplitude + 1, img.shape[:2])[..., None],
                     0, 255).astype(np.uint8)


def _face_paint(draw: Callable[[int, int, float, np.random.Generator], np.ndarray], u0: float, v0: float,
                w: float, h: float, seed: int) -> Callable:
    """A chart painter for a rectangle (u0, v0, w, h metres): draw(h_px, w_px, px_per_m, rng) makes its image,
    placed with its edges repeated into the bleed."""
    def paint(canvas, to_px, s):
        x0, y0 = _px(to_px, u0, v0 + h)
        x1, y1 = _px(to_px, u0 + w, v0)
        face = draw(y1 - y0, x1 - x0, s, np.random.default_rng(seed))
        canvas[:] = np.pad(face, ((y0, canvas.shape[0] - y1), (x0, canvas.shape[1] - x1), (0, 0)), mode="edge")
    return paint


# ---------------------------------------------------------------------------------------------
# Exact builders: boxes of grid cells with round holes, surfaces of revolution


_BOX_UV = {(0, 1): ((1, 1), (2, 1)), (0, -1): ((1, -1), (2, 1)), (1, 1): ((0, -1), (2, 1)),
           (1, -1): ((0, 1), (2, 1)), (2, 1): ((0, 1), (1, 1)), (2, -1): ((0, 1), (1, -1))}
"""Chart axes of a face whose outward normal is +-x, +-y, +-z: ((u axis, sign), (v axis, sign)); u right and v up
as seen from outside, as the sample box's faces (front = -y, right = +x, back = +y, left = -x)."""


def _box_uv(P: np.ndarray, axis: int, sign: int) -> np.ndarray:
    (ua, us), (va, vs) = _BOX_UV[axis, sign]
    return np.stack([us * P[..., ua], vs * P[..., va]], axis=-1)


@dataclass(frozen=True)
class _Hole:
    """A round hole along `axis` through a column of grid cells: from the cell `cell` to the cell whose index
    along `axis` is `last`; it is centred in the column's cross-section."""

    axis: int
    cell: tuple[int, int, int]
    last: int
    radius: float
    segments: int = 24


def _zipper(outer: np.ndarray, inner: np.ndarray, centre: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangulate the ring between a convex loop `outer` (n x 2) and a loop `inner` (m x 2) around `centre`
    by walking both in angle order: index triples into [outer, inner]. An inner point joins the outer corner
    nearer in angle, split at the angles of the outer sides' midpoints, so that every triangle sees its corner."""
    def angle(p):
        return np.arctan2(p[..., 1] - centre[1], p[..., 0] - centre[0])

    ao = angle(outer)
    start = int(np.argmin(ao))
    order = [(start + k) % len(outer) for k in range(len(outer))]
    if np.any(np.diff(np.mod(ao[order] - ao[start], 2 * math.pi)) <= 0):  # clockwise: walk it the other way
        order = order[:1] + order[1:][::-1]
    n, m = len(order), len(inner)
    O = outer[order + order[:1]]
    a_mid = np.mod(angle((O[:-1] + O[1:]) / 2) - ao[start], 2 * math.pi)
    a_mid[-1] -= 2 * math.pi  # the last side's midpoint lies before the first corner
    rel = np.mod(angle(inner) - ao[start] - a_mid[-1], 2 * math.pi) + a_mid[-1]
    i_order = np.argsort(rel, kind="stable")
    a_i = np.append(rel[i_order], rel[i_order[0]] + 2 * math.pi)
    a_mid = np.append(a_mid[:-1], a_mid[-1] + 2 * math.pi)
    Oi = [*order, order[0]]
    Ii = [n + int(k) for k in i_order] + [n + int(i_order[0])]
    tris, o, i = [], 0, 0
    while o < n or i < m:
        if i == m or (o < n and a_mid[o] <= a_i[i + 1]):
            tris.append((Oi[o], Oi[o + 1], Ii[i]))
            o += 1
        else:
            tris.append((Oi[o], Ii[i + 1], Ii[i]))
            i += 1
    pts = np.vstack([outer, inner])[np.array(tris)]
    cross = np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0])
    if not (np.all(cross > 0) or np.all(cross < 0)):
        raise AssertionError("the hole does not fit its cell: the ring would fold")
    return tris


def _add_cells(surf: _Surface, knots, occupied: np.ndarray, chart: Callable[[int, int, float], str],
               holes: tuple[_Hole, ...] = (), hole_chart: str | None = None) -> None:
    """The closed boundary of a union of axis-aligned grid cells (knots: three ascending arrays, metres;
    occupied: nx x ny x nz bool) with round holes through some of them. Boundary quads meet edge to edge, so
    the surface is watertight; flat faces are charted with the box convention (`chart(axis, sign, plane)`
    names the chart of a plane), hole walls unrolled in `hole_chart`."""
    knots = [np.asarray(k, dtype=float) for k in knots]
    pad = np.pad(occupied, 1)
    holed = {}
    for h in holes:
        lo, hi = list(h.cell), list(h.cell)
        hi[h.axis] = h.last
        holed[h.axis, -1, tuple(lo)] = h
        holed[h.axis, 1, tuple(hi)] = h
    circles = {}
    for h in holes:
        a1, a2 = [a for a in range(3) if a != h.axis]
        c = [(knots[a][h.cell[a]] + knots[a][h.cell[a] + 1]) / 2 for a in (a1, a2)]
        phi = 2 * math.pi * np.arange(h.segments) / h.segments
        circles[h] = np.stack([c[0] + h.radius * np.cos(phi), c[1] + h.radius * np.sin(phi)], axis=1), np.array(c)
    for axis in range(3):
        a1, a2 = [a for a in range(3) if a != axis]
        for sign in (-1, 1):
            shift = [slice(1, -1)] * 3
            shift[axis] = slice(1 + sign, pad.shape[axis] - 1 + sign)
            boundary = occupied & ~pad[tuple(shift)]
            normal = np.zeros(3)
            normal[axis] = sign
            for cell in map(tuple, np.argwhere(boundary)):
                plane = knots[axis][cell[axis] + (sign > 0)]
                square = np.array([[knots[a1][cell[a1] + i], knots[a2][cell[a2] + j]]
                                   for i, j in ((0, 0), (1, 0), (1, 1), (0, 1))])
                hole = holed.get((axis, sign, cell))
                if hole is None:
                    pts2, tris = square, [(0, 1, 2), (0, 2, 3)]
                else:
                    ring, centre = circles[hole]
                    pts2, tris = np.vstack([square, ring]), _zipper(square, ring, centre)
                pts = np.zeros((len(pts2), 3))
                pts[:, axis], pts[:, a1], pts[:, a2] = plane, pts2[:, 0], pts2[:, 1]
                P = pts[np.array(tris)]
                surf.add_oriented(chart(axis, sign, plane), P, _box_uv(P, axis, sign), normal)
    for h in holes:
        a1, a2 = [a for a in range(3) if a != h.axis]
        ring, centre = circles[h]
        z0, z1 = knots[h.axis][h.cell[h.axis]], knots[h.axis][h.last + 1]
        k = np.arange(h.segments)
        k1 = (k + 1) % h.segments
        quads = np.zeros((h.segments, 4, 3))
        for c, (idx, z) in enumerate(((k, z0), (k1, z0), (k1, z1), (k, z1))):
            quads[:, c, h.axis], quads[:, c, a1], quads[:, c, a2] = z, ring[idx, 0], ring[idx, 1]
        u = 2 * math.pi * h.radius * np.stack([k, k + 1, k + 1, k], axis=1) / h.segments
        uv = np.stack([u, np.broadcast_to([z0, z0, z1, z1], u.shape)], axis=-1)
        mid = (quads[:, 0] + quads[:, 1]) / 2
        inward = np.zeros((h.segments, 3))
        inward[:, a1], inward[:, a2] = centre[0] - mid[:, a1], centre[1] - mid[:, a2]
        for tri in ((0, 1, 2), (0, 2, 3)):
            surf.add_oriented(hole_chart, quads[:, tri], uv[:, tri], inward)


def _revolve(surf: _Surface, chart: str, prof: np.ndarray, segments: int, r_ref: float,
             smooth_deg: float = 40.0) -> None:
    """The surface of revolution about z of the (r, z) polyline `prof` (metres) from the bottom pole to the top
    pole, with `segments` facets around; charted (angle * r_ref, arclength); normals smoothed across profile
    vertices that bend by less than `smooth_deg`. The same construction as the sample bottle."""
    seg = np.diff(prof, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    s = np.concatenate([[0.0], np.cumsum(seg_len)])
    seg_n = np.stack([seg[:, 1], -seg[:, 0]], axis=1) / seg_len[:, None]
    vert_n = []
    for k in range(len(prof)):
        ns = [seg_n[i] for i in (k - 1, k) if 0 <= i < len(seg)]
        smooth = len(ns) == 2 and np.dot(ns[0], ns[1]) > math.cos(math.radians(smooth_deg))
        vert_n.append(ns[0] + ns[1] if smooth else None)
    P, Q, N = [], [], []

    def corner(k, j, side):
        a = 2 * math.pi * j / segments
        r, z = prof[k]
        n2 = vert_n[k] if vert_n[k] is not None else seg_n[k - 1 if side == 0 else k]
        n2 = n2 / np.linalg.norm(n2)
        return ((r * math.cos(a), r * math.sin(a), z), (a * r_ref, s[k]),
                (n2[0] * math.cos(a), n2[0] * math.sin(a), n2[1]))

    def tri(*cs):
        P.append([c[0] for c in cs])
        Q.append([c[1] for c in cs])
        N.append([c[2] for c in cs])

    for k in range(len(prof) - 1):
        for j in range(segments):
            a0, a1 = corner(k, j, 1), corner(k, j + 1, 1)
            b0, b1 = corner(k + 1, j, 0), corner(k + 1, j + 1, 0)
            if prof[k][0] == 0:
                tri(corner(k, j + 0.5, 1), b1, b0)
            elif prof[k + 1][0] == 0:
                tri(a0, a1, corner(k + 1, j + 0.5, 0))
            else:
                tri(a0, a1, b1)
                tri(a0, b1, b0)
    surf.add(chart, P, Q, N)


# ---------------------------------------------------------------------------------------------
# Signed distance fields (metres; negative inside) and their meshes


def _smin(a, b, k):
    """Polynomial smooth minimum (a union with a fillet of about k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a, b, k):
    return -_smin(-a, -b, k)


def _round_box(p, centre, half, r):
    q = np.abs(p - centre) - (np.asarray(half) - r)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0) - r


def _rounded(dr, dz, r):
    """A 2D profile (radial excess dr, axial excess dz) of a flat-ended solid with its edges rounded by r."""
    q = np.stack([dr + r, dz + r], axis=-1)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0) - r


def _cyl(p, centre, radius, half_h, r, axis=2):
    """A cylinder along `axis` with its rims rounded by r."""
    d = p - centre
    rad = np.sqrt(sum(d[..., a] ** 2 for a in range(3) if a != axis))
    return _rounded(rad - radius, np.abs(d[..., axis]) - half_h, r)


def _ellipsoid(p, centre, semi):
    """An ellipsoid (the usual distance bound, exact on the surface)."""
    q = (p - centre) / semi
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / semi, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _seg2(x, y, a, b):
    """Distance from 2D points (x, y) to the segment a-b."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    t = np.clip(((x - a[0]) * dx + (y - a[1]) * dy) / max(dx * dx + dy * dy, 1e-30), 0.0, 1.0)
    return np.hypot(x - a[0] - t * dx, y - a[1] - t * dy)


def _polyline2(x, y, pts):
    return np.min([_seg2(x, y, a, b) for a, b in zip(pts[:-1], pts[1:])], axis=0)


def _gradient(sdf, p, eps=1e-5):
    g = np.stack([sdf(p + e) - sdf(p - e) for e in np.eye(3) * eps], axis=-1)
    return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)


def _sdf_mesh(sdf, lo, hi, voxel: float, faces: int):
    """A closed, outward-wound mesh of the zero set of `sdf` in the box lo-hi (metres): marching cubes on a
    `voxel` grid, decimated to `faces` triangles, vertices projected back onto the surface, folded slivers
    flipped. Returns vertices, faces and unit normals (the field's gradient)."""
    lo, hi = np.asarray(lo) - 3 * voxel, np.asarray(hi) + 3 * voxel
    # An odd offset keeps grid samples off the flat faces at round coordinates (no zero-area triangles).
    axes = [lo[i] + voxel * (np.arange(int(math.ceil((hi[i] - lo[i]) / voxel)) + 1) + 0.37) for i in range(3)]
    # Narrow band: the field on a 4x coarser grid first, then exactly only where the surface may be near. A
    # distance field changes by at most the distance moved, so elsewhere the coarse value has the right sign,
    # and marching cubes only interpolates across edges that cross the surface.
    coarse = [a[::4] for a in axes]
    d = sdf(np.stack(np.meshgrid(*coarse, indexing="ij"), axis=-1).reshape(-1, 3)).reshape([len(a) for a in coarse])
    nearest = [np.minimum(np.round(np.arange(len(a)) / 4).astype(int), len(c) - 1) for a, c in zip(axes, coarse)]
    d = d[np.ix_(*nearest)]
    near = np.nonzero(np.abs(d) < 8 * voxel)
    d[near] = sdf(np.stack([a[i] for a, i in zip(axes, near)], axis=-1))
    v, f, _, _ = marching_cubes(d, 0.0, spacing=(voxel,) * 3, allow_degenerate=False)
    v += [a[0] for a in axes]
    f = f.astype(np.int64)
    for agg in (3.0, 2.0, 1.0, 5.0):  # a fast setting can leave an edge with four faces: try another
        vs, fs = fast_simplification.simplify(v, f, target_count=faces, agg=agg)
        if _closed(fs):
            break
    else:
        raise AssertionError("decimation did not keep the surface closed")
    v, f = vs, fs
    for _ in range(2):
        v = v - sdf(v)[:, None] * _gradient(sdf, v)
    f = _unfold(v, np.array(f, np.int64), sdf)
    return v, f, _gradient(sdf, v)


def _unfold(v: np.ndarray, f: np.ndarray, sdf, threshold: float = 0.5, passes: int = 8) -> np.ndarray:
    """Flip the edges of faces turned away from the field's normal: decimation leaves a few slivers folded
    across tight fillets. A flip is kept when it makes the worse of the two faces better; the surface stays
    closed (an edge that would appear twice is not made)."""
    def quality(tris):
        P = v[np.asarray(tris)].reshape(-1, 3, 3)
        n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        return np.einsum("fc,fc->f", n, _gradient(sdf, P.mean(1)))

    edges = {(a, b): i for i, (x, y, z) in enumerate(f.tolist()) for a, b in ((x, y), (y, z), (z, x))}
    for _ in range(passes):
        q = quality(f)
        bad = np.nonzero(q < threshold)[0]
        if not len(bad):
            break
        touched = set()
        for fi in bad[np.argsort(q[bad], kind="stable")]:
            if fi in touched:
                continue
            best = None
            a, b, c = (int(x) for x in f[fi])
            for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):
                gi = edges.get((y, x))
                if gi is None or gi in touched:
                    continue
                d = next(int(w) for w in f[gi] if w not in (x, y))
                if (z, d) in edges or (d, z) in edges:
                    continue
                new = quality([(x, d, z), (d, y, z)])
                if new.min() > min(q[fi], q[gi]) + 1e-6 and (best is None or new.min() > best[0]):
                    best = (new.min(), gi, (x, d, z), (d, y, z))
            if best is None:
                continue
            _, gi, t1, t2 = best
            for tri in (f[fi], f[gi]):
                for e in zip(tri, np.roll(tri, -1)):
                    edges.pop((int(e[0]), int(e[1])), None)
            f[fi], f[gi] = t1, t2
            for i, tri in ((fi, t1), (gi, t2)):
                for e in zip(tri, np.roll(tri, -1)):
                    edges[int(e[0]), int(e[1])] = i
            touched.update((fi, gi))
    return f


def _closed(faces: np.ndarray) -> bool:
    """Whether every edge of the triangles is shared by exactly two of them."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def _face_normals(P: np.ndarray) -> np.ndarray:
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def _add_box_charts(surf: _Surface, prefix: str, P, N, color, paints: dict | None = None) -> None:
    """Chart faces by box projection along the dominant axis of their normal: six planar charts."""
    n = _face_normals(P)
    axis = np.argmax(np.abs(n), axis=1)
    sign = np.where(n[np.arange(len(n)), axis] >= 0, 1, -1)
    for a in range(3):
        for sg in (1, -1):
            sel = (axis == a) & (sign == sg)
            key = f"{prefix}{'+' if sg > 0 else '-'}{'xyz'[a]}"
            surf.chart(key, color, (paints or {}).get(key))
            surf.add(key, P[sel], _box_uv(P[sel], a, sg), N[sel])


def _cyl_uv(P: np.ndarray, r_ref: float, seam: float = 0.0) -> np.ndarray:
    """Chart coordinates (angle from `seam` * r_ref, z) of face corners; a face across the seam is unwrapped."""
    a = np.mod(np.arctan2(P[..., 1], P[..., 0]) - seam, 2 * math.pi)
    wrap = (a.max(1) - a.min(1)) > math.pi
    a[wrap] = np.where(a[wrap] < math.pi, a[wrap] + 2 * math.pi, a[wrap])
    return np.stack([a * r_ref, P[..., 2]], axis=-1)


# ---------------------------------------------------------------------------------------------
# 1. The mug: glazed ceramic, hollow with a 4 mm wall, a handle, a print on one side

MUG_R, MUG_H, MUG_T = 0.040, 0.095, 0.004
"""Outer radius, height and wall thickness (metres)."""
_MUG_HANDLE = (0.036, 0.0475, 0.030, 0.0055)
"""Handle torus in the xz plane: centre x, centre z, ring radius, tube radius (metres)."""


_MUG_C, _MUG_RHO = MUG_R - MUG_T / 2, 0.008
"""Radius of the wall's centre line, and of its bend into the floor (metres)."""
_MUG_L = (_MUG_C - _MUG_RHO, _MUG_RHO * math.pi / 2, MUG_H - MUG_T - _MUG_RHO)
"""Lengths of the centre line's floor, bend and side."""


def _mug_wall(r, z):
    """Distance to the wall's centre line in the (r, z) half plane, and the wall chart's v there: the arclength
    of the nearest centre-line point up the outer side, then round the rim, then down the inner side."""
    c, t, rho = _MUG_C, MUG_T, _MUG_RHO
    lf, la, ls = _MUG_L
    floor = _seg2(r, z, (0.0, t / 2), (c - rho, t / 2))
    side = _seg2(r, z, (c, t / 2 + rho), (c, MUG_H - t / 2))
    qr, qz = r - (c - rho), z - (t / 2 + rho)
    on_arc = (qr >= 0) & (qz <= 0)
    arc = np.where(on_arc, np.abs(np.hypot(qr, qz) - rho), 1.0)
    d = np.minimum(np.minimum(floor, side), arc)
    length = np.where(d == floor, np.clip(r, 0.0, lf),
                      np.where(d == side, lf + la + np.clip(qz, 0.0, ls),
                               lf + (np.arctan2(qz, qr) + math.pi / 2) * rho))
    outer = np.where(d == floor, z < t / 2, np.where(d == side, r > c, np.hypot(qr, qz) > rho))
    total = lf + la + ls
    over_rim = lf + la + qz > total  # nearest the rim's end: the angle round it, outside (0) to inside (pi)
    rim = total + np.arctan2(z - (MUG_H - t / 2), r - c) * t / 2
    v = np.where(over_rim, rim, np.where(outer, length, 2 * total + math.pi * t / 2 - length))
    return d, v


def _mug_v_outside(z: float) -> float:
    """The wall chart's v on the outer side at height z (metres)."""
    lf, la, _ = _MUG_L
    return lf + la + z - MUG_T / 2 - _MUG_RHO


def _mug_parts(p):
    r = np.hypot(p[:, 0], p[:, 1])
    body = _mug_wall(r, p[:, 2])[0] - MUG_T / 2
    xc, zc, a, rm = _MUG_HANDLE
    handle = np.hypot(np.hypot(p[:, 0] - xc, p[:, 2] - zc) - a, p[:, 1]) - rm
    handle = np.maximum(handle, _MUG_C - r)  # no handle inside the wall's middle
    return body, handle


def _mug_sdf(p):
    body, handle = _mug_parts(p)
    return _smin(body, handle, 0.0025)


_MUG_CREAM, _MUG_BLUE, _MUG_BISCUIT = (238, 232, 218), (40, 70, 130), (196, 178, 150)


def _paint_mug_wall(img, to_px, s):
    """Glazes by band (unglazed foot ring, cream outside, blue from just inside the rim) and the print."""
    rng = np.random.default_rng(31)
    lf, la, ls = _MUG_L
    width = 2 * math.pi * MUG_R + 0.02
    _rect(img, to_px, -0.01, 0.0, width, lf, _MUG_BISCUIT)
    _rect(img, to_px, -0.01, lf + la + ls + 0.6 * math.pi * MUG_T / 2, width, 1.0, _MUG_BLUE)
    navy, red, gold = (30, 50, 110), (190, 40, 40), (230, 170, 40)

    def v(z):
        return _mug_v_outside(z)

    for i in range(int(2 * math.pi * MUG_R / 0.006) + 1):  # a dotted band under the rim, all round
        _circle(img, to_px, i * 0.006, v(0.084), 0.0012, s, navy)
    cv2.line(img, _px(to_px, -0.01, v(0.079)), _px(to_px, width, v(0.079)), navy, max(1, round(0.0008 * s)),
             cv2.LINE_AA)
    u0 = 1.5 * math.pi * MUG_R  # the print faces -y (the handle is at +x)
    _logo(img, *to_px(u0 - 0.018, v(0.060)), 0.011 * s, [gold, red, navy])
    _text_box(img, to_px, "N2D", u0 - 0.004, v(0.050), u0 + 0.040, v(0.071), navy, max(1, round(0.0012 * s)))
    _text_box(img, to_px, "turntable coffee", u0 - 0.034, v(0.038), u0 + 0.040, v(0.046), red, 1, FONT)
    _text_box(img, to_px, "est. 2024 - hot & strong", u0 - 0.030, v(0.030), u0 + 0.036, v(0.035), navy, 1,
              FONT_SMALL)
    for _ in range(14):  # scattered beans
        u, vb = u0 + rng.uniform(-0.05, 0.05), v(rng.uniform(0.012, 0.026))
        ax = (max(1, round(0.0022 * s)), max(1, round(0.0014 * s)))
        cv2.ellipse(img, _px(to_px, u, vb), ax, float(rng.uniform(0, 180)), 0, 360, (110, 70, 40), -1, cv2.LINE_AA)


def _make_mug():
    v, f, n = _sdf_mesh(_mug_sdf, (-MUG_R, -MUG_R, 0.0), (0.0715, MUG_R, MUG_H), 0.0007, 20000)
    P, N = v[f], n[f]
    c = P.mean(1)
    r = np.hypot(c[:, 0], c[:, 1])
    body, handle = _mug_parts(c)
    is_handle = handle < body
    surf = _Surface()
    # The wall chart runs continuously from the foot ring up, over the rim and down to the floor's edge, so
    # that glaze edges are painted lines, not the staircase of face boundaries; the middle of the foot and of
    # the floor (one colour each) are planar charts.
    wall = ~is_handle & (r > 0.02)
    surf.chart("mug.wall", _MUG_CREAM, _paint_mug_wall)
    wv = _mug_wall(np.hypot(P[wall][..., 0], P[wall][..., 1]), P[wall][..., 2])[1]
    surf.add("mug.wall", P[wall], np.stack([_cyl_uv(P[wall], MUG_R)[..., 0], wv], axis=-1), N[wall])
    middle = ~is_handle & ~wall
    for name, sel, color, sg in (("mug.foot", middle & (c[:, 2] < MUG_T / 2), _MUG_BISCUIT, -1),
                                 ("mug.floor", middle & (c[:, 2] >= MUG_T / 2), _MUG_BLUE, 1)):
        surf.chart(name, color)
        surf.add(name, P[sel], _box_uv(P[sel], 2, sg), N[sel])
    # The handle unrolled as a torus: angle round the ring * ring radius, angle round the tube * tube radius.
    xc, zc, a, rm = _MUG_HANDLE
    H = P[is_handle]
    phi = np.arctan2(H[..., 2] - zc, H[..., 0] - xc)
    psi = np.arctan2(H[..., 1], np.hypot(H[..., 0] - xc, H[..., 2] - zc) - a)
    wrap = (psi.max(1) - psi.min(1)) > math.pi
    psi[wrap] = np.where(psi[wrap] < 0, psi[wrap] + 2 * math.pi, psi[wrap])
    surf.chart("mug.handle", _MUG_CREAM)
    surf.add("mug.handle", H, np.stack([phi * a, psi * rm], axis=-1), N[is_handle])
    mesh, albedo = _bake(surf, px_per_mm=3.5)
    return mesh, albedo, {"roughness": 0.12, "specular": 0.6}


# ---------------------------------------------------------------------------------------------
# 2. The plain cube: exactly symmetric, one matte colour

CUBE_SIZE = 0.050


def _make_cube():
    knots = [np.linspace(-CUBE_SIZE / 2, CUBE_SIZE / 2, 6)] * 3
    surf = _Surface()
    color = (172, 182, 196)
    _add_cells(surf, knots, np.ones((5, 5, 5), bool),
               lambda axis, sign, plane: surf.chart(f"cube{'+' if sign > 0 else '-'}{'xyz'[axis]}", color))
    mesh, albedo = _bake(surf, px_per_mm=1.0, max_px=256)
    return mesh, albedo, {"roughness": 0.9, "specular": 0.3}


# ---------------------------------------------------------------------------------------------
# 3. The tin can: a plain metal body of revolution, symmetric top to bottom

CAN_R, CAN_H = 0.0365, 0.105
CAN_SEGMENTS = 72
"""Facets round the can (a multiple of 4: the bounding box is exact and symmetric)."""


def _can_profile() -> np.ndarray:
    """(r, z) metres from the bottom pole to the top pole: recessed ends, rolled seams, beads; mirror-symmetric
    about half height."""
    half = [(0.0, 2.8), (30.5, 2.8), (32.2, 1.2), (32.8, 0.0), (36.7, 0.0), (37.3, 0.6), (37.4, 2.4), (36.9, 3.4),
            (36.5, 4.2)]
    for zc in (16.0, 27.0, 38.0, 49.0):  # rolled beads: shallow grooves that stiffen the wall
        half += [(36.5 - 0.8 * math.sin(math.pi * t) ** 2, zc - 2.5 + 5.0 * t) for t in np.linspace(0, 1, 7)]
    half.append((36.5, CAN_H * 500))
    full = half + [(r, CAN_H * 1000 - z) for r, z in reversed(half[:-1])]
    return np.array(full) / 1000


def _make_can():
    surf = _Surface()
    surf.chart("can", (212, 214, 218))
    _revolve(surf, "can", _can_profile(), CAN_SEGMENTS, CAN_R)
    mesh, albedo = _bake(surf, px_per_mm=0.5, max_px=256)
    return mesh, albedo, {"roughness": 0.25, "specular": 0.5, "metallic": 1.0}


# ---------------------------------------------------------------------------------------------
# 4. The bracket: a textureless grey L angle with unequal legs and three bolt holes

BRACKET_KNOTS = ([-0.020, -0.015, -0.005, 0.005, 0.015, 0.020], [0.0, 0.005, 0.035, 0.045, 0.060],
                 [0.0, 0.005, 0.025, 0.035, 0.045])
"""Grid knots (x width, y base leg, z upright leg), metres: the plates are 5 mm thick."""


def _make_bracket():
    X, Y, Z = BRACKET_KNOTS
    occ = np.zeros((len(X) - 1, len(Y) - 1, len(Z) - 1), bool)
    occ[:, :, 0] = True  # the base plate
    occ[:, 0, :] = True  # the upright plate
    holes = (_Hole(2, (1, 2, 0), 0, 0.0033), _Hole(2, (3, 2, 0), 0, 0.0033), _Hole(1, (1, 0, 2), 0, 0.0033))
    surf = _Surface()
    grey = (128, 128, 130)
    surf.chart("bracket.holes", grey)
    _add_cells(surf, BRACKET_KNOTS, occ,
               lambda axis, sign, plane: surf.chart(f"bracket{'+' if sign > 0 else '-'}{'xyz'[axis]}{plane:.3f}",
                                                    grey), holes, "bracket.holes")
    mesh, albedo = _bake(surf, px_per_mm=1.0, max_px=256)
    return mesh, albedo, {"roughness": 0.6, "specular": 0.35}


# ---------------------------------------------------------------------------------------------
# 5. The remote: a near-black rounded slab with small raised buttons and fine print

REMOTE_HALF = (0.024, 0.0875, 0.008)
"""Half extents of the body (x, y, z; metres); the buttons stand 2 mm above its top."""
REMOTE_BLACK = (56, 56, 58)
"""sRGB of the body: linear albedo about 0.04."""


def _remote_buttons():
    """(kind, centre a, centre b, radius, colour, label): stadiums around the segment a-b (round if a = b), and
    the d-pad ring (radius = its middle radius)."""
    grey, red = (92, 92, 98), (175, 32, 30)
    buttons = [("round", (-0.013, 0.070), (-0.013, 0.070), 0.004, red, "power"),
               ("round", (0.013, 0.070), (0.013, 0.070), 0.0035, grey, "source"),
               ("ring", (0.0, 0.042), (0.0, 0.042), 0.012, grey, "dpad"),
               ("round", (0.0, 0.042), (0.0, 0.042), 0.0062, grey, "OK"),
               ("round", (-0.015, 0.008), (-0.015, 0.024), 0.0035, grey, "VOL"),
               ("round", (0.015, 0.008), (0.015, 0.024), 0.0035, grey, "CH"),
               ("round", (0.0, 0.021), (0.0, 0.021), 0.0035, grey, "home"),
               ("round", (0.0, 0.008), (0.0, 0.008), 0.003, grey, "mute")]
    for i, label in enumerate(["1", "2", "3", "4", "5", "6", "7", "8", "9", "*", "0", "#"]):
        c = (-0.013 + 0.013 * (i % 3), -0.008 - 0.014 * (i // 3))
        buttons.append(("round", c, c, 0.0045, grey, label))
    for i, color in enumerate([(200, 40, 40), (40, 160, 60), (220, 190, 40), (40, 90, 200)]):
        c = (-0.0135 + 0.009 * i, -0.066)
        buttons.append(("round", c, c, 0.0025, color, ""))
    return buttons


def _remote_button_sdf(p, kind, a, b, radius):
    top = 2 * REMOTE_HALF[2]
    dxy = _seg2(p[:, 0], p[:, 1], a, b)
    if kind == "ring":  # a 5 mm wide band round the middle radius
        dxy, radius = np.abs(dxy - radius), 0.0025
    return _rounded(dxy - radius, np.abs(p[:, 2] - (top + 0.0005)) - 0.0015, 0.0008)


def _remote_parts(p):
    body = _round_box(p, np.array([0.0, 0.0, REMOTE_HALF[2]]), REMOTE_HALF, 0.0055)
    near_top = np.nonzero(p[:, 2] > 2 * REMOTE_HALF[2] - 0.002)[0]
    buttons = np.full(len(p), 1.0)  # far: a finite distance keeps the smooth union finite
    q = p[near_top]
    sub = np.full(len(q), 1.0)
    for kind, a, b, radius, _, _ in _remote_buttons():
        reach = radius + (0.0026 if kind == "ring" else 0.0) + 0.002
        lo = np.array([min(a[0], b[0]) - reach, min(a[1], b[1]) - reach, -1.0])
        hi = np.array([max(a[0], b[0]) + reach, max(a[1], b[1]) + reach, 1.0])
        idx = np.nonzero(np.all((q >= lo) & (q <= hi), axis=1))[0]
        if len(idx):
            sub[idx] = np.minimum(sub[idx], _remote_button_sdf(q[idx], kind, a, b, radius))
    buttons[near_top] = sub
    return body, buttons


def _remote_sdf(p):
    body, buttons = _remote_parts(p)
    return _smin(body, buttons, 0.001)


def _paint_remote_top(img, to_px, s):
    white, dim = (235, 235, 235), (150, 150, 155)
    for kind, a, b, radius, color, label in _remote_buttons():
        if kind == "ring":
            cv2.circle(img, _px(to_px, *a), round(0.012 * s), color, max(1, round(0.0054 * s)), cv2.LINE_AA)
            for ang in range(0, 360, 90):  # arrows on the d-pad
                ca, sa = math.cos(math.radians(ang)), math.sin(math.radians(ang))
                tip = (a[0] + 0.0135 * ca, a[1] + 0.0135 * sa)
                base = [(a[0] + 0.0105 * ca - 0.0018 * sa, a[1] + 0.0105 * sa + 0.0018 * ca),
                        (a[0] + 0.0105 * ca + 0.0018 * sa, a[1] + 0.0105 * sa - 0.0018 * ca)]
                pts = np.array([_px(to_px, *tip), *(_px(to_px, *q) for q in base)], np.int32)
                cv2.fillPoly(img, [pts], white, cv2.LINE_AA)
            continue
        w = max(1, round(0.0001 * s))
        cv2.line(img, _px(to_px, *a), _px(to_px, *b), color, round(2 * (radius + 0.0002) * s), cv2.LINE_AA)
        _circle(img, to_px, *a, radius + 0.0002, s, color)
        _circle(img, to_px, *b, radius + 0.0002, s, color)
        cx, cy = (a[0] + b[0]) / 2, (a[1] + b[1]) / 2
        if label == "power":
            _circle(img, to_px, cx, cy, 0.0021, s, white, max(1, round(0.0005 * s)))
            cv2.line(img, _px(to_px, cx, cy), _px(to_px, cx, cy + 0.0027), color, round(0.0012 * s))
            cv2.line(img, _px(to_px, cx, cy + 0.0005), _px(to_px, cx, cy + 0.0028), white, max(1, round(0.0005 * s)))
        elif label in ("VOL", "CH"):
            _text_box(img, to_px, "+", a[0] - 0.002, b[1] - 0.003, a[0] + 0.002, b[1] + 0.002, white, w + 1)
            _text_box(img, to_px, "-", a[0] - 0.002, a[1] - 0.002, a[0] + 0.002, a[1] + 0.003, white, w + 1)
            x_text = a[0] + (0.0055 if a[0] < 0 else -0.0055)
            _text_rotated(img, label, _px(to_px, x_text, cy), 0.0018 * s, 90, dim, 1, FONT_SMALL)
        elif label in ("source", "home", "mute"):
            symbol = {"source": "IN", "home": "H", "mute": "M"}[label]
            _text_box(img, to_px, symbol, cx - 0.0022, cy - 0.0018, cx + 0.0022, cy + 0.0018, white, w)
        elif label:
            _text_box(img, to_px, label, cx - 0.0026, cy - 0.0023, cx + 0.0026, cy + 0.0023, white, w + 1)
    _text_box(img, to_px, "N2D", -0.012, -0.082, 0.012, -0.073, (200, 200, 205), max(1, round(0.0004 * s)))
    _text_box(img, to_px, "SMART TV", -0.010, 0.055, 0.010, 0.059, dim, 1, FONT_SMALL)
    _noise(img, np.random.default_rng(5), 2)


def _paint_remote_bottom(img, to_px, s):
    line = (80, 80, 84)
    _rect(img, to_px, -0.017, -0.075, 0.017, -0.005, line, max(1, round(0.0004 * s)))
    for i in range(6):  # finger grip ridges on the battery cover
        y = -0.012 - 0.003 * i
        cv2.line(img, _px(to_px, -0.008, y), _px(to_px, 0.008, y), line, max(1, round(0.0006 * s)), cv2.LINE_AA)
    _text_lines(img, ["MODEL RC-7", "2 x AAA  1.5 V", "made by n2d labs"], *_px(to_px, -0.015, -0.045),
                round(0.004 * s), 0.00011 * s, (150, 150, 155), FONT_SMALL)
    _noise(img, np.random.default_rng(6), 2)


def _paint_remote_front(img, to_px, s):
    _rect(img, to_px, -0.008, 0.0055, 0.008, 0.0115, (90, 20, 25))  # the infrared window (+y end)


def _make_remote():
    top = 2 * REMOTE_HALF[2]
    v, f, n = _sdf_mesh(_remote_sdf, (-REMOTE_HALF[0], -REMOTE_HALF[1], 0.0),
                        (REMOTE_HALF[0], REMOTE_HALF[1], top + 0.002), 0.0005, 18000)
    P, N = v[f], n[f]
    c = P.mean(1)
    body, buttons = _remote_parts(c)
    fn = _face_normals(P)
    surf = _Surface()
    on_top = (buttons < body) | (fn[:, 2] > 0.3)
    surf.chart("remote.top", REMOTE_BLACK, _paint_remote_top)
    surf.add("remote.top", P[on_top], _box_uv(P[on_top], 2, 1), N[on_top])
    rest = ~on_top
    _add_box_charts(surf, "remote", P[rest], N[rest], REMOTE_BLACK,
                    {"remote-z": _paint_remote_bottom, "remote+y": _paint_remote_front})
    mesh, albedo = _bake(surf, px_per_mm=5.0)
    return mesh, albedo, {"roughness": 0.5, "specular": 0.45}


# ---------------------------------------------------------------------------------------------
# 6. The spray bottle: a labelled body, a trigger head with a thin trigger and a nozzle

SPRAY_R = 0.031
_SPRAY_TRIGGER = [(0.019, 0.190), (0.026, 0.177), (0.030, 0.162), (0.030, 0.147)]
"""The trigger's centre line in the xz plane (metres): a curved 3.6 mm plate, 13 mm wide."""


def _spray_parts(p):
    body = _smin(_cyl(p, np.array([0.0, 0.0, 0.070]), SPRAY_R, 0.070, 0.006),
                 _cyl(p, np.array([0.0, 0.0, 0.150]), 0.0125, 0.020, 0.0), 0.012)
    collar = _cyl(p, np.array([0.0, 0.0, 0.174]), 0.0165, 0.009, 0.0015)
    head = _round_box(p, np.array([0.006, 0.0, 0.199]), (0.021, 0.0135, 0.017), 0.005)
    nozzle = _round_box(p, np.array([0.034, 0.0, 0.2065]), (0.008, 0.0065, 0.0065), 0.002)
    stroke = _polyline2(p[:, 0], p[:, 2], _SPRAY_TRIGGER) - 0.0018
    trigger = _rounded(stroke, np.abs(p[:, 1]) - 0.0065, 0.001)
    return {"body": body, "collar": collar, "head": head, "nozzle": nozzle, "trigger": trigger}


def _spray_sdf(p):
    parts = _spray_parts(p)
    d = _smin(parts["body"], parts["collar"], 0.002)
    d = _smin(d, parts["head"], 0.002)
    d = _smin(d, parts["nozzle"], 0.0015)
    return _smin(d, parts["trigger"], 0.0015)


def _paint_spray_label(img, to_px, s):
    rng = np.random.default_rng(11)
    blue, white, green, ink = (20, 80, 160), (248, 248, 246), (40, 160, 90), (40, 40, 50)
    u0 = 1.5 * math.pi * SPRAY_R  # the front label faces -y (the trigger points to +x)
    _rect(img, to_px, u0 - 0.042, 0.028, u0 + 0.042, 0.112, white)
    _rect(img, to_px, u0 - 0.042, 0.096, u0 + 0.042, 0.112, blue)
    _text_box(img, to_px, "N2D CLEAN", u0 - 0.034, 0.098, u0 + 0.034, 0.110, white, max(1, round(0.0008 * s)))
    for i in range(3):  # drops
        cx, cy = u0 - 0.030 + 0.012 * i, 0.078 - 0.004 * (i % 2)
        _circle(img, to_px, cx, cy, 0.004, s, (60, 150, 220))
        tri = np.array([_px(to_px, cx - 0.0036, cy + 0.0016), _px(to_px, cx + 0.0036, cy + 0.0016),
                        _px(to_px, cx, cy + 0.009)], np.int32)
        cv2.fillPoly(img, [tri], (60, 150, 220), cv2.LINE_AA)
    _text_box(img, to_px, "glass & steel", u0 - 0.002, 0.074, u0 + 0.038, 0.086, blue, 1, FONT)
    _text_box(img, to_px, "streak-free shine", u0 - 0.002, 0.066, u0 + 0.038, 0.072, green, 1, FONT)
    _text_lines(img, ["Spray 20 cm from the surface,", "wipe with a dry cloth.", "Keep away from children.",
                      "500 ml"], *_px(to_px, u0 - 0.036, 0.056), round(0.0055 * s), 0.00012 * s, ink)
    cv2.rectangle(img, _px(to_px, u0 - 0.042, 0.028), _px(to_px, u0 + 0.042, 0.031), green, -1)
    ub = 0.5 * math.pi * SPRAY_R  # the back label (+y): directions and a barcode
    _rect(img, to_px, ub - 0.035, 0.035, ub + 0.035, 0.100, white)
    _text_lines(img, [f"lot {int(rng.integers(1000, 9999))}", "contains < 5 %", "anionic surfactants",
                      "perfume"], *_px(to_px, ub - 0.030, 0.093), round(0.005 * s), 0.00012 * s, ink)
    (x0, y0), (x1, y1) = _px(to_px, ub - 0.028, 0.062), _px(to_px, ub + 0.028, 0.045)
    _barcode(img, x0, y0, x1 - x0, y1 - y0, rng)


def _paint_spray_head(text_u, text_v):
    def paint(img, to_px, s):
        _text_box(img, to_px, "N2D", text_u - 0.012, text_v - 0.005, text_u + 0.012, text_v + 0.005,
                  (245, 245, 240), max(1, round(0.0006 * s)))
    return paint


def _make_spray():
    v, f, n = _sdf_mesh(_spray_sdf, (-SPRAY_R, -SPRAY_R, 0.0), (0.043, SPRAY_R, 0.216), 0.0008, 18000)
    P, N = v[f], n[f]
    parts = _spray_parts(P.mean(1))
    names = list(parts)
    which = np.argmin(np.stack([parts[k] for k in names]), axis=0)
    fn = _face_normals(P)
    surf = _Surface()
    body = which == names.index("body")
    side = body & (np.abs(fn[:, 2]) < 0.7)
    surf.chart("spray.label", (170, 210, 230), _paint_spray_label)
    surf.add("spray.label", P[side], _cyl_uv(P[side], SPRAY_R), N[side])
    for name, sel, sg in (("spray.shoulder", body & (fn[:, 2] >= 0.7), 1),
                          ("spray.base", body & (fn[:, 2] <= -0.7), -1)):
        surf.chart(name, (170, 210, 230))
        surf.add(name, P[sel], _box_uv(P[sel], 2, sg), N[sel])
    colors = {"collar": (40, 150, 85), "head": (40, 150, 85), "nozzle": (236, 236, 230), "trigger": (236, 236, 230)}
    for k, color in colors.items():
        sel = which == names.index(k)
        paints = {"head-y": _paint_spray_head(0.006, 0.200), "head+y": _paint_spray_head(-0.006, 0.200)}
        _add_box_charts(surf, k, P[sel], N[sel], color, paints if k == "head" else None)
    mesh, albedo = _bake(surf, px_per_mm=4.0)
    return mesh, albedo, {"roughness": 0.45, "specular": 0.5}


# ---------------------------------------------------------------------------------------------
# 7. The gear: a brass spur gear with a keyed bore and five windows (teeth and holes: fine detail)

GEAR_TEETH, GEAR_MODULE, GEAR_THICKNESS = 28, 0.002, 0.016
_GEAR_BORE, _GEAR_KEY, _GEAR_HUB, _GEAR_RIM = 0.006, (0.008, 0.002), 0.013, 0.021
"""Bore radius; keyway depth (x of its floor) and half width; hub and rim radii of the windows (metres)."""
_GEAR_WINDOWS = [(math.radians(36 + 72 * k - 24), math.radians(36 + 72 * k + 24)) for k in range(5)]
BRASS = (205, 170, 95)


def _gear_outline() -> np.ndarray:
    """(angle, radius) of the tooth outline's corners, angle ascending in [0, 2 pi)."""
    rp = GEAR_TEETH * GEAR_MODULE / 2
    rt, rr = rp + GEAR_MODULE, rp - 1.25 * GEAR_MODULE
    p = 2 * math.pi / GEAR_TEETH
    shape = [(-p / 2, rr), (-0.33 * p, rr), (-0.25 * p, rp), (-0.11 * p, rt), (0.11 * p, rt), (0.25 * p, rp),
             (0.33 * p, rr)]
    pts = [(np.mod(j * p + a, 2 * math.pi), r) for j in range(GEAR_TEETH) for a, r in shape]
    return np.array(sorted(pts))


def _ray_polygon(theta: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """Radius at angles `theta` of the star-shaped polygon given by (angle, radius) corners."""
    a, r = outline[:, 0], outline[:, 1]
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    k = np.searchsorted(a, theta, side="right") - 1
    A, B = pts[k % len(a)], pts[(k + 1) % len(a)]
    u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    e = B - A
    return (A[:, 0] * e[:, 1] - A[:, 1] * e[:, 0]) / (u[:, 0] * e[:, 1] - u[:, 1] * e[:, 0])


def _gear_bore(theta: np.ndarray) -> np.ndarray:
    """Radius of the keyed bore: a round hole with a rectangular keyway along +x."""
    t = np.mod(theta + math.pi, 2 * math.pi) - math.pi
    depth, half = _GEAR_KEY
    t1, t2 = math.atan2(half, depth), math.asin(half / _GEAR_BORE)
    return np.where(np.abs(t) <= t1, depth / np.cos(t),
                    np.where(np.abs(t) <= t2, half / np.maximum(np.abs(np.sin(t)), 1e-12), _GEAR_BORE))


def _paint_gear_face(top: bool):
    def paint(img, to_px, s):
        rng = np.random.default_rng(17 if top else 18)
        sgn = 1 if top else -1
        for r in np.arange(0.0065, 0.0305, 0.00035):  # turning marks: concentric rings of slightly varying shade
            shade = tuple(int(np.clip(c + rng.integers(-10, 11), 0, 255)) for c in BRASS)
            _circle(img, to_px, 0.0, 0.0, r, s, shade, 1)
        if top:
            # an index mark on the rim next to the keyway, and the part number along a spoke
            tri = np.array([_px(to_px, 0.0215, 0.0), _px(to_px, 0.0245, 0.0022), _px(to_px, 0.0245, -0.0022)],
                           np.int32)
            cv2.fillPoly(img, [tri], (170, 30, 25), cv2.LINE_AA)
            _text_box(img, to_px, "M2 Z28", 0.0136, -0.0022, 0.0206, 0.0022, (90, 60, 25), 1, FONT_SMALL)
        else:
            _text_rotated(img, "N2D", _px(to_px, math.cos(math.radians(144)) * 0.017,
                                          sgn * math.sin(math.radians(144)) * 0.017), 0.0025 * s, -144, (90, 60, 25))
    return paint


def _make_gear():
    outline = _gear_outline()
    depth, half = _GEAR_KEY
    special = [0.0, math.atan2(half, depth), -math.atan2(half, depth), math.asin(half / _GEAR_BORE),
               -math.asin(half / _GEAR_BORE)] + [a for w in _GEAR_WINDOWS for a in w]
    theta = np.unique(np.round(np.concatenate([outline[:, 0], np.mod(special, 2 * math.pi)]), 12))
    loops = {"bore": _gear_bore(theta), "hub": np.full(len(theta), _GEAR_HUB), "rim": np.full(len(theta), _GEAR_RIM),
             "teeth": _ray_polygon(theta, outline)}
    xy = {k: np.stack([r * np.cos(theta), r * np.sin(theta)], axis=1) for k, r in loops.items()}
    n = len(theta)
    j, j1 = np.arange(n), (np.arange(n) + 1) % n
    mid = np.mod(theta + np.diff(np.append(theta, theta[0] + 2 * math.pi)) / 2, 2 * math.pi)
    in_window = np.zeros(n, bool)
    for w0, w1 in _GEAR_WINDOWS:
        in_window |= (mid > w0) & (mid < w1)
    T = GEAR_THICKNESS
    surf = _Surface()
    surf.chart("gear.top", BRASS, _paint_gear_face(True))
    surf.chart("gear.bottom", BRASS, _paint_gear_face(False))

    def lift(p2, z):
        return np.concatenate([p2, np.full((len(p2), 1), z)], axis=1)

    for z, name, sg in ((T, "gear.top", 1), (0.0, "gear.bottom", -1)):
        for a, b, keep in (("bore", "hub", np.ones(n, bool)), ("hub", "rim", ~in_window),
                           ("rim", "teeth", np.ones(n, bool))):
            q = np.stack([xy[a][j], xy[a][j1], xy[b][j1], xy[b][j]], axis=1)[keep]
            quad = np.stack([lift(q[:, i], z) for i in range(4)], axis=1)
            for tri in ((0, 1, 2), (0, 2, 3)):
                surf.add_oriented(name, quad[:, tri], _box_uv(quad[:, tri], 2, sg), (0.0, 0.0, sg))

    def wall(chart, p0, p1, outward, u0, u1):
        """Vertical quads from the xy points p0 to p1 (k x 2), charted (u, z)."""
        quad = np.stack([lift(p0, 0.0), lift(p1, 0.0), lift(p1, T), lift(p0, T)], axis=1)
        uv = np.stack([np.stack([u0, u1, u1, u0], axis=1), np.broadcast_to([0.0, 0.0, T, T], (len(u0), 4))], -1)
        e = p1 - p0
        normal = np.concatenate([outward * np.stack([e[:, 1], -e[:, 0]], axis=1), np.zeros((len(e), 1))], axis=1)
        for tri in ((0, 1, 2), (0, 2, 3)):
            surf.add_oriented(chart, quad[:, tri], uv[:, tri], normal)

    def arclength(p0, p1):
        seg = np.linalg.norm(p1 - p0, axis=1)
        u = np.concatenate([[0.0], np.cumsum(seg)])
        return u[:-1], u[1:]

    for name, loop, outward in (("gear.teeth", "teeth", 1.0), ("gear.bore", "bore", -1.0)):
        surf.chart(name, BRASS)
        wall(name, xy[loop][j], xy[loop][j1], outward, *arclength(xy[loop][j], xy[loop][j1]))
    surf.chart("gear.windows", BRASS)
    offset = 0.0
    for w0, w1 in _GEAR_WINDOWS:
        idx = np.nonzero((mid > w0) & (mid < w1))[0]
        start, end = idx[0], (idx[-1] + 1) % n
        hub0, hub1 = xy["hub"][idx], xy["hub"][(idx + 1) % n]
        rim0, rim1 = xy["rim"][(idx + 1) % n][::-1], xy["rim"][idx][::-1]
        # Round the window: hub arc, far side, rim arc back, near side; every wall faces into the window.
        pieces = [(hub0, hub1), (xy["hub"][end][None], xy["rim"][end][None]), (rim0, rim1),
                  (xy["rim"][start][None], xy["hub"][start][None])]
        for p0, p1 in pieces:
            u0, u1 = arclength(p0, p1)
            wall("gear.windows", p0, p1, 1.0, u0 + offset, u1 + offset)
            offset += u1[-1] + 0.0
        offset += 0.004
    mesh, albedo = _bake(surf, px_per_mm=8.0)
    return mesh, albedo, {"roughness": 0.35, "specular": 0.5, "metallic": 1.0}


# ---------------------------------------------------------------------------------------------
# 8. The book: a tall, flat hardcover with a printed cover, spine and back, and page edges

BOOK_SIZE = (0.150, 0.030, 0.220)
"""Width (x, the cover), thickness (y), height (z), metres; the front cover faces -y, the spine is at -x."""
_BOOK_COVER = (26, 66, 84)
_PAGES = (236, 228, 206)


def _draw_book_front(h, w, s, rng):
    k = s / 1000  # pixels per millimetre
    img = np.full((h, w, 3), _BOOK_COVER, np.uint8)
    cream, orange = (240, 226, 190), (236, 140, 50)
    _text_fit(img, "THE TURNING", int(10 * k), int(12 * k), w - int(20 * k), int(22 * k), cream, max(1, int(k)))
    _text_fit(img, "TABLE", int(25 * k), int(36 * k), w - int(50 * k), int(26 * k), orange, max(1, int(1.4 * k)))
    cv2.rectangle(img, (int(12 * k), int(70 * k)), (w - int(12 * k), int(170 * k)), (120, 170, 200), -1)
    cv2.circle(img, (int(110 * k), int(95 * k)), int(14 * k), (250, 200, 80), -1, cv2.LINE_AA)
    for i, color in enumerate([(60, 90, 110), (40, 70, 80), (30, 55, 60)]):  # mountain ridges
        xs = np.linspace(12, 138, 10) * k
        ys = (120 + 12 * i + rng.uniform(-14, 14, 10)) * k
        pts = np.array([[xs[0], 170 * k], *np.stack([xs, ys], 1), [xs[-1], 170 * k]], np.int32)
        cv2.fillPoly(img, [pts], color, cv2.LINE_AA)
    cv2.ellipse(img, (int(75 * k), int(158 * k)), (int(40 * k), int(7 * k)), 0, 0, 360, (200, 60, 50), -1,
                cv2.LINE_AA)
    cv2.ellipse(img, (int(75 * k), int(155 * k)), (int(40 * k), int(7 * k)), 0, 0, 360, (230, 90, 70), -1,
                cv2.LINE_AA)
    _text_fit(img, "R. T. PLATEAU", int(25 * k), int(182 * k), w - int(50 * k), int(12 * k), cream, max(1, int(k)))
    _text_fit(img, "a novel", int(55 * k), int(198 * k), w - int(110 * k), int(8 * k), orange, 1, FONT)
    _noise(img, rng, 3)
    return img


def _draw_book_back(h, w, s, rng):
    k = s / 1000
    img = np.full((h, w, 3), _BOOK_COVER, np.uint8)
    cream = (240, 226, 190)
    _text_fit(img, "\"A quiet, turning masterpiece.\"", int(12 * k), int(14 * k), w - int(24 * k), int(10 * k),
              (236, 140, 50), 1, FONT)
    words = "plate servo board camera light object mesh pose texture dataset frame turn".split()
    lines = [" ".join(rng.choice(words, 5)) for _ in range(14)]
    _text_lines(img, lines, int(12 * k), int(38 * k), int(7 * k), 0.17 * k, cream)
    cv2.rectangle(img, (int(80 * k), int(170 * k)), (int(140 * k), int(208 * k)), (255, 255, 255), -1)
    _barcode(img, int(84 * k), int(174 * k), int(52 * k), int(24 * k), rng)
    _text(img, "EUR 18.90", (12 * k, 200 * k), 0.2 * k, cream, 1, FONT)
    _noise(img, rng, 3)
    return img


def _draw_book_spine(h, w, s, rng):
    k = s / 1000
    side = np.full((w, h, 3), _BOOK_COVER, np.uint8)  # the spine lying on its side, for the running title
    _text_fit(side, "THE TURNING TABLE", int(12 * k), int(6 * k), int(140 * k), int(18 * k), (240, 226, 190),
              max(1, int(k)))
    _text_fit(side, "PLATEAU", int(160 * k), int(8 * k), int(45 * k), int(14 * k), (236, 140, 50), 1)
    img = np.ascontiguousarray(np.rot90(side, 3))
    for y in (int(6 * k), h - int(6 * k)):
        cv2.line(img, (0, y), (w, y), (236, 140, 50), max(1, int(0.8 * k)))
    _noise(img, rng, 3)
    return img


def _draw_book_edge(board_u: tuple[bool, bool], board_v: tuple[bool, bool], lines_along_v: bool):
    """Page edges: fine lines (one per few pages) between the cover boards on the named sides."""
    def draw(h, w, s, rng):
        k = s / 1000
        img = np.full((h, w, 3), _PAGES, np.uint8)
        n = w if lines_along_v else h
        for i in range(0, n, 2):
            shade = tuple(int(c - rng.integers(10, 40)) for c in _PAGES)
            if lines_along_v:
                cv2.line(img, (i, 0), (i, h), shade, 1)
            else:
                cv2.line(img, (0, i), (w, i), shade, 1)
        b = max(1, int(2.5 * k))
        if board_u[0]:
            img[:, :b] = _BOOK_COVER
        if board_u[1]:
            img[:, w - b:] = _BOOK_COVER
        if board_v[0]:
            img[h - b:] = _BOOK_COVER
        if board_v[1]:
            img[:b] = _BOOK_COVER
        return img
    return draw


def _make_book():
    sx, sy, sz = BOOK_SIZE
    knots = [np.linspace(0, sx, 4), np.linspace(0, sy, 2), np.linspace(0, sz, 5)]
    paints = {  # chart name -> painter of its rectangle (u0, v0, w, h in the box convention)
        "book-y": _face_paint(_draw_book_front, 0.0, 0.0, sx, sz, 1),
        "book+y": _face_paint(_draw_book_back, -sx, 0.0, sx, sz, 2),
        "book-x": _face_paint(_draw_book_spine, -sy, 0.0, sy, sz, 3),
        "book+x": _face_paint(_draw_book_edge((True, True), (False, False), True), 0.0, 0.0, sy, sz, 4),
        "book+z": _face_paint(_draw_book_edge((True, False), (True, True), False), 0.0, 0.0, sx, sy, 5),
        "book-z": _face_paint(_draw_book_edge((True, False), (True, True), False), 0.0, -sy, sx, sy, 6),
    }
    surf = _Surface()

    def chart(axis, sign, plane):
        name = f"book{'+' if sign > 0 else '-'}{'xyz'[axis]}"
        return surf.chart(name, _BOOK_COVER, paints[name])

    _add_cells(surf, knots, np.ones((3, 1, 4), bool), chart)
    mesh, albedo = _bake(surf, px_per_mm=3.0)
    return mesh, albedo, {"roughness": 0.55, "specular": 0.35}


# ---------------------------------------------------------------------------------------------
# 9. The duck: a smooth organic blob with a concave neck, a beak and painted eyes

_DUCK_HEAD = (np.array([0.022, 0.0, 0.068]), 0.019)
_DUCK_EYE = np.array([0.34, 0.85, 0.40]) / np.linalg.norm([0.34, 0.85, 0.40])
"""Direction from the head's centre to the (+y) eye."""


def _duck_parts(p):
    body = _smin(_ellipsoid(p, np.array([0.0, 0.0, 0.030]), np.array([0.044, 0.033, 0.027])),
                 _ellipsoid(p, np.array([-0.037, 0.0, 0.043]), np.array([0.016, 0.014, 0.010])), 0.010)
    head = np.linalg.norm(p - _DUCK_HEAD[0], axis=1) - _DUCK_HEAD[1]
    beak = _ellipsoid(p, np.array([0.042, 0.0, 0.064]), np.array([0.012, 0.0095, 0.0045]))
    return {"body": body, "head": head, "beak": beak}


def _duck_sdf(p):
    parts = _duck_parts(p)
    d = _smin(_smin(parts["body"], parts["head"], 0.014), parts["beak"], 0.003)
    return _smax(d, 0.008 - p[:, 2], 0.002)  # a flat bottom to stand on


def _paint_duck_eye(side: int):
    def paint(img, to_px, s):
        c, r = _DUCK_HEAD
        e = c + r * _DUCK_EYE * np.array([1.0, side, 1.0])
        u, v = (-e[0] if side > 0 else e[0]), e[2]
        _circle(img, to_px, u, v, 0.0032, s, (20, 20, 24))
        _circle(img, to_px, u + 0.001 * (-side), v + 0.001, 0.0009, s, (250, 250, 250))
    return paint


def _make_duck():
    v, f, n = _sdf_mesh(_duck_sdf, (-0.055, -0.034, 0.008), (0.055, 0.034, 0.088), 0.0009, 14000)
    P, N = v[f], n[f]
    parts = _duck_parts(P.mean(1))
    names = list(parts)
    which = np.argmin(np.stack([parts[k] for k in names]), axis=0)
    surf = _Surface()
    yellow, orange = (250, 206, 40), (240, 120, 30)
    for k in names:
        sel = which == names.index(k)
        paints = {"head+y": _paint_duck_eye(1), "head-y": _paint_duck_eye(-1)} if k == "head" else None
        _add_box_charts(surf, k, P[sel], N[sel], orange if k == "beak" else yellow, paints)
    mesh, albedo = _bake(surf, px_per_mm=4.0)
    return mesh, albedo, {"roughness": 0.3, "specular": 0.5}


# ---------------------------------------------------------------------------------------------
# The registry


@dataclass(frozen=True)
class SuiteObject:
    """One object of the suite."""

    name: str
    tags: tuple[str, ...]
    """Kinds, from TAGS."""
    description: str
    symmetry: Symmetry = NO_SYMMETRY
    """The expected symmetry (shape and texture together), for checking a symmetry detector."""
    maker: Callable | None = None
    """Returns (mesh, albedo, material); None for the shipped samples."""


TAGS = {
    "textured": "printed all over: the albedo varies",
    "textureless": "one uniform colour",
    "dark": "mean linear albedo below 0.08",
    "glossy": "roughness at most 0.35",
    "metallic": "a metal (material metallic 1)",
    "thin": "has parts a few millimetres thin (a handle, a trigger, a plate)",
    "concave": "volume below 85 % of its convex hull's",
    "fine": "millimetre detail in the shape (buttons, teeth, holes)",
    "symmetric": "a rotation maps it, shape and texture, onto itself",
    "flat": "smallest extent at most 0.4 x the middle one",
    "tall": "height at least 1.45 x the larger horizontal extent",
    "organic": "a smooth free-form shape",
}
"""The kinds an object can be tagged with, and what each means."""

SUITE_OBJECTS: dict[str, SuiteObject] = {o.name: o for o in (
    SuiteObject("box", ("textured", "tall"), "printed cardboard box 90 x 60 x 140 mm (shipped sample)"),
    SuiteObject("bottle", ("textured", "glossy", "tall"),
                "glossy water bottle 70 x 150 mm, body of revolution with a wrap-around label (shipped sample)"),
    SuiteObject("mug", ("textured", "glossy", "concave", "thin"),
                "glazed ceramic mug 80 mm across, hollow (4 mm wall), a handle, a print on one side", maker=_make_mug),
    SuiteObject("cube_plain", ("textureless", "symmetric"), "plain matte 50 mm cube of one colour",
                Symmetry(24), _make_cube),
    SuiteObject("can", ("textureless", "symmetric", "glossy", "metallic"),
                "plain tin can 75 x 105 mm, beaded wall, recessed ends; symmetric top to bottom",
                Symmetry(2, (0.0, 0.0, 1.0)), _make_can),
    SuiteObject("bracket", ("textureless", "concave", "thin", "fine"),
                "grey L angle bracket, unequal legs 60 / 45 mm, 5 mm plate, three bolt holes", maker=_make_bracket),
    SuiteObject("remote", ("dark", "fine", "flat"),
                "near-black remote control 48 x 175 x 18 mm with 24 raised buttons and small print",
                maker=_make_remote),
    SuiteObject("spray", ("textured", "thin", "tall", "concave"),
                "spray bottle 216 mm tall: labelled body, trigger head, thin trigger and nozzle", maker=_make_spray),
    SuiteObject("gear", ("fine", "flat", "metallic", "glossy", "concave"),
                "brass spur gear 60 mm, 28 teeth, 16 mm thick, keyed bore and five windows", maker=_make_gear),
    SuiteObject("book", ("textured", "tall", "flat"),
                "hardcover book 150 x 30 x 220 mm standing upright, printed cover, spine and page edges",
                maker=_make_book),
    SuiteObject("duck", ("glossy", "concave", "organic"),
                "rubber duck 100 mm long, smooth blob with a concave neck, beak and painted eyes", maker=_make_duck),
)}
"""Name -> object, samples first."""

SUITE: tuple[str, ...] = tuple(SUITE_OBJECTS)
"""The names of the suite's objects (the samples and the generated ones), for benchmarks to loop over."""


def suite_version() -> str:
    """The cache key of the generated objects: SUITE_VERSION and a hash of the code that makes them."""
    digest = hashlib.sha256()
    for module in (Path(__file__), Path(__file__).with_name("objects.py")):
        digest.update(module.read_bytes())
    return f"v{SUITE_VERSION}-{digest.hexdigest()[:10]}"


def _object(name: str) -> SuiteObject:
    if name not in SUITE_OBJECTS:
        raise ConfigError(f"unknown suite object {name!r}", f"choose one of {', '.join(SUITE)}")
    return SUITE_OBJECTS[name]


def write_suite_object(name: str, out: str | Path) -> Path:
    """Generate the suite object `name` into the directory `out` (files, then the manifest) and return it."""
    obj = _object(name)
    if obj.maker is None:
        return write_object(out, name, _MAKERS[name]())
    extra = {"tags": list(obj.tags), "symmetry": obj.symmetry.label, "suite_version": suite_version()}
    return write_object(out, name, obj.maker(), source="n2d_sim.suite", label="suite object",
                        info_extra=obj.symmetry.bop(), extra=extra)


def suite_cache() -> Path:
    """The cache directory of this version of the suite ($N2D_SUITE_DIR or ~/.cache/n2d/suite, then the version)."""
    root = os.environ.get("N2D_SUITE_DIR") or Path.home() / ".cache" / "n2d" / "suite"
    return Path(root) / suite_version()


def suite_object_dir(name: str, cache: str | Path | None = None) -> Path:
    """The model directory of the suite object `name`, generated on first use.

    Samples are the package's own directories. Generated objects live in `cache/<version>/<name>` (default:
    `suite_cache()`); an object is generated into a temporary sibling and renamed into place, so a half-written
    one is never taken for complete, and two processes racing both end up with the same complete directory.
    """
    obj = _object(name)
    if obj.maker is None:
        return sample_object_dir(name)
    root = Path(cache) / suite_version() if cache is not None else suite_cache()
    target = root / name
    if _complete(target):
        return target
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", suffix=".partial", dir=root))
    try:
        write_suite_object(name, tmp)
        if target.exists() and not _complete(target):
            shutil.rmtree(target, ignore_errors=True)
        try:
            os.rename(tmp, target)
        except OSError:
            if not _complete(target):  # someone else's half-written directory in the way: not ours to keep
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def _complete(directory: Path) -> bool:
    try:
        manifest = read_manifest(directory)
    except ContractError:  # a corrupt manifest: an incomplete object
        return False
    return bool(manifest and manifest.get("complete") and manifest.get("kind") == "model"
                and manifest.get("extra", {}).get("suite_version") == suite_version())


# ---------------------------------------------------------------------------------------------
# Contact sheet


def _look_at(eye: np.ndarray) -> np.ndarray:
    """T_cam_obj of an OpenCV camera at `eye` looking at the origin, the object's z up in the image."""
    f = -eye / np.linalg.norm(eye)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, f])
    T[:3, 3] = -T[:3, :3] @ eye
    return T


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Positions, UVs, normals and F x 3 x 3 (v, vt, vn) corner indices of a triangle OBJ as written here."""
    rows: dict[str, list] = {"v": [], "vt": [], "vn": [], "f": []}
    for line in path.read_text().splitlines():
        key, _, rest = line.partition(" ")
        if key == "f":
            rows["f"].append([[int(i) - 1 for i in corner.split("/")] for corner in rest.split()])
        elif key in rows:
            rows[key].append([float(x) for x in rest.split()])
    return (np.array(rows["v"]), np.array(rows["vt"]), np.array(rows["vn"]), np.array(rows["f"], np.int64))


def render_views(directory: str | Path, size: int = 240,
                 views=((-60.0, 25.0), (130.0, 40.0))) -> list[np.ndarray]:
    """Shaded renders (RGB uint8, light grey background) of a model directory from (azimuth, elevation)
    degrees: its texture from n2d_common.raster.render_textured, times a Lambert term of the OBJ's normals."""
    from n2d_common.raster import rasterize, render_textured

    directory = Path(directory)
    vertices, uvs, normals, corners = _read_obj(directory / "mesh.obj")
    faces = corners[..., 0]
    texture = cv2.cvtColor(cv2.imread(str(directory / "albedo.png"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    extent = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    dist = 3.0 * extent
    f = size * dist / (1.2 * extent)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    light = np.array([-0.35, -0.55, -1.0]) / np.linalg.norm([-0.35, -0.55, -1.0])
    out = []
    for az, el in views:
        a, e = math.radians(az), math.radians(el)
        T = _look_at(dist * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]))
        rgb, mask = render_textured(vertices, faces, uvs[corners[..., 1]], texture, K, T, size, size)
        raster = rasterize(vertices @ T[:3, :3].T + T[:3, 3], faces, K, size, size)
        n = np.einsum("pk,pkc->pc", raster.bary[mask], normals[corners[raster.face[mask], :, 2]]) @ T[:3, :3].T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        shade = 0.3 + 0.7 * np.clip(n @ light, 0.0, 1.0)
        img = np.full((size, size, 3), 232, np.uint8)
        img[mask] = np.clip(rgb[mask] * shade[:, None], 0, 255).astype(np.uint8)
        out.append(img)
    return out


def contact_sheet(out_path: str | Path, names: tuple[str, ...] = SUITE, root: str | Path | None = None,
                  per_row: int = 4, size: int = 240) -> Path:
    """Render every named object from two viewpoints into one labelled JPEG and return its path; the objects
    are `root/<name>` (as `--out` writes them), or by default `suite_object_dir(name)`."""
    tiles = []
    for name in names:
        directory = Path(root) / name if root is not None else suite_object_dir(name)
        views = render_views(directory, size)
        tile = np.concatenate(views, axis=1)
        label = np.full((30, tile.shape[1], 3), 255, np.uint8)
        info = json.loads((directory / "models_info.json").read_text())["1"]
        dims = " x ".join(f"{info[f'size_{a}']:.0f}" for a in "xyz")
        _text(label, f"{name}  {dims} mm", (6, 14), 0.45, (20, 20, 20), 1, FONT)
        _text(label, ", ".join(SUITE_OBJECTS[name].tags), (6, 26), 0.36, (90, 90, 90), 1, FONT_SMALL)
        tiles.append(np.concatenate([tile, label], axis=0))
    blank = np.full_like(tiles[0], 255)
    rows = [np.concatenate((tiles[i:i + per_row] + [blank] * per_row)[:per_row], axis=1)
            for i in range(0, len(tiles), per_row)]
    sheet = np.concatenate(rows, axis=0)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out_path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 88]):
        raise OSError(f"could not write {out_path}")
    return out_path


def main(argv: list[str] | None = None) -> None:
    """Write suite objects into a directory, render a contact sheet, or list the suite."""
    parser = argparse.ArgumentParser(prog="python -m n2d_sim.suite", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="write the objects into OUT/<name>")
    parser.add_argument("--sheet", type=Path, help="render a contact sheet of the objects into this JPEG")
    parser.add_argument("names", nargs="*", default=list(SUITE), help="objects (default: the whole suite)")
    args = parser.parse_args(argv)
    for name in args.names:
        _object(name)
    if args.out is not None:
        for name in args.names:
            path = write_suite_object(name, args.out / name)
            size = sum(f.stat().st_size for f in path.iterdir())
            print(f"{path}: {size / 1024:.0f} KiB")
    if args.sheet is not None:  # of what was just written, or else of the cached suite
        print(contact_sheet(args.sheet, tuple(args.names), args.out))
    if args.out is None and args.sheet is None:
        for o in SUITE_OBJECTS.values():
            print(f"{o.name:11s} {o.symmetry.label:28s} {', '.join(o.tags):40s} {o.description}")


if __name__ == "__main__":
    main()
