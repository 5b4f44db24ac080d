"""The simulated camera: its geometry, and rendered frames checked against that geometry.

Small renders (160x120, K scaled) check the exact object mask against the projected ground-truth
mesh; one 640x480 render checks that the ChArUco board is detectable where T_cam_turntable and
T_plate_board say it is; the object turned over in the built scene (`place`) is rendered, masked and posed
where it lies then.
"""

import math

import cv2
import numpy as np
import pytest
import trimesh

from n2d_common.config import ConfigError, from_dict, to_dict
from n2d_common.formats.board import BoardSpec, T_plate_board, board_image
from n2d_common.frames import inv_T, project, transform_points
from n2d_sim import world
from n2d_sim.camera import SimCamera
from n2d_sim.objects import SAMPLE_OBJECTS, sample_object_dir
from n2d_sim.session import turned as turned_world
from n2d_sim.world import SimWorldConfig

SMALL = dict(width=160, height=120, focal_px=150.0, samples=2, denoiser="none", background_samples=2)
"""A quarter-size camera with the same field of view, few samples: fast on 2 CPU cores."""
ANGLES = (0.0, 0.9, 2.3)


def _vertices(name: str) -> np.ndarray:
    return trimesh.load(sample_object_dir(name) / "mesh.obj", force="mesh").vertices


def _centres_inside_convex(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """HxW bool: pixel centres inside the convex hull of the Nx2 pixel coordinates `points`."""
    hull = cv2.convexHull(points.astype(np.float32)).reshape(-1, 2).astype(float)
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    sign = np.sign(cv2.contourArea(hull.astype(np.float32), oriented=True))
    inside = np.ones(shape, bool)
    for p, q in zip(hull, np.roll(hull, -1, axis=0)):
        inside &= sign * ((q[0] - p[0]) * (ys - p[1]) - (q[1] - p[1]) * (xs - p[0])) >= 0
    return inside


# ---------------------------------------------------------------------------------------------
# Geometry (no rendering)


def test_board_spec_round_trips_and_rejects_bad_values():
    spec = BoardSpec()
    assert BoardSpec.from_dict(spec.to_dict()) == spec
    assert spec.size_m == pytest.approx((0.21, 0.21))
    with pytest.raises(ConfigError):
        BoardSpec.from_dict({**spec.to_dict(), "marker_m": 0.05})
    with pytest.raises(ValueError, match="does not fit"):
        BoardSpec(squares_x=11, squares_y=11)
    with pytest.raises(ValueError, match="dictionary"):
        BoardSpec(dictionary="DICT_NOPE")


def test_board_image_has_exact_physical_scale():
    spec = BoardSpec()
    img = board_image(spec, px_per_m=4000)
    s = img.shape[1] / spec.size_m[0]
    assert img.dtype == np.uint8 and img.shape == (840, 840)
    # Square (0, 0) is black and its boundary with square (1, 0) lies on a pixel edge.
    k = round(spec.square_m * s)
    assert img[:k - 1, :k - 1].max() == 0 and img[k // 2, k] == 255


def test_board_lies_centred_and_face_up_on_the_plate():
    spec = BoardSpec()
    T = T_plate_board(spec)
    w, h = spec.size_m
    np.testing.assert_allclose(transform_points(T, [[w / 2, h / 2, 0]]), [[0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0])  # board x along plate +X
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1])  # board z into the board, i.e. down
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_camera_sees_the_whole_plate_and_looks_at_its_target():
    cfg = SimWorldConfig()
    K = world.K(cfg)
    assert K[0, 2] == (cfg.width - 1) / 2 and K[1, 2] == (cfg.height - 1) / 2
    T = world.T_cam_turntable(cfg)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    target = [[0, 0, cfg.camera_target_height_m]]
    np.testing.assert_allclose(project(K, T, target), [[K[0, 2], K[1, 2]]], atol=1e-9)
    centre = inv_T(T)[:3, 3]
    assert np.linalg.norm(centre - target[0]) == pytest.approx(cfg.camera_distance_m)
    assert math.degrees(math.asin((centre[2] - target[0][2]) / cfg.camera_distance_m)) == pytest.approx(
        cfg.camera_elevation_deg)
    with pytest.raises(ValueError, match="whole plate"):
        SimWorldConfig(camera_distance_m=0.2)


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_object_stands_on_the_plate_centre_and_turns_with_it(name):
    cfg = SimWorldConfig(object=name)
    v = _vertices(name)
    for angle in ANGLES:
        p = transform_points(world.T_turntable_obj(cfg, angle), v)
        assert p[:, 2].min() == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose((p.min(0) + p.max(0))[:2] / 2, 0, atol=0.004)  # rotated bbox stays centred
    T0, T1 = world.T_turntable_obj(cfg, 0.0), world.T_turntable_obj(cfg, 0.9)
    R = T0[:3, :3].T @ T1[:3, :3]
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(0.9)


def test_config_round_trips_through_a_plain_dict():
    cfg = SimWorldConfig(object="bottle", board=BoardSpec(square_m=0.028, marker_m=0.021))
    assert from_dict(SimWorldConfig, to_dict(cfg)) == cfg
    with pytest.raises(ConfigError):
        from_dict(SimWorldConfig, {"object": "teapot"})


def test_noise_is_fresh_and_follows_the_sensor_model():
    cam = SimCamera(SimWorldConfig(read_noise_dn=2.0, shot_noise=0.5))  # noisy() needs no worker
    flat = np.full((200, 200, 3), 100, np.uint8)
    a, b = cam.noisy(flat, np.random.default_rng(1)), cam.noisy(flat, np.random.default_rng(2))
    assert a.dtype == np.uint8 and not np.array_equal(a, b)
    assert a.astype(float).mean() == pytest.approx(100, abs=0.1)
    assert a.astype(float).std() == pytest.approx(math.sqrt(2.0**2 + 0.5 * 100), rel=0.05)


# ---------------------------------------------------------------------------------------------
# Rendered frames


@pytest.fixture(scope="module", params=SAMPLE_OBJECTS)
def small_frames(request):
    cfg = SimWorldConfig(object=request.param, **SMALL)
    with SimCamera(cfg) as cam:
        frames = [cam.render(a) for a in ANGLES]
        again = cam.render(ANGLES[1] + 2 * math.pi)
    return request.param, cfg, frames, again


def test_mask_matches_the_projected_ground_truth_mesh(small_frames):
    name, cfg, frames, _ = small_frames
    v = _vertices(name)
    for frame in frames:
        assert frame.rgb.shape == (cfg.height, cfg.width, 3) and frame.rgb.dtype == np.uint8
        assert frame.mask.shape == (cfg.height, cfg.width) and frame.mask.dtype == bool
        np.testing.assert_allclose(frame.T_cam_obj, world.T_cam_obj(cfg, frame.angle_rad))
        uv = project(frame.K, frame.T_cam_obj, v)
        dilated = cv2.dilate(frame.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        x, y = np.round(uv).astype(int).T
        assert dilated[y, x].mean() >= 0.995
        ys, xs = np.nonzero(frame.mask)
        # Pixel centres inside the silhouette: the mask's extent is the projected one, rounded inwards.
        np.testing.assert_allclose([xs.min(), ys.min()], uv.min(0), atol=1.0)
        np.testing.assert_allclose([xs.max(), ys.max()], uv.max(0), atol=1.0)
        # Planar depth on the object lies between the nearest and farthest vertex.
        z = transform_points(frame.T_cam_obj, v)[:, 2]
        d = frame.depth[frame.mask]
        assert z.min() - 1e-3 <= d.min() and d.max() <= z.max() + 1e-3
        assert (frame.depth[~frame.mask] > 0).all()
        if name == "box":  # convex: the exact mask is the set of pixel centres inside the projected hull
            assert (_centres_inside_convex(uv, frame.mask.shape) != frame.mask).sum() <= 2


def test_mask_follows_the_plate_and_repeats_are_cached(small_frames):
    _, _, frames, again = small_frames
    assert not np.array_equal(frames[0].mask, frames[1].mask)
    assert not np.array_equal(frames[1].mask, frames[2].mask)
    assert again.render_s == 0.0 and again.rgb is frames[1].rgb
    assert again.angle_rad == pytest.approx(ANGLES[1] + 2 * math.pi)  # the angle asked for, not wrapped
    np.testing.assert_allclose(again.T_cam_obj, frames[1].T_cam_obj, atol=1e-12)


def test_charuco_board_is_detected_where_the_ground_truth_puts_it():
    cfg = SimWorldConfig(background_samples=4)
    angle = 0.8
    with SimCamera(cfg) as cam:
        frame = cam.render(angle)
        image = cam.noisy(frame.rgb, np.random.default_rng(0))
    assert frame.rgb.std() > 20  # a real picture, not a blank frame
    board = cfg.board.cv_board()
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    assert ids is not None and len(ids) >= 8
    # OpenCV 4.11 reports ChArUco corners +0.5 px off; cornerSubPix removes the bias.
    corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    T_cam_board = frame.T_cam_turntable @ world.T_turntable_plate(angle) @ T_plate_board(cfg.board)
    np.testing.assert_allclose(T_cam_board, world.T_cam_board(cfg, angle))
    expected = project(frame.K, T_cam_board, board.getChessboardCorners()[ids.ravel()])
    error = np.linalg.norm(corners.reshape(-1, 2) - expected, axis=1)
    assert error.mean() < 0.4 and error.max() < 1.0, error


@pytest.mark.slow
def test_turned_over_in_the_built_scene_the_frames_and_truth_follow():
    cfg = SimWorldConfig(object="box", **SMALL)
    turned = turned_world(cfg)
    v = _vertices("box")
    with SimCamera(cfg) as cam:
        upright = cam.render(ANGLES[1])
        cam.place(turned.placement_deg)
        lying = cam.render(ANGLES[1])  # the same angle: not the cached upright frame
        cam.place(cfg.placement_deg)
        back = cam.render(ANGLES[1])
    np.testing.assert_allclose(lying.T_cam_obj, world.T_cam_obj(turned, ANGLES[1]))
    assert lying.render_s > 0 and not np.array_equal(lying.mask, upright.mask)
    # the convex box's exact mask is the projected hull of its mesh where it lies now
    uv = project(lying.K, lying.T_cam_obj, v)
    assert (_centres_inside_convex(uv, lying.mask.shape) != lying.mask).sum() <= 2
    np.testing.assert_array_equal(back.mask, upright.mask)
    np.testing.assert_allclose(back.T_cam_obj, upright.T_cam_obj)
