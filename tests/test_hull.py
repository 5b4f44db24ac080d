"""The visual hull of exact masks, and pulling a mesh back inside it: a ball seen by a ring of cameras."""

import numpy as np
import pytest
import trimesh
from helpers import look_at

from n2d_reconstruct.data import Views
from n2d_reconstruct.hull import HullConfig, VisualHull, pull_inside

RADIUS_M = 0.03
CENTRE = np.array([0.0, 0.0, 0.05])
K = np.array([[300.0, 0.0, 80.0], [0.0, 300.0, 60.0], [0.0, 0.0, 1.0]])


def _ball_views(n: int = 12) -> Views:
    """`n` cameras on a ring 0.3 m away at 30 degrees elevation; each mask is the ball's exact outline (a disc)."""
    azimuth = np.arange(n) * 2 * np.pi / n
    eyes = CENTRE + 0.3 * np.stack([np.cos(azimuth) * np.cos(np.pi / 6), np.sin(azimuth) * np.cos(np.pi / 6),
                                    np.full(n, np.sin(np.pi / 6))], 1)
    radius_px = K[0, 0] * np.tan(np.arcsin(RADIUS_M / 0.3))
    v, u = np.mgrid[0:120, 0:160]
    disc = (u - K[0, 2]) ** 2 + (v - K[1, 2]) ** 2 <= radius_px ** 2
    return Views(np.zeros((n, 120, 160, 3), np.uint8), np.repeat(disc[None], n, 0), K,
                 np.stack([look_at(e, CENTRE) for e in eyes]), [f"{i:04d}.png" for i in range(n)])


def test_a_bump_outside_the_hull_is_pulled_back_and_the_true_surface_barely_moves():
    views = _ball_views()
    hull = VisualHull(views, HullConfig())
    assert hull.pixel_m == np.linalg.norm(views.T_turntable_cam[0, :3, 3]) / 300.0  # at the turntable centre
    ball = _ball()
    # the true surface is inside the hull, to a fraction of the masks' pixel
    assert hull(ball.vertices).max() < 0.5 * hull.pixel_m

    bumped = ball.vertices.copy()
    # a 4 mm bump on the side: outside the hull (the cameras' rims cover the sides, not the top above 30 degrees)
    side = bumped[:, 0] > CENTRE[0] + 0.9 * RADIUS_M
    bumped[side] += 0.004 * ball.vertex_normals[side]
    mesh = trimesh.Trimesh(bumped, ball.faces, process=False)
    slack = 0.25 * hull.pixel_m
    pulled, stats = pull_inside(mesh, hull, slack)
    assert hull(pulled.vertices[side]).max() < slack + 0.05 * hull.pixel_m  # back to the slack, to a few passes
    assert np.linalg.norm(pulled.vertices - CENTRE, axis=1)[side].max() < RADIUS_M + 0.0015  # the hull's own gaps
    # the rest moves only where the binary masks' hull cuts into the true ball by more than the slack
    assert np.linalg.norm(pulled.vertices - ball.vertices, axis=1)[~side].max() < 0.1 * hull.pixel_m
    assert stats["moved_fraction"] >= side.mean() and 3.0 < stats["max_move_mm"] < 5.0
    assert len(pulled.faces) == len(ball.faces) and pulled.is_watertight


def _ball() -> trimesh.Trimesh:
    ball = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_M)
    return ball.apply_translation(CENTRE)


def test_one_mask_that_misses_a_sliver_does_not_notch_the_surface_when_its_view_is_forgiven():
    views = _ball_views()
    views.masks[3, :, int(K[0, 2]) + 10:] = False  # view 3's mask lost the ball's right edge (about 7 px)
    hull = VisualHull(views, HullConfig())
    ball = _ball()
    slack = 0.25 * hull.pixel_m
    notched, notched_stats = pull_inside(ball, hull, slack)
    kept, kept_stats = pull_inside(ball, lambda p: hull.lenient(p, 0.75 * hull.pixel_m), slack)
    assert notched_stats["max_move_mm"] > 2.0  # pulled into the notch
    # only where the notch is shallower than the 0.75 px forgiven (its rim) is the ball pulled in, by less
    assert np.linalg.norm(kept.vertices - ball.vertices, axis=1).max() < 0.75 * hull.pixel_m
    assert kept_stats["moved_fraction"] < 0.2 * notched_stats["moved_fraction"]
    # where the masks agree, the true ball is pulled as by the whole hull
    exact = VisualHull(_ball_views(), HullConfig())
    strict, _ = pull_inside(ball, exact, slack)
    lenient, _ = pull_inside(ball, lambda p: exact.lenient(p, 0.75 * exact.pixel_m), slack)
    assert np.linalg.norm(strict.vertices - lenient.vertices, axis=1).max() < 0.1 * exact.pixel_m


def test_a_vertex_whose_normal_points_inwards_is_not_pushed_out():
    views = _ball_views()
    hull = VisualHull(views, HullConfig())
    ball = _ball()
    inflated = trimesh.Trimesh(CENTRE + 1.1 * (ball.vertices - CENTRE), ball.faces[:, ::-1], process=False)
    before = hull(inflated.vertices)
    pulled, stats = pull_inside(inflated, hull, 0.25 * hull.pixel_m)  # the normals of a mesh turned inside out
    assert np.all(hull(pulled.vertices) <= before + 1e-12)
    assert stats["moved_fraction"] == 0.0


def test_a_slack_that_is_not_a_number_is_refused():
    with pytest.raises(ValueError, match="slack_px must be a number"):
        HullConfig(slack_px=float("nan"))


def test_forgiving_as_many_views_as_there_are_is_refused_and_lenient_needs_a_view_to_spare():
    with pytest.raises(ValueError, match="must be smaller than the number of views"):
        VisualHull(_ball_views(4), HullConfig(forgive_views=4))
    hull = VisualHull(_ball_views(4), HullConfig(forgive_views=3))  # every view but one forgiven already
    points = _ball().vertices
    assert np.array_equal(hull.lenient(points, 0.0), hull(points))
