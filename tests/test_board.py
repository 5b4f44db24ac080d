"""ChArUco detection, board poses, calibration and print files, checked against exact geometry.

A synthetic board (board_image warped by a known homography) checks corner accuracy to hundredths
of a pixel; twelve 640x480 renders of the simulated turntable (one SimCamera for the module) check
poses against the simulator's ground truth and calibration against its focal length; projected
points with distortion check calibration from hand-held views. No render: print files, degenerate
inputs, serialisation.
"""

import json
import math
import re
import struct
import zlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from n2d_capture.board import (
    MIN_CORNERS,
    BoardDetection,
    CalibrationError,
    board_pose,
    corners_well_spread,
    detect_board,
)
from n2d_capture.board_print import POINTS_PER_M, write_board_print
from n2d_capture.calibration import Intrinsics, calibrate
from n2d_common.errors import ConfigError
from n2d_common.formats.board import BoardSpec, board_image
from n2d_sim import world
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

SPEC = BoardSpec()
SOURCE_PX_PER_SQUARE = 120
"""Synthetic source resolution: markers sit exactly centred in their squares, as on a good print."""
VIEWS = 12


def _rotation_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def _synthetic_view(H: np.ndarray, size: tuple[int, int], blur: float, supersample: int = 4) -> np.ndarray:
    """The board seen through homography H (board metres -> image pixels), box-filtered, then blurred."""
    src = board_image(SPEC, SOURCE_PX_PER_SQUARE / SPEC.square_m)
    s = src.shape[1] / SPEC.size_m[0]
    board_to_src = np.array([[s, 0, -0.5], [0, s, -0.5], [0, 0, 1.0]])  # board_image's pixel-centre convention
    k = supersample  # a low-res pixel i averages high-res pixels k*i .. k*i + k - 1, centred at k*i + (k-1)/2
    fine = np.array([[k, 0, (k - 1) / 2], [0, k, (k - 1) / 2], [0, 0, 1.0]])
    hi = cv2.warpPerspective(src, fine @ H @ np.linalg.inv(board_to_src), (size[0] * k, size[1] * k),
                             flags=cv2.INTER_LINEAR, borderValue=255)
    img = cv2.resize(hi, size, interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(img, (0, 0), blur) if blur else img


FRONTO = np.array([[40 / SPEC.square_m, 0, 30.3], [0, 40 / SPEC.square_m, 20.7], [0, 0, 1.0]])
OBLIQUE = cv2.getPerspectiveTransform(np.float32([[0, 0], [0.21, 0], [0.21, 0.21], [0, 0.21]]),
                                      np.float32([[120, 60], [520, 80], [580, 420], [60, 400]]))


# ---------------------------------------------------------------------------------------------
# Detection on synthetic boards


@pytest.mark.parametrize(("H", "size", "blur"), [(FRONTO, (360, 340), 0.0), (FRONTO, (360, 340), 1.0),
                                                 (OBLIQUE, (640, 480), 0.8)], ids=["sharp", "blurred", "oblique"])
def test_corners_are_unbiased_on_a_synthetic_board(H, size, blur):
    img = _synthetic_view(H, size, blur)
    det = detect_board(cv2.cvtColor(img, cv2.COLOR_GRAY2RGB), SPEC)
    assert det is not None and len(det) == (SPEC.squares_x - 1) * (SPEC.squares_y - 1)
    expected = cv2.perspectiveTransform(det.object_points[None, :, :2], H)[0]
    error = det.corners_px - expected
    assert np.linalg.norm(error, axis=1).max() < 0.05
    np.testing.assert_array_equal(det.object_points, SPEC.cv_board().getChessboardCorners()[det.ids])
    assert det.image_size == size


def test_detection_refuses_missing_and_degenerate_boards():
    assert detect_board(np.full((240, 320, 3), 200, np.uint8), SPEC) is None
    full = _synthetic_view(FRONTO, (360, 340), 1.0)
    # A corner of the board in which OpenCV finds 4 ChArUco corners: too few.
    assert detect_board(full[:170, :170], SPEC) is None
    with pytest.raises(ValueError, match="uint8"):
        detect_board(full.astype(np.float32), SPEC)
    line = np.array([[x * SPEC.square_m, SPEC.square_m, 0.0] for x in range(1, 7)])
    assert not corners_well_spread(line)
    assert corners_well_spread(np.array([[x * SPEC.square_m, y * SPEC.square_m, 0.0]
                                         for x in (1, 2, 3) for y in (1, 2)]))
    det = detect_board(full, SPEC)
    K = np.array([[800.0, 0, 180], [0, 800, 170], [0, 0, 1]])
    assert board_pose(det, K) is not None
    few = BoardDetection(det.ids[:MIN_CORNERS - 1], det.corners_px[:MIN_CORNERS - 1],
                         det.object_points[:MIN_CORNERS - 1], det.image_size)
    assert board_pose(few, K) is None
    row = np.flatnonzero(det.object_points[:, 1] == det.object_points[0, 1])
    collinear = BoardDetection(det.ids[row], det.corners_px[row], det.object_points[row], det.image_size)
    assert len(collinear) >= MIN_CORNERS and board_pose(collinear, K) is None


# ---------------------------------------------------------------------------------------------
# Rendered turntable views


@pytest.fixture(scope="module")
def rendered():
    """Twelve noisy 640x480 views of the default simulated turntable, 30 degrees apart."""
    cfg = SimWorldConfig()
    rng = np.random.default_rng(0)
    angles = [2 * math.pi * i / VIEWS for i in range(VIEWS)]
    with SimCamera(cfg) as cam:
        images = [cam.noisy(cam.render(a).rgb, rng) for a in angles]
    return cfg, angles, images


def test_board_poses_match_the_ground_truth(rendered):
    cfg, angles, images = rendered
    K = world.K(cfg)
    rot, trans, corner_err = [], [], []
    for angle, image in zip(angles, images):
        det = detect_board(image, cfg.board)
        assert det is not None and len(det) >= 10  # the object hides the board's middle
        gt = world.T_cam_board(cfg, angle)
        corner_err.append(det.corners_px - cv2.projectPoints(det.object_points, cv2.Rodrigues(gt[:3, :3])[0],
                                                             gt[:3, 3], K, None)[0].reshape(-1, 2))
        pose = board_pose(det, K)
        assert pose is not None and pose.n_corners == len(det) and pose.rms_px < 0.3
        rot.append(_rotation_deg(gt[:3, :3].T @ pose.T_cam_board[:3, :3]))
        trans.append(1000 * np.linalg.norm(gt[:3, 3] - pose.T_cam_board[:3, 3]))
    corner_err = np.concatenate(corner_err)
    assert np.sqrt(np.mean(np.sum(corner_err ** 2, axis=1))) < 0.2
    assert np.abs(corner_err.mean(0)).max() < 0.05  # no half-pixel bias left
    assert np.median(rot) <= 0.1 and max(rot) < 0.3, rot
    assert np.median(trans) <= 1.0 and max(trans) < 3.0, trans


def test_calibration_from_the_turntable_sweep_recovers_the_focal_length(rendered):
    cfg, _, images = rendered
    detections = [detect_board(image, cfg.board) for image in images]
    size = (cfg.width, cfg.height)
    intr = calibrate(detections, size, fix_principal_point=True, fix_aspect_ratio=True, zero_distortion=True)
    assert intr.fx == pytest.approx(cfg.focal_px, rel=0.005) and intr.fy == intr.fx
    assert (intr.cx, intr.cy) == ((cfg.width - 1) / 2, (cfg.height - 1) / 2)
    assert not intr.dist.any() and intr.views == VIEWS and intr.rms_px < 0.2
    # The board on the plate stays in one plane: with more unknowns the views are degenerate.
    with pytest.raises(CalibrationError, match="parallel planes"):
        calibrate(detections, size)


# ---------------------------------------------------------------------------------------------
# Calibration from hand-held views (projected points), and its errors


def _handheld_detections(K, dist, views=10, noise_px=0.05, seed=1):
    rng = np.random.default_rng(seed)
    obj = SPEC.cv_board().getChessboardCorners().astype(np.float64)
    centre = np.array([*[v / 2 for v in SPEC.size_m], 0.0])
    out = []
    while len(out) < views:
        R = cv2.Rodrigues(np.radians(rng.uniform(-35, 35, 3)) * [1, 1, 0.3] + [math.pi, 0, 0])[0]
        t = np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.35, 0.6)]) - R @ centre
        uv = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
        inside = ((uv >= 0) & (uv <= [639, 479])).all(1)
        if inside.sum() >= 20:
            uv = uv + rng.normal(0, noise_px, uv.shape)
            out.append(BoardDetection(np.flatnonzero(inside), uv[inside], obj[inside], (640, 480)))
    return out


def test_calibration_from_handheld_views_recovers_intrinsics_and_distortion():
    K = np.array([[810.0, 0, 326.0], [0, 805.0, 244.0], [0, 0, 1]])
    dist = np.array([-0.12, 0.08, 0.001, -0.0005, 0.0])
    intr = calibrate(_handheld_detections(K, dist), (640, 480))
    np.testing.assert_allclose([intr.fx, intr.fy], [810, 805], rtol=0.003)
    np.testing.assert_allclose([intr.cx, intr.cy], [326, 244], atol=1.5)
    np.testing.assert_allclose(intr.dist[:2], dist[:2], atol=0.02)
    assert intr.rms_px < 0.1 and intr.views == 10


def test_calibration_refuses_too_few_views_with_a_hint():
    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    views = _handheld_detections(K, None, views=2)
    with pytest.raises(CalibrationError, match=r"at least 3 views.*got 2 of 4 \(2 without a board") as info:
        calibrate([*views, None, None], (640, 480))
    assert info.value.hint
    with pytest.raises(CalibrationError, match="640x480 image"):
        calibrate(_handheld_detections(K, None, views=3), (1280, 960))


# ---------------------------------------------------------------------------------------------
# Intrinsics serialisation


def test_intrinsics_round_trip_through_dicts_and_camera_info():
    intr = Intrinsics(K=[[600.0, 0, 319.5], [0, 601.0, 239.5], [0, 0, 1]], dist=[0.1, -0.05, 0, 0, 0.01],
                      width=640, height=480, rms_px=0.12, views=15)
    again = Intrinsics.from_dict(json.loads(json.dumps(intr.to_dict())))
    np.testing.assert_array_equal(again.K, intr.K)
    np.testing.assert_array_equal(again.dist, intr.dist)
    assert (again.width, again.height, again.rms_px, again.views) == (640, 480, 0.12, 15)
    ros2 = Intrinsics.from_camera_info(intr.to_camera_info())
    np.testing.assert_array_equal(ros2.K, intr.K)
    assert ros2.rms_px is None and intr.to_camera_info()["p"][:4] == [600.0, 0.0, 319.5, 0.0]
    ros1 = Intrinsics.from_camera_info(SimpleNamespace(K=list(intr.K.ravel()), D=[], width=640, height=480,
                                                       distortion_model=""))
    assert ros1.fx == 600.0 and ros1.dist.tolist() == [0.0] * 5 and ros1.distortion_model == "plumb_bob"
    with pytest.raises(ConfigError, match="positive"):
        Intrinsics.from_camera_info({"k": [0.0] * 9, "d": [], "width": 640, "height": 480})
    with pytest.raises(ConfigError, match="equidistant"):
        Intrinsics.from_camera_info({"k": list(intr.K.ravel()), "d": [0] * 4, "distortion_model": "equidistant",
                                     "width": 640, "height": 480})
    with pytest.raises(ConfigError, match="missing 'K'"):
        Intrinsics.from_dict({"width": 640, "height": 480})


# ---------------------------------------------------------------------------------------------
# Print files


def _pdf_objects(pdf: bytes) -> dict[int, bytes]:
    """Object number -> body, checking that the xref table points at each object."""
    xref = int(re.search(rb"startxref\n(\d+)\n%%EOF\n$", pdf).group(1))
    assert pdf[xref:xref + 5] == b"xref\n"
    count = int(re.match(rb"xref\n0 (\d+)\n", pdf[xref:]).group(1))
    entries = re.findall(rb"(\d{10}) 00000 n \n", pdf[xref:])
    assert len(entries) == count - 1
    objects = {}
    for number, offset in enumerate(entries, start=1):
        body = re.match(rb"%d 0 obj\n(.*?)\nendobj\n" % number, pdf[int(offset):], re.S)
        assert body, f"xref entry {number} does not point at its object"
        objects[number] = body.group(1)
    return objects


def _stream(body: bytes) -> bytes:
    length = int(re.search(rb"/Length (\d+)", body).group(1))
    start = body.index(b"stream\n") + 7
    return body[start:start + length]


def _png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    chunks, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        assert struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0] == zlib.crc32(kind + body)
        chunks.append((kind, body))
        pos += 12 + length
    return chunks


def test_print_files_have_exact_physical_size(tmp_path):
    paths = write_board_print(SPEC, tmp_path, dpi=150)
    assert set(paths) == {"pdf", "png", "json"} and all(p.is_file() for p in paths.values())
    assert BoardSpec.from_dict(json.loads(paths["json"].read_text())) == SPEC

    pdf = paths["pdf"].read_bytes()
    assert pdf.startswith(b"%PDF-1.4\n")
    objects = _pdf_objects(pdf)
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", objects[3]).group(1).split()]
    sheet_w, sheet_h = SPEC.sheet_m
    assert box == pytest.approx([0, 0, sheet_w * POINTS_PER_M, sheet_h * POINTS_PER_M], abs=1e-3)
    content = _stream(objects[4]).decode()
    w, _, _, h, x, y = (float(v) for v in re.search(r"q ([\d. ]+) cm /Im0 Do Q", content).group(1).split())
    assert (w, h) == pytest.approx((SPEC.size_m[0] * POINTS_PER_M, SPEC.size_m[1] * POINTS_PER_M), abs=1e-3)
    assert (x, y) == pytest.approx((SPEC.margin_m * POINTS_PER_M,) * 2, abs=1e-3)
    assert "measure one square: should be 30 mm" in content and "DICT_5X5_100" in content
    image = objects[5]
    width, height = (int(re.search(rb"/%s (\d+)" % k, image).group(1)) for k in (b"Width", b"Height"))
    pixels = np.frombuffer(zlib.decompress(_stream(image)), np.uint8).reshape(height, width)
    np.testing.assert_array_equal(pixels, board_image(SPEC, 150 / 0.0254))

    png = paths["png"].read_bytes()
    chunks = _png_chunks(png)
    assert [c[0] for c in chunks[:2]] == [b"IHDR", b"pHYs"]
    px_per_square = round(SPEC.square_m * 150 / 0.0254)
    assert struct.unpack(">IIB", chunks[1][1]) == (round(px_per_square / SPEC.square_m),) * 2 + (1,)
    sheet = cv2.imread(str(paths["png"]), cv2.IMREAD_GRAYSCALE)
    margin = round(SPEC.margin_m * px_per_square / SPEC.square_m)
    assert sheet.shape == (7 * px_per_square + 2 * margin,) * 2
    # The printed PNG is a board whose corners sit where its resolution says.
    det = detect_board(cv2.GaussianBlur(sheet, (0, 0), 1.0), SPEC)
    expected = det.object_points[:, :2] * px_per_square / SPEC.square_m + margin - 0.5
    assert len(det) == 36 and np.abs(det.corners_px - expected).max() < 0.05


def test_print_grows_the_page_when_the_margin_cannot_hold_the_caption(tmp_path):
    spec = BoardSpec(margin_m=0.001)
    objects = _pdf_objects(write_board_print(spec, tmp_path, dpi=72)["pdf"].read_bytes())
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", objects[3]).group(1).split()]
    assert box[2] == pytest.approx(spec.sheet_m[0] * POINTS_PER_M, abs=1e-3)
    assert box[3] == pytest.approx((spec.size_m[1] + 0.001 + 0.004) * POINTS_PER_M, abs=1e-3)

