"""The fast renderer: textured meshes, textured planes, point and sun lights with shadow maps, a gradient sky,
drawn with n2d's CPU rasterizer and shaded per pixel in numpy (no bpy, no OpenGL).

It renders the same labels as the Cycles path, exactly at pixel centres: the instance index (the label of the
nearest surface, 0 for everything that is not a target) and the planar depth along the optical axis (metres,
inf where nothing is hit). The image is linear RGB in the units of Blender's lights (a point light of P watts
gives P / (4 pi d^2) W/m^2; the sky is a radiance), so the same exposure code tones both paths.

Shading: Lambert diffuse plus a normalised Blinn-Phong lobe whose exponent follows the roughness, metals tint
their highlights with the albedo; a hemisphere term lights from the sky. Shadows come from a depth map rendered
from each shadowing light over the meshes (planes receive shadows, they cast none), filtered over a few taps so
their edges are soft. Frames: world Z up; cameras are OpenCV (x right, y down, z forward), `T_world_cam`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from n2d_common.frames import inv_T
from n2d_common.raster import rasterize

NEAR_M = 1e-3
"""Surfaces nearer to the camera than this (metres) are not drawn."""
SHADOW_MAP_PX = 384
"""Width and height of a light's shadow map, pixels."""
REMAP_COLUMNS = 4096
"""Texture lookups go through cv2.remap in rows of this many samples."""
SHADOW_TAPS = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
"""Shadow map texels averaged per lookup (percentage-closer filtering): softens shadow edges."""


@dataclass
class Material:
    """How a surface reflects light."""

    roughness: float = 0.5
    """0 mirror-like .. 1 matte: sets the highlight's width."""
    specular: float = 0.5
    """Strength of the highlight of a dielectric (Blender's Specular IOR Level: 0.5 is 4 % at normal incidence)."""
    metallic: float = 0.0
    """1: the highlight takes the albedo's colour and there is no diffuse part."""


@dataclass
class Body:
    """A textured mesh placed in the world."""

    vertices: np.ndarray
    """V x 3 object-frame vertices, metres."""
    faces: np.ndarray
    """F x 3 vertex indices."""
    corner_normals: np.ndarray
    """F x 3 x 3 unit normals at each face corner, object frame."""
    face_uvs: np.ndarray
    """F x 3 x 2 texture coordinates (OBJ convention, v up); values beyond [0, 1] repeat the texture."""
    texture: np.ndarray
    """Ht x Wt x 3 float32 linear albedo."""
    T_world: np.ndarray
    """4 x 4 pose in the world."""
    material: Material = field(default_factory=Material)
    label: int = 0
    """Instance index written into the label image (0: not a target)."""


@dataclass
class Plane:
    """A textured rectangle origin + s * u + t * v, 0 <= s <= size[0], 0 <= t <= size[1] (floor, walls)."""

    origin: np.ndarray
    u: np.ndarray
    """Unit vector along the first side."""
    v: np.ndarray
    """Unit vector along the second side; the normal is u x v."""
    size: tuple[float, float]
    texture: np.ndarray
    """Ht x Wt x 3 float32 linear albedo, repeated every `period_m`."""
    period_m: float
    material: Material = field(default_factory=Material)


@dataclass
class Light:
    """A point light (`position`) or a sun (`direction` towards the light)."""

    color: np.ndarray
    """Linear RGB power: watts for a point light, W/m^2 of irradiance for a sun."""
    position: np.ndarray | None = None
    direction: np.ndarray | None = None
    shadow: bool = True


@dataclass
class Sky:
    """A gradient from the horizon to the zenith: background and hemisphere light."""

    horizon: np.ndarray
    zenith: np.ndarray
    strength: float = 1.0

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """N x 3 radiance seen along N x 3 unit world directions."""
        t = np.clip(0.5 + 0.5 * directions[:, 2:3], 0.0, 1.0)
        return self.strength * ((1 - t) * self.horizon + t * self.zenith)


@dataclass
class RasterScene:
    """Everything the fast renderer draws."""

    bodies: list[Body]
    planes: list[Plane]
    lights: list[Light]
    sky: Sky


@dataclass
class Geometry:
    """What the camera sees at each pixel: the labels and what shading needs."""

    index: np.ndarray
    """H x W int32 instance label."""
    depth: np.ndarray
    """H x W float32 planar depth, metres (inf: sky)."""
    kind: np.ndarray
    """H x W int8: -1 sky, 0 body, 1 + k plane k."""
    face: np.ndarray
    """H x W int32 face of the merged meshes (-1 where none is visible)."""
    bary: np.ndarray
    """H x W x 3 float32 barycentrics in that face."""
    rays: np.ndarray
    """H x W x 3 world direction of each pixel's ray, scaled so that depth * ray + eye is the surface point."""
    eye: np.ndarray
    focal_px: float


class MergedMeshes:
    """The scene's meshes as one: world vertices, faces, and per face its body, UVs and normals."""

    def __init__(self, bodies: list[Body]):
        verts, faces, body, uvs, normals = [], [], [], [], []
        offset = 0
        for k, b in enumerate(bodies):
            R, t = b.T_world[:3, :3], b.T_world[:3, 3]
            verts.append(b.vertices @ R.T + t)
            faces.append(b.faces + offset)
            offset += len(b.vertices)
            body.append(np.full(len(b.faces), k, np.int32))
            uvs.append(b.face_uvs)
            normals.append(b.corner_normals @ R.T)
        empty = not bodies
        self.vertices = np.zeros((0, 3)) if empty else np.concatenate(verts)
        self.faces = np.zeros((0, 3), np.int64) if empty else np.concatenate(faces)
        self.body = np.zeros(0, np.int32) if empty else np.concatenate(body)
        self.uvs = np.zeros((0, 3, 2)) if empty else np.concatenate(uvs)
        self.normals = np.zeros((0, 3, 3)) if empty else np.concatenate(normals)
        self.labels = np.array([b.label for b in bodies] or [0], np.int32)


def corner_normals(vertices: np.ndarray, faces: np.ndarray, crease_deg: float = 30.0) -> np.ndarray:
    """F x 3 x 3 shading normals: at each face corner, the area-weighted mean of the normals of the faces around
    that point (vertices at the same position count as one, so UV seams do not show) that turn less than
    `crease_deg` from this face. Edges sharper than that stay sharp."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length: twice the area
    unit = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    _, point = np.unique(np.round(v / 1e-7), axis=0, return_inverse=True)
    corner_point = point.reshape(-1)[f].ravel()
    corner_face = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(corner_point, kind="stable")
    sorted_point = corner_point[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_point)) + 1]
    counts = np.diff(np.r_[starts, len(sorted_point)])
    group = np.repeat(np.arange(len(starts)), counts)
    reps = counts[group]
    a = np.repeat(np.arange(len(sorted_point)), reps)
    b = starts[group[a]] + np.arange(len(a)) - np.repeat(np.cumsum(reps) - reps, reps)
    fa, fb = corner_face[order[a]], corner_face[order[b]]
    ok = np.einsum("ij,ij->i", unit[fa], unit[fb]) > np.cos(np.radians(crease_deg))
    target = order[a][ok]
    acc = np.stack([np.bincount(target, fn[fb[ok], c], minlength=len(corner_face)) for c in range(3)], 1)
    acc /= np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-30)
    return acc.reshape(-1, 3, 3)


def _pixel_rays(K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """H x W x 3 world ray directions with unit camera-z component (so a planar depth scales them to points)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    cam = np.stack([x, y, np.ones_like(x)], -1)
    return cam @ T_world_cam[:3, :3].T


def trace(scene: RasterScene, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
          merged: MergedMeshes | None = None) -> Geometry:
    """Labels and per-pixel geometry of the scene seen by the camera."""
    merged = merged or MergedMeshes(scene.bodies)
    T_cam_world = inv_T(T_world_cam)
    v_cam = merged.vertices @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    r = rasterize(v_cam, merged.faces, K, width, height, near=NEAR_M)
    depth = r.depth.astype(np.float64)
    kind = np.where(r.face >= 0, 0, -1).astype(np.int8)
    rays = _pixel_rays(K, T_world_cam, width, height)
    eye = T_world_cam[:3, 3]
    for k, p in enumerate(scene.planes):
        n = np.cross(p.u, p.v)
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.dot(p.origin - eye, n) / denom
        hit = eye + t[..., None] * rays - p.origin
        s, q = hit @ p.u, hit @ p.v
        ok = (t > NEAR_M) & (s >= 0) & (s <= p.size[0]) & (q >= 0) & (q <= p.size[1]) & (t < depth)
        depth = np.where(ok, t, depth)
        kind[ok] = 1 + k
    face = np.where(kind == 0, r.face, -1)
    index = np.zeros((height, width), np.int32)
    body_pixels = face >= 0
    index[body_pixels] = merged.labels[merged.body[face[body_pixels]]]
    return Geometry(index, depth.astype(np.float32), kind, face, r.bary, rays, eye, float(K[1, 1]))


def _sample(texture: np.ndarray, uv: np.ndarray, wrap: bool) -> np.ndarray:
    """N x 3 bilinear samples at N x 2 UVs (v up); repeated beyond [0, 1] when `wrap`, else clamped."""
    h, w = texture.shape[:2]
    if wrap:
        uv = uv - np.floor(uv)
    n = len(uv)
    rows = -(-n // REMAP_COLUMNS)  # cv2.remap takes maps of fewer than 32767 rows and columns
    maps = np.zeros((2, rows * REMAP_COLUMNS), np.float32)
    maps[0, :n] = uv[:, 0] * w - 0.5
    maps[1, :n] = (1.0 - uv[:, 1]) * h - 0.5
    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REPLICATE
    out = cv2.remap(texture, maps[0].reshape(rows, -1), maps[1].reshape(rows, -1), cv2.INTER_LINEAR,
                    borderMode=border)
    return out.reshape(-1, 3)[:n]


def _pyramid(texture: np.ndarray) -> list[np.ndarray]:
    """The texture and its halvings down to 4 texels across (box-filtered: a repeated texture's mean is kept)."""
    levels = [texture]
    while min(levels[-1].shape[:2]) >= 8:
        t = levels[-1]
        h, w = t.shape[0] // 2 * 2, t.shape[1] // 2 * 2
        levels.append(cv2.resize(t[:h, :w], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return levels


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


class _ShadowMap:
    """Depth of the meshes seen from a light, and the lookup that says how much of a point the light sees."""

    def __init__(self, merged: MergedMeshes, light: Light, centre: np.ndarray, radius: float):
        if light.position is not None:
            eye = np.asarray(light.position, float)
        else:  # a sun: a far point in its direction, far enough that its rays are nearly parallel
            eye = centre + light.direction / np.linalg.norm(light.direction) * max(4.0 * radius, 2.0)
        self.T_world_cam = _look_at(eye, centre)
        distance = float(np.linalg.norm(eye - centre))
        half = np.arctan2(radius, max(distance - radius, 1e-3))
        f = SHADOW_MAP_PX / 2 / np.tan(min(half * 1.1, np.radians(80)))
        c = (SHADOW_MAP_PX - 1) / 2
        self.K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
        T_cam_world = inv_T(self.T_world_cam)
        v = merged.vertices @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        self.depth = rasterize(v, merged.faces, self.K, SHADOW_MAP_PX, SHADOW_MAP_PX, near=NEAR_M).depth
        self.texel_m = distance / f

    def lit(self, points: np.ndarray) -> np.ndarray:
        """N fraction in 0..1 of the shadow map taps around each world point that the light reaches."""
        T = inv_T(self.T_world_cam)
        p = points @ T[:3, :3].T + T[:3, 3]
        z = np.maximum(p[:, 2], 1e-6)
        u = self.K[0, 0] * p[:, 0] / z + self.K[0, 2]
        v = self.K[1, 1] * p[:, 1] / z + self.K[1, 2]
        bias = 3.0 * self.texel_m * z + 2e-3
        lit = np.zeros(len(p))
        for du, dv in SHADOW_TAPS:
            x = np.clip(np.rint(u + du).astype(np.int64), 0, SHADOW_MAP_PX - 1)
            y = np.clip(np.rint(v + dv).astype(np.int64), 0, SHADOW_MAP_PX - 1)
            lit += self.depth[y, x] >= z - bias
        inside = (u >= 0) & (u < SHADOW_MAP_PX) & (v >= 0) & (v < SHADOW_MAP_PX) & (p[:, 2] > 0)
        return np.where(inside, lit / len(SHADOW_TAPS), 1.0)


def shade(scene: RasterScene, g: Geometry, merged: MergedMeshes | None = None) -> np.ndarray:
    """H x W x 3 float32 linear image of the traced scene."""
    merged = merged or MergedMeshes(scene.bodies)
    h, w = g.depth.shape
    out = np.zeros((h * w, 3), np.float32)
    rays = g.rays.reshape(-1, 3)
    view = -rays / np.linalg.norm(rays, axis=1, keepdims=True)
    kind = g.kind.ravel()
    sky_px = kind < 0
    out[sky_px] = scene.sky.radiance(-view[sky_px])
    px = np.flatnonzero(~sky_px)
    if not len(px):
        return out.reshape(h, w, 3)
    points = g.eye + g.depth.ravel()[px, None].astype(np.float64) * rays[px]
    normal = np.zeros((len(px), 3))
    albedo = np.zeros((len(px), 3), np.float32)
    rough, spec, metal = np.zeros(len(px)), np.zeros(len(px)), np.zeros(len(px))
    pk = kind[px]
    on_body = pk == 0
    if on_body.any():
        face = g.face.ravel()[px[on_body]]
        bary = g.bary.reshape(-1, 3)[px[on_body]].astype(np.float64)
        n = np.einsum("nk,nkc->nc", bary, merged.normals[face])
        normal[on_body] = n
        uv = np.einsum("nk,nkc->nc", bary, merged.uvs[face])
        which = merged.body[face]
        rows = np.flatnonzero(on_body)
        for k in np.unique(which):
            sel = which == k
            b = scene.bodies[k]
            albedo[rows[sel]] = _sample(b.texture, uv[sel], wrap=True)
            rough[rows[sel]], spec[rows[sel]], metal[rows[sel]] = (b.material.roughness, b.material.specular,
                                                                   b.material.metallic)
    for k, p in enumerate(scene.planes):
        sel = pk == 1 + k
        if not sel.any():
            continue
        rel = points[sel] - p.origin
        uv = np.stack([rel @ p.u, rel @ p.v], 1) / p.period_m
        n = np.cross(p.u, p.v)
        # Mipmapping: the pyramid level whose texels are about a pixel's footprint on the plane, so a far floor
        # shows its mean colour instead of aliasing into moire.
        slant = np.maximum(np.abs(view[px[sel]] @ n), 0.05)
        footprint = g.depth.ravel()[px[sel]] / (g.focal_px * slant) * p.texture.shape[1] / p.period_m
        pyramid = _pyramid(p.texture)
        level = np.clip(np.floor(np.log2(np.maximum(footprint, 1.0))), 0, len(pyramid) - 1).astype(int)
        rows = np.flatnonzero(sel)
        for k in np.unique(level):
            at = level == k
            albedo[rows[at]] = _sample(pyramid[k], uv[at], wrap=True)
        normal[sel] = n
        rough[sel], spec[sel], metal[sel] = p.material.roughness, p.material.specular, p.material.metallic
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    v = view[px]
    facing = np.einsum("ij,ij->i", normal, v)
    normal[facing < 0] *= -1  # a back face seen through a gap is lit as its front
    diffuse_albedo = albedo * (1 - metal)[:, None]
    f0 = (0.08 * spec)[:, None] * (1 - metal)[:, None] + albedo * metal[:, None]
    exponent = np.clip(2.0 / np.maximum(rough, 0.03) ** 4 - 2.0, 1.0, 4000.0)
    sky_up = scene.sky.radiance(normal)
    colour = diffuse_albedo * sky_up
    reflect = 2 * np.einsum("ij,ij->i", normal, v)[:, None] * normal - v
    colour += f0 * scene.sky.radiance(reflect) * (1 - 0.7 * rough)[:, None]
    centre, radius = _bounds(merged)
    for light in scene.lights:
        if light.position is not None:
            to_light = light.position - points
            d2 = np.maximum(np.einsum("ij,ij->i", to_light, to_light), 1e-6)
            to_light /= np.sqrt(d2)[:, None]
            irradiance = light.color[None, :] / (4 * np.pi * d2[:, None])
        else:
            to_light = np.broadcast_to(light.direction / np.linalg.norm(light.direction), points.shape)
            irradiance = np.broadcast_to(light.color, points.shape)
        cos = np.clip(np.einsum("ij,ij->i", normal, to_light), 0.0, None)
        lit = cos > 0
        if light.shadow and len(merged.faces):
            idx = np.flatnonzero(lit)
            vis = np.ones(len(points))
            vis[idx] = _ShadowMap(merged, light, centre, radius).lit(points[idx])
            cos = cos * vis
        half = to_light + v
        half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
        lobe = (exponent + 8) / (8 * np.pi) * np.clip(np.einsum("ij,ij->i", normal, half), 0, 1) ** exponent
        colour += irradiance * cos[:, None] * (diffuse_albedo / np.pi + f0 * lobe[:, None])
    out[px] = colour
    return out.reshape(h, w, 3)


def _bounds(merged: MergedMeshes) -> tuple[np.ndarray, float]:
    """Centre and radius of a sphere around the meshes (what shadow maps must cover)."""
    if not len(merged.vertices):
        return np.zeros(3), 1.0
    lo, hi = merged.vertices.min(0), merged.vertices.max(0)
    return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.05)


def render(scene: RasterScene, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int
           ) -> tuple[np.ndarray, Geometry]:
    """(H x W x 3 float32 linear image, the labels) of the scene seen by the camera."""
    merged = MergedMeshes(scene.bodies)
    g = trace(scene, K, T_world_cam, width, height, merged)
    return shade(scene, g, merged), g
