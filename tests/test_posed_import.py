"""Import of posed photos from nerfstudio and COLMAP: a simulated session written as a nerfstudio dataset and as a
COLMAP model with its frame thrown away (every pose moved by one unknown similarity) comes back in the turntable
frame, metric from the board or from a known camera distance; a model reconstructed from it has the true size;
bad input is refused and leaves nothing behind."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from n2d.cli import main as cli
from n2d_capture.board import CalibrationError
from n2d_capture.calibration import Intrinsics
from n2d_capture.posed_import import (
    PosedImportConfig,
    PosedViews,
    fit_ring,
    import_posed,
    parse_scale_from,
    place_views,
)
from n2d_common.contracts import open_stage
from n2d_common.errors import ConfigError, ContractError
from n2d_common.formats.session import OPENGL_FROM_OPENCV, PIXEL_EDGE, read_session
from n2d_common.frames import inv_T, make_T, quat_from_R, transform_points
from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct
from n2d_sim.session import render_session, small_world

VIEWS = 24
SCALE = 3.7
"""Source units per metre of the thrown-away frame."""


def _similarity(seed: int = 7) -> np.ndarray:
    """T_world_turntable: a random rotation, a shift and the scale SCALE (source units per metre)."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return make_T(SCALE * R, rng.uniform(-2, 2, 3))


def _moved(T_world_turntable: np.ndarray, T_turntable_cam: np.ndarray) -> np.ndarray:
    """A camera pose carried by the similarity, kept rigid (OpenCV axes)."""
    T = T_world_turntable @ T_turntable_cam
    T[:3, :3] /= SCALE
    return T


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    """A simulated session (the board on the plate, exact poses and masks) and its ground truth."""
    out = tmp_path_factory.mktemp("posed") / "session"
    gt = render_session(out, small_world("box", 480, 360), VIEWS)
    return read_session(out), gt


def _nerfstudio(truth, directory, masks=True):
    """The session's views as a nerfstudio dataset, poses moved by _similarity(), OpenGL camera axes."""
    session = truth[0]
    S = _similarity()
    frames = []
    for i, view in enumerate(session.views):
        image, mask = f"images/frame_{i + 1:05d}.png", f"masks/frame_{i + 1:05d}.png"
        (directory / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(view.image, directory / image)
        T_world_cam = _moved(S, view.T_turntable_cam) @ OPENGL_FROM_OPENCV
        frame = {"file_path": image, "transform_matrix": T_world_cam.tolist()}
        if masks:
            (directory / "masks").mkdir(exist_ok=True)
            shutil.copy(view.mask, directory / mask)
            frame["mask_path"] = mask
        frames.append(frame)
    K = session.K
    (directory / "transforms.json").write_text(json.dumps({
        "camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + PIXEL_EDGE,
        "cy": K[1, 2] + PIXEL_EDGE, "w": session.width, "h": session.height, "k1": 0.0, "k2": 0.0, "p1": 0.0,
        "p2": 0.0, "frames": frames}))
    return directory


def _colmap(truth, directory, points=True):
    """The session's views as a COLMAP text model (world-to-camera, OpenCV), poses moved by _similarity(), with
    sparse points on the object and the plate."""
    session = truth[0]
    S = _similarity()
    model = directory / "sparse" / "0"
    model.mkdir(parents=True)
    (directory / "images").mkdir()
    K = session.K
    (model / "cameras.txt").write_text(f"1 PINHOLE {session.width} {session.height} {K[0, 0]} {K[1, 1]} "
                                       f"{K[0, 2] + PIXEL_EDGE} {K[1, 2] + PIXEL_EDGE}\n")
    lines = []
    for i, view in enumerate(session.views):
        name = f"IMG_{i:04d}.png"
        shutil.copy(view.image, directory / "images" / name)
        T = inv_T(_moved(S, view.T_turntable_cam))  # cam_from_world
        x, y, z, w = quat_from_R(T[:3, :3])
        lines += [f"{i + 1} {w} {x} {y} {z} {' '.join(map(str, T[:3, 3]))} 1 {name}", ""]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    world = _sparse_points(truth) if points else []
    rows = [f"{i + 1} {p[0]} {p[1]} {p[2]} 128 128 128 0.5" for i, p in enumerate(world)]
    (model / "points3D.txt").write_text("\n".join(rows) + "\n")
    return directory


def _sparse_points(truth) -> np.ndarray:
    """Points on the object and on the plate around it, as structure from motion finds them, moved by
    _similarity()."""
    gt = truth[1]
    mesh = trimesh.load(gt.model_dir / "mesh.obj", force="mesh")
    rng = np.random.default_rng(1)
    on_object = transform_points(gt.T_turntable_obj, np.asarray(mesh.sample(600, seed=0)))
    r, a = 0.15 * np.sqrt(rng.uniform(size=400)), rng.uniform(0, 2 * np.pi, 400)
    on_plate = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(400)], 1)
    return transform_points(_similarity(), np.concatenate([on_object, on_plate]))


def _camera_distance(truth, a: int, b: int) -> float:
    views = truth[0].views
    return float(np.linalg.norm(views[a].T_turntable_cam[:3, 3] - views[b].T_turntable_cam[:3, 3]))


def _pose_errors(imported, session, about_z=False):
    """(rotation deg, translation mm) per view between imported and true camera poses; with `about_z`, after the
    turn about Z that best aligns them (a frame whose X was chosen differently)."""
    A = np.stack([v.T_turntable_cam for v in imported.views])
    B = np.stack([v.T_turntable_cam for v in session.views])
    if about_z:
        a, b = A[:, :2, 3], B[:, :2, 3]
        angle = math.atan2((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum(), (a * b).sum())
        c, s = math.cos(angle), math.sin(angle)
        A = make_T(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.zeros(3)) @ A
    R = np.swapaxes(A[:, :3, :3], 1, 2) @ B[:, :3, :3]
    rot = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return rot, 1000 * np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)


def _nothing_written(out):
    return not out.exists() and not out.with_name(out.name + ".partial").exists()


@pytest.fixture(scope="module")
def nerfstudio_session(truth, tmp_path_factory):
    """The nerfstudio dataset imported through the CLI."""
    tmp = tmp_path_factory.mktemp("ns")
    source, out = _nerfstudio(truth, tmp / "dataset"), tmp / "session"
    assert cli(["capture", "import", "--from", "nerfstudio", str(source), str(out)]) == 0
    return out


def test_nerfstudio_import_recovers_the_turntable_frame_metric_from_the_board(truth, nerfstudio_session):
    imported = read_session(nerfstudio_session)
    assert len(imported.views) == VIEWS and np.allclose(imported.K, truth[0].K)
    rot, trans = _pose_errors(imported, truth[0])
    assert np.median(rot) < 0.2 and rot.max() < 0.5, rot
    assert np.median(trans) < 1.5 and trans.max() < 3.0, trans
    info = json.loads((nerfstudio_session / "capture.json").read_text())["import"]
    assert info["scale_from"] == "board" and info["plate_from"] == "board"
    assert abs(info["scale_m_per_unit"] * SCALE - 1) < 0.003, info
    assert info["alignment_mm"] < 2 and info["board_tilt_deg"] < 0.5, info
    assert open_stage(nerfstudio_session, "capture_session")["extra"]["masks_given"] == VIEWS


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_model_from_the_nerfstudio_import_has_the_true_size(truth, nerfstudio_session, tmp_path):
    """The fast path (visual hull refined by photo-consistency) on the imported session: metric from the board
    alone (measured: diameter -0.7 %, size +1.8 / +2.2 / +0.0 %; 24 views of 480x360 leave the hull's corners)."""
    cfg = ReconstructConfig(object_name="box", holdout_every=0)
    cfg.mesh.voxel_m, cfg.mesh.target_faces, cfg.texture.size_px = 0.002, 3000, 64
    report = reconstruct(nerfstudio_session, tmp_path / "model", cfg)
    true = json.loads((truth[1].model_dir / "models_info.json").read_text())["1"]
    assert abs(report["model"]["diameter_mm"] / true["diameter"] - 1) < 0.01, report["model"]
    true_size = np.array([true["size_x"], true["size_y"], true["size_z"]])
    assert np.all(np.abs(np.array(report["model"]["size_mm"]) / true_size - 1) < 0.04), report["model"]


def test_colmap_import_with_a_known_camera_distance_places_the_plate_from_the_points(truth, tmp_path):
    source = _colmap(truth, tmp_path / "colmap")
    half = VIEWS // 2
    cfg = PosedImportConfig(scale_from=f"cam:IMG_0000.png,IMG_{half:04d}.png={_camera_distance(truth, 0, half):.6f}")
    summary = import_posed(source, tmp_path / "session", cfg, source="colmap")
    assert summary["scale_from"] == "distance" and summary["masks_made"] == VIEWS
    rot, trans = _pose_errors(read_session(tmp_path / "session"), truth[0], about_z=True)  # X: to the first camera
    assert np.median(rot) < 0.2 and rot.max() < 0.5, rot
    assert np.median(trans) < 2.0 and trans.max() < 4.0, trans


def test_nerfstudio_import_with_a_known_camera_distance_and_its_point_cloud(truth, tmp_path):
    source = _nerfstudio(truth, tmp_path / "dataset")
    trimesh.PointCloud(_sparse_points(truth)).export(source / "sparse_pc.ply")
    _edit(source, lambda t: t.update(ply_file_path="sparse_pc.ply"))
    cfg = PosedImportConfig(scale_from=f"cam:frame_00003.png,frame_00011.png={_camera_distance(truth, 2, 10):.6f}")
    summary = import_posed(source, tmp_path / "session", cfg)
    assert summary["scale_from"] == "distance" and summary["masks_given"] == VIEWS
    rot, trans = _pose_errors(read_session(tmp_path / "session"), truth[0], about_z=True)
    assert np.median(rot) < 0.2 and np.median(trans) < 2.0, (rot, trans)


def test_colmap_import_metric_from_the_board(truth, tmp_path):
    source = _colmap(truth, tmp_path / "colmap", points=False)
    (source / "masks").mkdir()
    for i, view in enumerate(truth[0].views):
        shutil.copy(view.mask, source / "masks" / f"IMG_{i:04d}.png.png")
    assert cli(["capture", "import", "--from", "colmap", str(source), str(tmp_path / "session")]) == 0
    extra = open_stage(tmp_path / "session", "capture_session")["extra"]
    assert extra["scale_from"] == "board" and extra["masks_given"] == VIEWS
    rot, trans = _pose_errors(read_session(tmp_path / "session"), truth[0])
    assert np.median(rot) < 0.2 and np.median(trans) < 1.5, (rot, trans)


def test_ring_fit_and_scale_option():
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = np.stack([0.4 * np.cos(angles), 0.4 * np.sin(angles), np.full(12, 0.3)], 1) @ _similarity()[:3, :3].T
    normal, centre, radius, rms = fit_ring(ring)
    assert abs(radius / (0.4 * SCALE) - 1) < 1e-9 and rms < 1e-9
    assert abs(abs(normal @ _similarity()[:3, 2] / SCALE) - 1) < 1e-9
    with pytest.raises(CalibrationError, match="line"):
        fit_ring(np.outer(np.arange(5.0), [1, 2, 3]))
    s = parse_scale_from("cam:a.png, b.png=0.35")
    assert (s.image_a, s.image_b, s.distance_m) == ("a.png", "b.png", 0.35)
    for bad in ("a.png,b.png=0.3", "cam:a.png,b.png=-1", "cam:a.png,b.png=x", "cam:a.png=0.3"):
        with pytest.raises(ConfigError):
            parse_scale_from(bad)


def test_cameras_off_a_ring_take_up_from_the_table_plane_of_the_points():
    """A hand-held walk at two heights is no ring: Z is the normal of the sparse points' dominant plane."""
    rng = np.random.default_rng(2)
    poses, truth_centres = [], []
    for k in range(16):
        azimuth, elevation = 2 * np.pi * k / 16, math.radians(20 if k % 2 else 50)
        c = 0.5 * np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                            math.sin(elevation)])
        z = (np.array([0, 0, 0.05]) - c) / np.linalg.norm(np.array([0, 0, 0.05]) - c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        poses.append(_moved(_similarity(), make_T(np.stack([x, np.cross(z, x), z], 1), c)))
        truth_centres.append(c)
    r, a = 0.3 * np.sqrt(rng.uniform(size=2000)), rng.uniform(0, 2 * np.pi, 2000)
    table = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(2000)], 1)
    box = rng.uniform([-0.05, -0.05, 0], [0.05, 0.05, 0.15], (500, 3))
    views = PosedViews([Path(f"{k}.png") for k in range(16)], [f"{k}.png" for k in range(16)], [None] * 16,
                       Intrinsics(np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]]), np.zeros(5), 640, 480),
                       np.stack(poses), transform_points(_similarity(), np.concatenate([table, box])))
    distance = np.linalg.norm(truth_centres[0] - truth_centres[8])
    placement = place_views(views, [None] * 16, PosedImportConfig(scale_from=f"cam:0.png,8.png={distance}"))
    assert placement.up_from == "points" and placement.plate_from == "points", placement
    found = transform_points(placement.T_turntable_world, views.T_world_cam[:, :3, 3])
    truth_centres = np.array(truth_centres)
    assert np.abs(found[:, 2] - truth_centres[:, 2]).max() < 1e-3, found[:, 2] - truth_centres[:, 2]
    radial = np.linalg.norm(found[:, :2], axis=1) - np.linalg.norm(truth_centres[:, :2], axis=1)
    assert np.abs(radial).max() < 1e-3, radial


def _edit(directory, change):
    t = json.loads((directory / "transforms.json").read_text())
    change(t)
    (directory / "transforms.json").write_text(json.dumps(t))


def test_bad_input_is_refused_and_nothing_is_written(truth, tmp_path, capsys):
    out = tmp_path / "session"
    with pytest.raises(ContractError, match="transforms.json"):
        import_posed(tmp_path, out, PosedImportConfig())
    with pytest.raises(ContractError, match="sparse model"):
        import_posed(tmp_path, out, PosedImportConfig(), source="colmap")
    source = _nerfstudio(truth, tmp_path / "ns", masks=False)
    good = (source / "transforms.json").read_text()
    cases = [
        (lambda t: t["frames"][3].update(file_path="images/missing.png"), ContractError, "missing.png"),
        (lambda t: t["frames"][2].update(mask_path="masks/none.png"), ContractError, "none.png"),
        (lambda t: t["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")), ContractError, "finite"),
        (lambda t: t["frames"][1]["transform_matrix"][0].__setitem__(0, 2.0), ContractError, "rotation"),
        (lambda t: t["frames"][4].update(fl_x=t["fl_x"] * 1.1), ContractError, "other intrinsics"),
        (lambda t: t.update(w=t["w"] // 2, h=t["h"] // 2), ContractError, "240x180"),
        (lambda t: t.update(camera_model="OPENCV_FISHEYE"), ContractError, "camera_model"),
        (lambda t: t.update(frames=[]), ContractError, "no frames"),
        (lambda t: t.pop("cx"), ContractError, "missing 'cx'"),
    ]
    for change, error, match in cases:
        (source / "transforms.json").write_text(good)
        _edit(source, change)
        with pytest.raises(error, match=match):
            import_posed(source, out, PosedImportConfig())
        assert _nothing_written(out)
    (source / "transforms.json").write_text(good)
    _edit(source, lambda t: t.update(frames=t["frames"][:2]))
    with pytest.raises(ConfigError, match="too few to make the session metric") as exc:
        import_posed(source, out, PosedImportConfig())  # the board in 2 views: no scale
    assert "--scale-from" in exc.value.hint and _nothing_written(out)
    assert cli(["capture", "import", str(source / "images"), str(out), "--scale-from", "cam:a,b=1"]) == 2
    assert "--scale-from and posed.* settings need --from" in capsys.readouterr().err and _nothing_written(out)
    assert cli(["capture", "import", "--from", "nerfstudio", str(source), str(out), "--set",
                "posed.min_board_views=2"]) == 2  # a config check: at least 3
    assert "min_board_views" in capsys.readouterr().err and _nothing_written(out)
    assert cli(["capture", "import", "--from", "nerfstudio", str(source), str(out)]) == 2
    assert "hint:" in capsys.readouterr().err and _nothing_written(out)
    with pytest.raises(ConfigError, match="no view named"):
        import_posed(source, out, PosedImportConfig(scale_from="cam:nope.png,images/frame_00001.png=0.3"))
    (source / "transforms.json").write_text(good)
    _edit(source, lambda t: t.update(frames=t["frames"][:6]))
    with pytest.raises(ContractError, match="no sparse points"):  # nerfstudio without a board: no plate
        import_posed(source, out, PosedImportConfig(scale_from="cam:frame_00001.png,frame_00004.png=0.1"))
    assert _nothing_written(out)
