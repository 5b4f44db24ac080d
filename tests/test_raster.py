"""The CPU rasterizer against analytic geometry: silhouettes, depths and barycentrics of a box, exact
single coverage along shared edges and vertices, the z-test, UV-atlas coverage and texture sampling."""

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from n2d_common.frames import transform_points
from n2d_common.raster import rasterize, rasterize_2d, render_depth, render_textured

W, H = 320, 240
K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
HALF = np.array([0.15, 0.1, 0.125])
"""Half extents of the test box, metres."""


def pose(rvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    T[:3, 3] = t
    return T


def pixel_grid(width=W, height=H) -> np.ndarray:
    """H x W x 2 pixel centres (x, y)."""
    return np.stack(np.meshgrid(np.arange(width), np.arange(height)), -1).astype(float)


def project(points_cam: np.ndarray, K=K) -> np.ndarray:
    p = points_cam @ K.T
    return p[..., :2] / p[..., 2:]


def inside_convex(points: np.ndarray, polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(strictly inside, distance to the nearest edge line) of ... x 2 points for a convex polygon."""
    hull = ConvexHull(polygon)
    normals, offsets = hull.equations[:, :2], hull.equations[:, 2]  # n . p + d <= 0 inside
    signed = points @ normals.T + offsets
    return (signed < 0).all(-1), np.abs(signed).min(-1)


def box_depth(T_cam_obj: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Planar depth of the box along each pixel's ray (slab method), inf on a miss."""
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    rays = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], -1) @ np.linalg.inv(K).T  # z = 1
    origin, direction = -R.T @ t, rays @ R  # object frame
    with np.errstate(divide="ignore"):
        t1, t2 = (-HALF - origin) / direction, (HALF - origin) / direction
    near, far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    return np.where((near <= far) & (near > 0), near, np.inf)


def test_box_silhouette_depth_and_barycentrics():
    box = trimesh.creation.box(extents=2 * HALF)
    T = pose([0.4, -0.6, 0.2], [0.02, -0.01, 0.8])
    v_cam = transform_points(T, box.vertices)
    r = rasterize(v_cam, box.faces, K, W, H)

    inside, distance = inside_convex(pixel_grid(), project(v_cam))
    assert inside.sum() > 10_000
    assert np.all((r.mask == inside) | (distance < 1e-6))

    depth = box_depth(T, pixel_grid())
    np.testing.assert_allclose(r.depth[r.mask], depth[r.mask], rtol=0, atol=1e-5)
    assert np.all(np.isinf(r.depth[~r.mask])) and np.all(r.face[~r.mask] == -1)
    assert r.mask[H // 2, W // 2] and r.depth[H // 2, W // 2] == pytest.approx(depth[H // 2, W // 2], abs=1e-5)

    point = np.einsum("nk,nkc->nc", r.bary[r.mask].astype(float), v_cam[box.faces[r.face[r.mask]]])
    np.testing.assert_allclose(project(point), pixel_grid()[r.mask], rtol=0, atol=1e-3)
    np.testing.assert_allclose(point[:, 2], r.depth[r.mask], rtol=0, atol=1e-5)
    assert np.all(r.bary[r.mask] >= -1e-6) and np.allclose(r.bary[r.mask].sum(-1), 1, atol=1e-6)


def test_box_filling_the_image():
    """Twelve big triangles, most far outside the image: every pixel is the near face, at its depth."""
    box = trimesh.creation.box(extents=(4.0, 3.0, 1.0))
    T = pose([0.05, 0.1, 0.0], [0.0, 0.0, 0.8])
    r = rasterize(transform_points(T, box.vertices), box.faces, K, W, H)
    assert r.mask.all()
    plane_normal = T[:3, :3][:, 2]  # the box's -z face: n . p = n . t - 0.5
    rays = np.concatenate([pixel_grid(), np.ones((H, W, 1))], -1) @ np.linalg.inv(K).T
    expected = (plane_normal @ T[:3, 3] - 0.5) / (rays @ plane_normal)
    np.testing.assert_allclose(r.depth, expected, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(render_depth(box.vertices, box.faces, K, T, W, H), r.depth)


def grid_mesh(n: int, jitter: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n + 1)^2 x 2 unit-square grid vertices, interior ones jittered, and its 2 n^2 triangles, half of
    them wound clockwise and half counter-clockwise."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1)), -1).reshape(-1, 2).astype(float) / n
    interior = ((g > 0) & (g < 1)).all(1)
    g[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 2)) / n
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.ravel()
    faces = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    flip = rng.random(len(faces)) < 0.5
    faces[flip] = faces[flip][:, ::-1]
    return g, faces


def coverage(raster_one, n_faces: int) -> np.ndarray:
    """How many faces cover each pixel, each face rasterised on its own."""
    return sum(raster_one(i).mask.astype(int) for i in range(n_faces))


def test_subdivided_plane_is_covered_exactly_once():
    g, faces = grid_mesh(8, jitter=0.35, seed=1)
    plane = np.concatenate([(g - 0.5) * [0.5, 0.4], np.zeros((len(g), 1))], 1)
    v_cam = transform_points(pose([0.5, 0.3, 0.1], [0.0, 0.0, 0.6]), plane)
    Ks = K * [[0.5], [0.5], [1.0]] - [[0, 0, 0.25], [0, 0, 0.25], [0, 0, 0]]  # half the resolution
    count = coverage(lambda i: rasterize(v_cam, faces[[i]], Ks, W // 2, H // 2), len(faces))
    corners = project(v_cam[[0, 8, 80, 72]], Ks)
    inside, distance = inside_convex(pixel_grid(W // 2, H // 2), corners)
    assert inside.sum() > 1_500
    assert np.all(count <= 1)
    assert np.all(((count == 1) == inside) | (distance < 1e-6))
    together = rasterize(v_cam, faces, Ks, W // 2, H // 2)
    np.testing.assert_array_equal(together.mask, count == 1)


def test_centres_on_edges_and_vertices_go_to_one_triangle():
    """Vertices on pixel centres, edges through them, both windings: each centre is drawn once."""
    g, faces = grid_mesh(6, jitter=0.0, seed=2)
    points = 4 + 6 * g * 6  # 6 px cells: vertices on centres, diagonals through centres
    count = coverage(lambda i: rasterize_2d(points, faces[[i]], 48, 48), len(faces))
    inside, distance = inside_convex(pixel_grid(48, 48), points[[0, 6, 48, 42]])
    assert np.all(count <= 1)
    assert np.all(count[inside] == 1)
    # a fan around a centre, spokes in 16 directions to integer points
    ring = np.array([[8, 0], [8, 3], [8, 8], [3, 8], [0, 8], [-5, 8], [-8, 8], [-8, 1], [-8, 0], [-8, -2],
                     [-8, -8], [-1, -8], [0, -8], [6, -8], [8, -8], [8, -5]], float)
    fan = np.concatenate([[[20.0, 20.0]], 20 + ring])
    fan_faces = np.stack([np.zeros(16, int), 1 + np.arange(16), 1 + (np.arange(16) + 1) % 16], 1)
    fan_faces[::3] = fan_faces[::3, ::-1]
    count = coverage(lambda i: rasterize_2d(fan, fan_faces[[i]], 48, 48), len(fan_faces))
    assert count[20, 20] == 1
    assert np.all(count <= 1) and np.all(count[13:28, 13:28] == 1)


def test_nearer_triangle_wins_and_near_plane_drops():
    tri = np.array([[-0.3, -0.3, 0.0], [0.3, -0.3, 0.0], [0.0, 0.3, 0.0]])
    near, far = tri + [0, 0, 0.5], tri + [0.15, 0, 0.7]
    for order in ((near, far), (far, near)):
        r = rasterize(np.concatenate(order), [[0, 1, 2], [3, 4, 5]], K, W, H)
        near_face = 0 if order[0] is near else 1
        alone = rasterize(near, [[0, 1, 2]], K, W, H)
        np.testing.assert_array_equal(r.face[alone.mask], near_face)
        np.testing.assert_allclose(r.depth[alone.mask], 0.5, atol=1e-6)
        assert np.any(r.face == 1 - near_face)  # the far one shows where the near one does not cover
    crossing = tri + [0, 0, 0.5]
    crossing[0, 2] = -0.1
    assert not rasterize(crossing, [[0, 1, 2]], K, W, H).mask.any()


def test_rasterize_2d_covers_the_texel_centres_inside():
    tri = np.array([[3.3, 4.1], [57.8, 20.5], [21.2, 60.9]])
    r = rasterize_2d(tri, [[0, 1, 2]], 64, 64)
    p = pixel_grid(64, 64)
    M = np.array([[tri[0, 0] - tri[2, 0], tri[1, 0] - tri[2, 0]], [tri[0, 1] - tri[2, 1], tri[1, 1] - tri[2, 1]]])
    l01 = np.linalg.solve(M, (p - tri[2]).reshape(-1, 2).T).T.reshape(64, 64, 2)
    bary = np.concatenate([l01, 1 - l01.sum(-1, keepdims=True)], -1)
    np.testing.assert_array_equal(r.mask, (bary > 0).all(-1))
    np.testing.assert_allclose(r.bary[r.mask], bary[r.mask], atol=1e-6)
    assert np.all(r.depth[r.mask] == 0) and np.all(r.face[r.mask] == 0)


def test_render_textured_reproduces_the_texture():
    """A fronto-parallel quad whose 64 x 64 pixels land on the 64 x 64 texel centres: exact copy, v up."""
    texture = np.random.default_rng(3).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    quad = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])  # y down
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv_corner = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])  # top of the image is v = 1
    Kq = np.array([[64.0, 0.0, 41.5], [0.0, 64.0, 41.5], [0.0, 0.0, 1.0]])  # quad spans pixels 10..73
    T = pose([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    rgb, mask = render_textured(quad, faces, uv_corner[faces], texture, Kq, T, 84, 84)
    assert mask[10:74, 10:74].all() and mask.sum() == 64 * 64
    np.testing.assert_array_equal(rgb[10:74, 10:74], texture)
    assert np.all(rgb[~mask] == 0)
    depth = render_depth(quad, faces, Kq, T, 84, 84)
    np.testing.assert_allclose(depth[mask], 1.0, atol=1e-6)
