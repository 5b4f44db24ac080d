"""Offline import of photos into a capture session: simulated views written as a user's JPEG/PNG folder,
imported with and without plate angles, checked against the simulator's ground truth; bad inputs refused."""

import json
import math

import cv2
import numpy as np
import pytest
import yaml
from helpers import write_photos

from n2d_capture.board import CalibrationError
from n2d_capture.capture import CaptureConfig
from n2d_capture.importer import import_photos, load_intrinsics, read_angles
from n2d_capture.masks import iou
from n2d_common.errors import ConfigError, ContractError
from n2d_common.formats.session import read_session
from n2d_common.frames import inv_T, rot_z
from n2d_common.images import read_png
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

ANGLES_DEG = [5.0, 52.0, 95.0, 141.0, 186.0, 230.0, 277.0, 322.0]
"""Uneven stops, as a hand-turned plate gives."""


@pytest.fixture(scope="module")
def shots():
    """Noisy views of the box and of the empty plate at ANGLES_DEG, with the exact masks (one SimCamera)."""
    world = SimWorldConfig(object="box")
    rng = np.random.default_rng(3)
    views, empties, masks = [], [], []
    with SimCamera(world) as camera:
        for angle in map(math.radians, ANGLES_DEG):
            frame = camera.render(angle)
            views.append(camera.noisy(frame.rgb, rng))
            masks.append(frame.mask)
            empties.append(camera.noisy(camera.render(angle, object_visible=False).rgb, rng))
        return {"world": world, "K": camera.K, "T_cam_turntable": camera.T_cam_turntable,
                "views": views, "empties": empties, "masks": masks}


def _photos(tmp_path, shots):
    """A folder of object photos (.JPG, plus a stray text file) and one of empty-plate photos (.png)."""
    photos = write_photos(tmp_path / "photos", shots["views"], ".JPG")
    (photos / "notes.txt").write_text("not a photo")
    return photos, write_photos(tmp_path / "empty", shots["empties"], ".png")


def _check_against_truth(session_dir, shots):
    session = read_session(session_dir)
    assert len(session.views) == len(ANGLES_DEG)
    rot, trans, ious = [], [], []
    for view, angle, gt_mask in zip(session.views, ANGLES_DEG, shots["masks"]):
        gt = inv_T(shots["T_cam_turntable"] @ rot_z(math.radians(angle)))
        R = view.T_turntable_cam[:3, :3].T @ gt[:3, :3]
        rot.append(math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
        trans.append(1000 * np.linalg.norm(view.T_turntable_cam[:3, 3] - gt[:3, 3]))
        ious.append(iou(read_png(view.mask) > 0, gt_mask))
    assert np.median(rot) <= 0.2, rot
    assert np.median(trans) <= 2.0, trans
    assert np.mean(ious) >= 0.95, ious
    return session


def _nothing_written(out):
    return not out.exists() and not out.with_name(out.name + ".partial").exists()


@pytest.mark.timeout(300)
def test_import_with_angles_file_calibrates_and_matches_ground_truth(tmp_path, shots):
    photos, empty = _photos(tmp_path, shots)
    (photos / "angles.csv").write_text("file,angle_deg\n" + "".join(
        f"IMG_{i:04d}.JPG,{a}\n" for i, a in reversed(list(enumerate(ANGLES_DEG)))))
    reports = []
    summary = import_photos(photos, tmp_path / "session", CaptureConfig(), empty_dir=empty, progress=reports.append)
    assert summary["views"] == len(ANGLES_DEG)
    fractions = [p.fraction for p in reports]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0

    session = _check_against_truth(tmp_path / "session", shots)
    assert session.K[0, 0] == pytest.approx(shots["K"][0, 0], rel=0.01)  # calibrated from the board
    info = json.loads((tmp_path / "session" / "capture.json").read_text())
    assert info["intrinsics_source"] == "calibrate" and info["fit_on"] == "empty"
    assert [v["angle_rad"] for v in info["views"]] == pytest.approx(np.radians(ANGLES_DEG))
    assert info["import"]["angles_from"] == "angles.csv"
    assert info["import"]["photos"] == [f"IMG_{i:04d}.JPG" for i in range(len(ANGLES_DEG))]
    assert all(v["mask_method"] == "reference" for v in info["views"])


@pytest.mark.timeout(300)
def test_import_without_angles_with_camera_info_poses_every_view_from_its_board(tmp_path, shots):
    photos, empty = _photos(tmp_path, shots)
    K = shots["K"]
    world = shots["world"]
    camera_info = tmp_path / "camera.yaml"
    camera_info.write_text(yaml.safe_dump({
        "image_width": world.width, "image_height": world.height, "camera_name": "dslr",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()}, "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5}}))
    import_photos(photos, tmp_path / "session", CaptureConfig(), empty_dir=empty, intrinsics=camera_info)

    session = _check_against_truth(tmp_path / "session", shots)
    assert np.allclose(session.K, K)
    info = json.loads((tmp_path / "session" / "capture.json").read_text())
    assert info["intrinsics_source"] == "camera_info" and info["import"]["angles_from"] is None
    assert all(v["angle_rad"] is None and v["pose_source"] == "board" for v in info["views"])


def test_without_angles_a_view_hiding_the_board_is_an_error_naming_it(tmp_path, shots):
    photos, empty = _photos(tmp_path, shots)
    blank = np.full_like(shots["views"][0], 128)
    cv2.imwrite(str(photos / "IMG_0003.JPG"), blank)
    out = tmp_path / "session"
    with pytest.raises(CalibrationError, match="IMG_0003.JPG"):
        import_photos(photos, out, CaptureConfig(), empty_dir=empty)
    assert _nothing_written(out)


def test_bad_inputs_are_refused_and_nothing_is_written(tmp_path, shots):
    photos, empty = _photos(tmp_path, shots)
    out = tmp_path / "session"
    cfg = CaptureConfig()

    (tmp_path / "none").mkdir()
    (tmp_path / "none" / "readme.txt").write_text("")
    with pytest.raises(ContractError, match="holds no photos"):
        import_photos(tmp_path / "none", out, cfg)
    with pytest.raises(ContractError, match="does not exist"):
        import_photos(tmp_path / "missing", out, cfg)

    mixed = write_photos(tmp_path / "mixed", shots["views"][:3], ".png")
    cv2.imwrite(str(mixed / "IMG_0001.png"), cv2.resize(shots["views"][1], (320, 240)))
    with pytest.raises(ContractError, match="320x240"):
        import_photos(mixed, out, cfg)

    few = write_photos(tmp_path / "few", shots["empties"][:5], ".png")
    with pytest.raises(ContractError, match="8 photos .* but 5 empty-plate photos"):
        import_photos(photos, out, cfg, empty_dir=few)
    with pytest.raises(ConfigError, match="3 plate angles for 8 photos"):
        import_photos(photos, out, cfg, angles_deg=[0.0, 10.0, 20.0])
    (photos / "angles.csv").write_text("IMG_0000.JPG,0\nIMG_9999.JPG,10\n")
    with pytest.raises(ConfigError, match="no photo named IMG_9999.JPG"):
        import_photos(photos, out, cfg)
    assert _nothing_written(out)

    out.mkdir()
    (out / "n2d.json").write_text(json.dumps({"kind": "capture_session", "version": 1, "complete": True}))
    with pytest.raises(ContractError, match="already exists"):
        import_photos(photos, out, cfg, angles_deg=ANGLES_DEG)
    assert sorted(p.name for p in out.iterdir()) == ["n2d.json"]
    assert not out.with_name("session.partial").exists()


def test_angle_and_intrinsics_file_formats(tmp_path):
    photos = [tmp_path / n for n in ("b.jpg", "a.PNG")]
    for p in photos:
        p.write_bytes(b"")
    photos = sorted(photos)
    assert read_angles(tmp_path, photos) == (None, None)
    (tmp_path / "angles.json").write_text(json.dumps({"b.jpg": 90, "a.PNG": -10.5}))
    assert read_angles(tmp_path, photos) == ([-10.5, 90.0], "angles.json")
    (tmp_path / "angles.json").write_text("[1, 2]")
    assert read_angles(tmp_path, photos) == ([1.0, 2.0], "angles.json")
    (tmp_path / "angles.csv").write_text("a.PNG,0\n")
    with pytest.raises(ConfigError, match="keep one"):
        read_angles(tmp_path, photos)
    (tmp_path / "angles.json").unlink()
    (tmp_path / "angles.csv").write_text("# turntable log\nfile,angle_deg\n\na.PNG, 0\nb.jpg,abc\n")
    with pytest.raises(ConfigError, match="row 5: 'abc'"):
        read_angles(tmp_path, photos)

    K = [[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]]
    (tmp_path / "intrinsics.json").write_text(json.dumps({"K": K, "dist": [0.1, 0, 0, 0, 0], "width": 640,
                                                          "height": 480}))
    intr = load_intrinsics(tmp_path / "intrinsics.json")
    assert np.allclose(intr.K, K) and intr.dist[0] == 0.1 and (intr.width, intr.height) == (640, 480)
    (tmp_path / "camera.yaml").write_text("image_width: 640\ncamera_matrix: {rows: 3, cols: 3, data: [1, 0, 0]}\n")
    with pytest.raises(ConfigError, match="image_height|9 numbers"):
        load_intrinsics(tmp_path / "camera.yaml")
