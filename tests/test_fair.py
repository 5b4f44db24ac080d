"""The membrane over plain surfaces, on objects photographed by a ring of cameras (images ray-traced exactly
here): a box with textured sides and a plain top whose mesh has a dome on the top, as NeuS leaves one, and a
plain ball with a printed band, which the membrane alone would pull flat."""

import numpy as np
import pytest
import trimesh
from helpers import look_at

from n2d_reconstruct.data import Views
from n2d_reconstruct.fair import FairConfig, fair_plain, patch_contrast, span

HALF = np.array([0.03, 0.03, 0.025])
CENTRE = np.array([0.0, 0.0, 0.025])
K = np.array([[300.0, 0.0, 80.0], [0.0, 300.0, 60.0], [0.0, 0.0, 1.0]])
W, H = 160, 120
BALL_M = 0.025


def _rays(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera centre relative to CENTRE and the H x W x 3 ray directions of camera pose T (turntable frame)."""
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1) @ T[:3, :3].T
    return T[:3, 3] - CENTRE, rays


def _checker(p: np.ndarray) -> np.ndarray:
    return (np.floor(p / 0.006).astype(int).sum(-1) % 2) * 160 + 40


def _render(T: np.ndarray) -> np.ndarray:
    """Grey image of the box: sides carry a 6 mm checker (texture), the top is a plain 128, the rest black."""
    origin, rays = _rays(T)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (-HALF - origin) / rays, (HALF - origin) / rays
    near = np.minimum(t0, t1).max(-1)
    hit = (near < np.maximum(t0, t1).min(-1)) & (near > 0)
    p = origin + near[..., None] * rays
    top = hit & (np.abs(p[..., 2] - HALF[2]) < 1e-9)
    grey = np.where(top, 128, np.where(hit, _checker(p), 0)).astype(np.uint8)
    return np.repeat(grey[..., None], 3, -1)


def _render_ball(T: np.ndarray) -> np.ndarray:
    """Grey image of a ball of radius BALL_M at CENTRE: plain 128 but for a checkered band 15-22 mm above its
    centre; black background."""
    origin, rays = _rays(T)
    d = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    b = d @ origin
    disc = b ** 2 - (origin @ origin - BALL_M ** 2)
    hit = disc > 0
    p = origin + (-b - np.sqrt(np.maximum(disc, 0)))[..., None] * d
    band = hit & (p[..., 2] > 0.015) & (p[..., 2] < 0.022)
    grey = np.where(band, _checker(p), np.where(hit, 128, 0)).astype(np.uint8)
    return np.repeat(grey[..., None], 3, -1)


def _views(render, n: int = 12) -> Views:
    """n cameras on a ring 0.3 m away at 45 degrees elevation; masks where the object is."""
    azimuth = np.arange(n) * 2 * np.pi / n + 0.3
    eyes = CENTRE + 0.3 * np.stack([np.cos(azimuth) * np.cos(np.pi / 4), np.sin(azimuth) * np.cos(np.pi / 4),
                                    np.full(n, np.sin(np.pi / 4))], 1)
    poses = np.stack([look_at(e, CENTRE) for e in eyes])
    images = np.stack([render(T) for T in poses])
    return Views(images, images[..., 0] > 0, K, poses, [f"{i:04d}.png" for i in range(n)])


def _domed_box() -> tuple[trimesh.Trimesh, np.ndarray]:
    """The box's mesh (3 mm edges) with a 4 mm dome over the middle of its top, and which vertices are on the top."""
    box = trimesh.creation.box(2 * HALF)
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.003)
    mesh = trimesh.Trimesh(v + CENTRE, f)
    v = mesh.vertices.copy()
    r = np.hypot(*(v[:, :2] - CENTRE[:2]).T)
    on_top = v[:, 2] > CENTRE[2] + HALF[2] - 1e-9
    v[:, 2] += np.where(on_top, 0.004 * np.clip(1 - (r / 0.02) ** 2, 0, None), 0.0)
    return trimesh.Trimesh(v, mesh.faces, process=False), on_top


def test_a_dome_on_a_plain_top_is_spanned_flat_and_textured_sides_stay():
    views = _views(_render)
    domed, on_top = _domed_box()
    contrast = patch_contrast(domed, views, FairConfig())
    inner = on_top & (np.abs(domed.vertices[:, :2] - CENTRE[:2]).max(1) < HALF[0] - 0.006)
    sides = ~on_top & (np.abs(domed.vertices[:, 2] - CENTRE[2]) < HALF[2] - 0.005)
    assert np.all(contrast[inner] < 1.0) and np.median(contrast[sides]) > 30
    out, stats = fair_plain(domed, views, FairConfig())
    top_z = CENTRE[2] + HALF[2]
    assert np.abs(out.vertices[on_top, 2] - top_z).max() < 0.0005, np.abs(out.vertices[on_top, 2] - top_z).max()
    assert np.abs(domed.vertices[on_top, 2] - top_z).max() > 0.0039
    assert np.allclose(out.vertices[sides], domed.vertices[sides])
    assert 0.1 < stats["plain_fraction"] < 0.3 and stats["max_move_mm"] == pytest.approx(4.0, abs=0.1)


def test_a_plain_patch_with_no_rim_stays_and_disabled_changes_nothing():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    assert np.array_equal(span(sphere, np.ones(len(sphere.vertices), bool)).vertices, sphere.vertices)
    assert span(sphere, np.zeros(len(sphere.vertices), bool)) is sphere
    views = _views(_render, 3)
    domed, _ = _domed_box()
    out, stats = fair_plain(domed, views, FairConfig(enabled=False))
    assert out is domed and stats is None
    with pytest.raises(ValueError, match="min_contrast"):
        FairConfig(min_contrast=float("nan"))


def test_a_plain_curved_flank_keeps_the_silhouettes_it_covered():
    """Between its band and its unseen bottom the ball is plain: the membrane alone pulls that flank taut, cutting
    into the ball; checked against the silhouettes, it stays where the outlines saw it. (The cap above the band
    is spanned: no outline sees it from 45 degrees.)"""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=BALL_M).apply_translation(CENTRE)
    views = _views(_render_ball)
    plain = patch_contrast(ball, views, FairConfig()) < FairConfig().min_contrast
    flank = (np.abs(ball.vertices[:, 2] - CENTRE[2]) < 0.008) & plain  # (patches crossing an outline are not)
    assert flank.sum() > 100
    radius = np.linalg.norm(span(ball, plain).vertices - CENTRE, axis=1)
    assert (BALL_M - radius[flank]).max() > 0.004  # the taut membrane alone cuts 5 mm into the ball's waist
    out, stats = fair_plain(ball, views, FairConfig())
    radius = np.linalg.norm(out.vertices - CENTRE, axis=1)
    below_band = ball.vertices[:, 2] < CENTRE[2] + 0.012
    assert np.abs(radius[below_band] - BALL_M).max() < 0.0003, np.abs(radius[below_band] - BALL_M).max()
    assert stats["held_by_silhouettes"] > 0.3
