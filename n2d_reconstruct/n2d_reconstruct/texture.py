"""UV atlas and diffuse albedo: xatlas charts, then colours baked from the photos or from a colour field.

Baking from photos: every texel's surface point is projected into every training view; a view
counts where the point is visible (its depth agrees with the mesh's own depth map there), inside
the view's mask, and faces the camera. Views are blended with weights cos(view angle)^sharpness, so
the most frontal views dominate and the texture stays sharp. Texels no view sees (the base that
stood on the plate) and the gutters between charts are filled by push-pull, which also pads seams.
UVs follow the OBJ convention (v up: v = 0 is the bottom row of the image).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
import xatlas

from n2d_common.frames import inv_T, transform_points
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_common.raster import rasterize_2d, render_depth, sample_bilinear
from n2d_reconstruct.data import Views


@dataclass
class TextureConfig:
    """UV unwrapping and baking."""

    size_px: int = 1024
    """Width and height of the square albedo texture, pixels."""
    padding_px: int = 4
    """Gap between UV charts, texels (filled with the nearest chart colours: no seams under mipmapping)."""
    sharpness: float = 6.0
    """Exponent on cos(view angle) in the blend weights: higher prefers the most frontal view."""
    min_cos: float = 0.15
    """Views seeing the surface more obliquely than this (cosine of the angle) are not used."""
    depth_tolerance_m: float = 0.002
    """A texel is visible in a view when its depth is within this of the mesh's depth there, metres."""

    def __post_init__(self):
        if self.size_px < 64:
            raise ValueError("size_px must be >= 64")
        if not 0 <= self.min_cos < 1:
            raise ValueError("min_cos must be in [0, 1)")


@dataclass
class TexturedMesh:
    """A mesh with one UV per vertex (vertices are split along chart seams) and its albedo."""

    vertices: np.ndarray
    """V x 3 float64, metres."""
    faces: np.ndarray
    """F x 3 int64."""
    uvs: np.ndarray
    """V x 2 float64 in [0, 1], v up."""
    albedo: np.ndarray | None = None
    """S x S x 3 uint8 sRGB."""

    @property
    def face_uvs(self) -> np.ndarray:
        """F x 3 x 2 texture coordinates of each face corner."""
        return self.uvs[self.faces]

    def transformed(self, T: np.ndarray) -> TexturedMesh:
        """The same mesh with its vertices mapped by the 4 x 4 rigid transform `T`."""
        return TexturedMesh(transform_points(T, self.vertices), self.faces, self.uvs, self.albedo)


def unwrap(mesh: trimesh.Trimesh, cfg: TextureConfig) -> TexturedMesh:
    """Charts and packing by xatlas for an S x S texture with cfg.padding_px texels between charts."""
    atlas = xatlas.Atlas()
    # In millimetres: xatlas leaves faces under FLT_EPSILON in area out of every chart (all their UVs 0), and in
    # metres that is 0.12 mm2, 2 % of a 40k-face model of a 10 cm object, each drawn in the colour of texel (0, 0).
    atlas.add_mesh((1000.0 * mesh.vertices).astype(np.float32), mesh.faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = cfg.size_px
    pack.padding = cfg.padding_px
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, indices, uvs = atlas[0]
    return TexturedMesh(mesh.vertices[vmapping], indices.astype(np.int64), uvs.astype(np.float64))


def texel_faces(tm: TexturedMesh, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covered texels of an S x S atlas: (K x 2 (row, col) indices, K face indices, K x 3 barycentrics)."""
    px = np.stack([tm.uvs[:, 0] * size - 0.5, (1.0 - tm.uvs[:, 1]) * size - 0.5], axis=1)
    r = rasterize_2d(px, tm.faces, size, size)
    return np.argwhere(r.mask), r.face[r.mask], r.bary[r.mask].astype(np.float64)


def texels(tm: TexturedMesh, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covered texels of an S x S atlas: (K x 2 (row, col) indices, K x 3 surface points, K x 3 unit normals)."""
    idx, face, bary = texel_faces(tm, size)
    points = np.einsum("nk,nkc->nc", bary, tm.vertices[tm.faces[face]])
    normals = trimesh.Trimesh(tm.vertices, tm.faces, process=False).face_normals[face]
    return idx, points, normals


def bake_from_views(tm: TexturedMesh, views: Views, cfg: TextureConfig,
                    progress: ProgressFn = no_progress) -> np.ndarray:
    """S x S x 3 uint8 albedo blended from the photos (see the module doc); `tm` in the views' frame."""
    size = cfg.size_px
    idx, points, normals = texels(tm, size)
    acc = np.zeros((len(points), 3))
    wsum = np.zeros(len(points))
    for i in range(len(views)):
        T_cam = inv_T(views.T_turntable_cam[i])
        depth = render_depth(tm.vertices, tm.faces, views.K, T_cam, views.width, views.height)
        uv, z = views.project(i, points)
        px, ok = views.pixels(uv)
        ok &= z > 0
        pxo = px[ok]
        visible = np.zeros(len(points), dtype=bool)
        visible[ok] = (np.abs(depth[pxo[:, 1], pxo[:, 0]] - z[ok]) < cfg.depth_tolerance_m) & \
            views.masks[i][pxo[:, 1], pxo[:, 0]]
        to_cam = views.T_turntable_cam[i][:3, 3] - points
        cos = np.einsum("nc,nc->n", normals, to_cam) / np.linalg.norm(to_cam, axis=1)
        use = visible & (cos > cfg.min_cos)
        w = cos[use] ** cfg.sharpness
        acc[use] += w[:, None] * _bilinear(views.rgb[i], uv[use])
        wsum[use] += w
        progress(Progress((i + 1) / len(views), "texturing", message=f"view {i + 1}/{len(views)}"))
    seen = wsum > 0
    colours = np.zeros((len(points), 3))
    colours[seen] = acc[seen] / wsum[seen, None]
    return _assemble(idx[seen], colours[seen], size)


def bake_from_function(tm: TexturedMesh, colour: Callable[[np.ndarray, np.ndarray], np.ndarray],
                       size: int) -> np.ndarray:
    """S x S x 3 uint8 albedo from `colour(points, normals)` (N x 3 each -> N x 3 floats in [0, 1])."""
    idx, points, normals = texels(tm, size)
    return _assemble(idx, 255.0 * np.clip(colour(points, normals), 0.0, 1.0), size)


def bake_from_surface(tm: TexturedMesh, colour: Callable[[np.ndarray, np.ndarray], np.ndarray],
                      size: int) -> np.ndarray:
    """S x S x 3 uint8 albedo from `colour(faces, bary)` (N face indices of `tm` and N x 3 barycentrics in them
    -> N x 3 floats in [0, 1]): for colours given on the mesh itself (vertex colours, another UV layout)."""
    idx, face, bary = texel_faces(tm, size)
    return _assemble(idx, 255.0 * np.clip(colour(face, bary), 0.0, 1.0), size)


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """N x 3 float samples of an H x W x 3 image at N x 2 pixel coordinates (pixel centres at integers)."""
    h, w = image.shape[:2]
    return sample_bilinear(image, np.stack([(uv[:, 0] + 0.5) / w, 1.0 - (uv[:, 1] + 0.5) / h], axis=1))


def _assemble(idx: np.ndarray, colours: np.ndarray, size: int) -> np.ndarray:
    """An S x S x 3 uint8 texture with `colours` at texels `idx`, every other texel filled by push-pull."""
    tex = np.zeros((size, size, 3))
    valid = np.zeros((size, size), dtype=bool)
    tex[idx[:, 0], idx[:, 1]] = colours
    valid[idx[:, 0], idx[:, 1]] = True
    return np.clip(np.rint(push_pull(tex, valid)), 0, 255).astype(np.uint8)


def push_pull(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill the invalid pixels of an H x W x C float image from their valid neighbourhood, coarse to fine."""
    if valid.all() or not valid.any() or min(valid.shape) <= 1:
        return image
    w = valid.astype(np.float64)[..., None]
    h2, w2 = (valid.shape[0] + 1) // 2, (valid.shape[1] + 1) // 2
    pad = ((0, 2 * h2 - valid.shape[0]), (0, 2 * w2 - valid.shape[1]), (0, 0))
    num = np.pad(image * w, pad).reshape(h2, 2, w2, 2, -1).sum((1, 3))
    den = np.pad(w, pad).reshape(h2, 2, w2, 2, 1).sum((1, 3))
    coarse = push_pull(np.where(den > 0, num / np.maximum(den, 1e-12), 0.0), den[..., 0] > 0)
    up = coarse.repeat(2, 0).repeat(2, 1)[:valid.shape[0], :valid.shape[1]]
    return np.where(valid[..., None], image, up)

