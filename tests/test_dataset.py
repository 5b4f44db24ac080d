"""The dataset stage on small real Cycles renders: the contract on disk, annotation accuracy against the
meshes (mask boundaries, depth, visibility, DOPE vs BOP), reproducibility, resume after a cancel, bad
input, and the `n2d dataset` CLI."""

import json
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from n2d_common.config import load_config
from n2d_common.contracts import read_manifest
from n2d_common.errors import Cancelled, ContractError
from n2d_common.frames import R_from_quat, make_T, project, transform_points
from n2d_common.images import read_png
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dataset.models import CUBOID_SIGNS, load_models
from n2d_reconstruct.raster import render_depth
from n2d_sim.objects import sample_object_dir

MODELS = [sample_object_dir("box"), sample_object_dir("bottle")]
SMALL = ["frames=3", "camera.width=320", "camera.height=240", "camera.focal_px=300", "render.samples=4",
         "scene.in_hand=0.5", "scene.distractors=[2,4]"]


def small_config(*more: str) -> DatasetConfig:
    return load_config(DatasetConfig, overrides=SMALL + list(more))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dataset") / "ds"
    generate_dataset(MODELS, out, small_config())
    return out


def _frames(root: Path):
    """(chunk dir, im id, DOPE json, scene_gt list, scene_gt_info list, K) of every frame."""
    chunk = root / "train_pbr" / "000000"
    gt, info, cam = (json.loads((chunk / f"{k}.json").read_text()) for k in ("scene_gt", "scene_gt_info",
                                                                               "scene_camera"))
    for im in sorted(gt, key=int):
        dope = json.loads((chunk / "rgb" / f"{int(im):06d}.json").read_text())
        yield chunk, int(im), dope, gt[im], info[im], np.array(cam[im]["cam_K"]).reshape(3, 3)


def _pose(g: dict) -> np.ndarray:
    return make_T(np.array(g["cam_R_m2c"]).reshape(3, 3), np.array(g["cam_t_m2c"]) / 1000.0)


def test_contract(dataset):
    manifest = read_manifest(dataset)
    assert manifest["kind"] == "dataset" and manifest["complete"]
    assert manifest["extra"]["cuboid_order"][0] == "front top right"
    assert manifest["extra"]["units"]["bop"] == "mm"
    assert not (dataset / "records").exists() and not dataset.with_name("ds.partial").exists()
    assert json.loads((dataset / "camera.json").read_text())["fx"] == 300
    info = json.loads((dataset / "models" / "models_info.json").read_text())
    assert set(info) == {"1", "2"} and (dataset / "models" / "obj_000001.ply").is_file()
    assert (dataset / "models" / "box" / "mesh.obj").is_file()
    sheet = read_png(dataset / "contact_sheet.png")
    assert sheet.shape[0] > 100 and sheet.std() > 10
    frames = list(_frames(dataset))
    assert len(frames) == 3
    for chunk, im, dope, gt, info, _ in frames:
        assert len(gt) == len(info) == len(dope["objects"]) >= 2
        assert cv2.imread(str(chunk / "rgb" / f"{im:06d}.jpg")).shape == (240, 320, 3)
        depth = cv2.imread(str(chunk / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (240, 320)
        for k in range(len(gt)):
            assert (chunk / "mask" / f"{im:06d}_{k:06d}.png").is_file()
            assert (chunk / "mask_visib" / f"{im:06d}_{k:06d}.png").is_file()


def _silhouette(mesh, T_cam_obj, K, w, h, ss: int = 8) -> np.ndarray:
    """Whether each pixel centre lies inside the projected mesh, from polygons filled at `ss` x resolution
    (OpenCV, independent of n2d's rasterizer and of Blender)."""
    uv = project(K, T_cam_obj, mesh.vertices)
    # pixel centre u maps to ss * u + (ss - 1) / 2 on the fine grid, the centre of its ss x ss block
    fine = np.round((uv * ss + (ss - 1) / 2) * 16).astype(np.int32)
    canvas = np.zeros((h * ss, w * ss), np.uint8)
    for tri in fine[mesh.faces]:  # one at a time: fillPoly's even-odd rule would cancel overlapping faces
        cv2.fillConvexPoly(canvas, tri, 1, lineType=cv2.LINE_8, shift=4)
    return canvas[ss // 2::ss, ss // 2::ss].astype(bool)


def test_masks_fall_on_the_projected_meshes(dataset):
    """Where an instance is fully visible, its written mask_visib (Cycles' index pass) agrees with the mesh
    projected with the written pose and K: mean boundary offset (XOR area / perimeter) <= 0.5 px."""
    models = {m.obj_id: m for m in load_models(MODELS)}
    offsets = []
    for chunk, im, _, gt, info, K in _frames(dataset):
        for k, (g, i) in enumerate(zip(gt, info)):
            if i["visib_fract"] < 0.999 or i["px_count_visib"] < 200:
                continue
            visib = read_png(chunk / "mask_visib" / f"{im:06d}_{k:06d}.png") > 0
            truth = _silhouette(models[g["obj_id"]].mesh, _pose(g), K, 320, 240)
            contours, _ = cv2.findContours(truth.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            perimeter = sum(cv2.arcLength(c, True) for c in contours)
            offsets.append((visib ^ truth).sum() / perimeter)
    assert offsets, "no fully visible instance in the test frames"
    assert np.mean(offsets) <= 0.5, offsets


def test_depth_and_visibility_match_the_meshes(dataset):
    """Written depth equals the mesh depth under the written pose within 1 mm on visible pixels, and
    visib_fract matches a BOP-style recount (mesh depth vs scene depth within 5 mm)."""
    models = {m.obj_id: m for m in load_models(MODELS)}
    errors, recounts = [], []
    for chunk, im, _, gt, info, K in _frames(dataset):
        depth = cv2.imread(str(chunk / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED) * 1e-4  # 0.1 mm -> m
        for k, (g, i) in enumerate(zip(gt, info)):
            mesh = models[g["obj_id"]].mesh
            own = render_depth(mesh.vertices, mesh.faces, K, _pose(g), 320, 240)
            visib = read_png(chunk / "mask_visib" / f"{im:06d}_{k:06d}.png") > 0
            both = visib & np.isfinite(own)
            errors.append(np.abs(depth[both] - own[both]))
            x, y, w, h = i["bbox_obj"]
            if x >= 0 and y >= 0 and x + w <= 320 and y + h <= 240 and i["px_count_all"] > 100:
                mask = np.isfinite(own)
                visible = mask & (depth > 0) & (np.abs(depth - own) < 0.005)
                recounts.append((visible.sum() / mask.sum(), i["visib_fract"]))
    errors = np.concatenate(errors)
    assert np.mean(errors) < 0.001 and np.percentile(errors, 95) < 0.001, (errors.mean(), np.percentile(errors, 95))
    assert recounts
    for recount, written in recounts:
        assert abs(recount - written) < 0.03, recounts


def test_dope_agrees_with_bop(dataset):
    """DOPE JSON (cm, quaternion, projected cuboid in the documented corner order) encodes the BOP pose."""
    models = {m.obj_id: m for m in load_models(MODELS)}
    for _, _, dope, gt, _, K in _frames(dataset):
        assert dope["camera_data"]["intrinsics"]["fx"] == K[0, 0]
        for obj, g in zip(dope["objects"], gt):
            T = _pose(g)
            m = models[g["obj_id"]]
            assert obj["class"] == m.name
            np.testing.assert_allclose(np.array(obj["location"]) / 100.0, T[:3, 3], atol=1e-9)
            np.testing.assert_allclose(R_from_quat(obj["quaternion_xyzw"]), T[:3, :3], atol=1e-6)
            corners = m.min_m + m.size_m / 2 + CUBOID_SIGNS * m.size_m / 2
            np.testing.assert_allclose(obj["projected_cuboid"], project(K, T, corners), atol=1e-6)
            # corner 0 is front (+z) top (+y) right (+x) of the object frame; the centroid is last
            np.testing.assert_allclose(np.array(obj["cuboid"][0]) / 100.0,
                                       transform_points(T, (m.min_m + m.size_m)[None])[0], atol=1e-9)
            assert len(obj["keypoint_visibility"]) == 9 and set(obj["keypoint_visibility"]) <= {0, 1}


def test_resume_after_cancel_is_reproducible(dataset, tmp_path):
    """Cancelled after a frame, then resumed: the same frames as one uninterrupted run of the same config."""
    out = tmp_path / "ds"
    cancel = threading.Event()

    def stop_after_first(p):
        if p.info.get("frames_done", 0) >= 1:
            cancel.set()

    with pytest.raises(Cancelled):
        generate_dataset(MODELS, out, small_config(), progress=stop_after_first, cancel=cancel)
    assert not out.exists()
    records = list((out.with_name("ds.partial") / "records").glob("*.json"))
    assert 1 <= len(records) < 3
    summary = generate_dataset(MODELS, out, small_config())
    assert summary["resumed_frames"] == len(records)
    for (_, im, dope, gt, _, _), (_, _, dope0, gt0, _, _) in zip(_frames(out), _frames(dataset)):
        assert gt == gt0 and dope == dope0
        a, b = (cv2.imread(str(d / "train_pbr/000000/rgb" / f"{im:06d}.jpg")).astype(float) for d in (out, dataset))
        assert np.abs(a - b).mean() < 1.0


def test_bad_input_writes_nothing(tmp_path):
    not_a_model = tmp_path / "photos"
    not_a_model.mkdir()
    with pytest.raises(ContractError, match="no n2d.json"):
        generate_dataset([not_a_model], tmp_path / "ds", small_config())
    with pytest.raises(ContractError, match="no models"):
        generate_dataset([], tmp_path / "ds", small_config())
    assert not (tmp_path / "ds").exists() and not (tmp_path / "ds.partial").exists()


def test_cli_two_workers(tmp_path):
    """`n2d dataset` shards frames over two render processes; errors are one line with a hint."""
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "n2d.cli", "dataset", *map(str, MODELS), str(out), "--frames", "2", "--workers", "2",
           "--set", "camera.width=160", "--set", "camera.height=120", "--set", "camera.focal_px=150",
           "--set", "render.samples=2", "--set", "scene.distractors=[0,1]"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "2 frames" in run.stdout
    assert len(list((out / "train_pbr" / "000000" / "rgb").glob("*.jpg"))) == 2
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "already exists" in again.stderr and "hint" in again.stderr
