"""The fast dataset path (`render.engine=raster`): the same contract and exact annotations as the Cycles path,
reproducible across worker counts and resumes, no bpy; its shading against closed-form values; resting poses."""

import json
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from n2d_common.config import load_config
from n2d_common.contracts import read_manifest
from n2d_common.errors import Cancelled, ConfigError
from n2d_common.frames import R_from_quat, make_T, quat_from_R
from n2d_common.symmetry import canonical_pose, find_symmetries, to_models_info
from n2d_dataset.check import check_dataset, frames
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dataset.placement import rest_height, resting_poses, sample_orientation
from n2d_dataset.shading import Body, Light, Material, Plane, RasterScene, Sky, corner_normals, render
from n2d_dope.config import TrainConfig
from n2d_dope.data import DopeSamples, canonical_instance, check_mix, epoch_order, open_dataset, open_datasets
from n2d_dope.train import train
from n2d_sim.objects import sample_object_dir

MODELS = [sample_object_dir("box"), sample_object_dir("bottle")]
SMALL = ["frames=4", "camera.width=320", "camera.height=240", "camera.focal_px=300", "render.engine=raster",
         "scene.in_hand=0.5", "scene.distractors=[2,4]", "scene.boards=0.5", "workers=1"]


def small_config(*more: str) -> DatasetConfig:
    return load_config(DatasetConfig, overrides=SMALL + list(more))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("raster") / "ds"
    generate_dataset(MODELS, out, small_config())
    return out


def test_contract_and_exact_annotations(dataset):
    """The Cycles path's contract and checks: masks on the projected meshes (<= 0.5 px), depth within 1 mm,
    visib_fract as recounted, DOPE JSON encoding the BOP pose; the manifest names the renderer."""
    manifest = read_manifest(dataset)
    assert manifest["complete"] and manifest["extra"]["renderer"] == "raster"
    report = check_dataset(dataset)
    assert report["instances"] >= 8, report
    assert report["mask_boundary_offset_px"]["mean"] <= 0.5, report
    assert report["depth_error_mm"]["mean"] < 1.0 and report["depth_error_mm"]["p95"] < 1.0, report
    assert report["visib_fract_error"]["max"] < 0.03, report
    assert report["dope_vs_pose_px_max"] < 1e-3, report
    for chunk, im, dope, gt, _, _ in frames(dataset):
        rgb = cv2.imread(str(chunk / "rgb" / f"{im:06d}.jpg"))
        assert rgb.shape == (240, 320, 3) and rgb.std() > 10  # a picture, not a blank frame
        assert len(gt) == len(dope["objects"]) >= 2


@pytest.mark.slow
def test_same_frames_whatever_the_workers_and_resumes(dataset, tmp_path):
    """Two workers, and a run cancelled after a frame then resumed, write the frames one worker writes, byte for
    byte (a frame depends only on (seed, frame))."""
    two = tmp_path / "two"
    generate_dataset(MODELS, two, small_config("workers=2"))
    cancel = threading.Event()

    def stop(p):
        if p.info.get("frames_done", 0) >= 1:
            cancel.set()

    resumed = tmp_path / "resumed"
    with pytest.raises(Cancelled):
        generate_dataset(MODELS, resumed, small_config(), progress=stop, cancel=cancel)
    assert not resumed.exists()
    assert generate_dataset(MODELS, resumed, small_config())["resumed_frames"] >= 1
    for other in (two, resumed):
        for name in ("rgb/000002.jpg", "depth/000003.png", "scene_gt.json", "scene_gt_info.json"):
            chunk = Path("train_pbr/000000") / name
            assert (other / chunk).read_bytes() == (dataset / chunk).read_bytes(), (other, name)


def test_worker_needs_no_blender(tmp_path):
    """The fast path renders in a process that never imports bpy."""
    code = ("import sys, threading; from n2d_dataset.raster_worker import render_frames; "
            "from n2d_common.config import to_dict; from n2d_common.config import load_config; "
            "from n2d_dataset.config import DatasetConfig; "
            f"cfg = load_config(DatasetConfig, overrides={SMALL!r}); "
            f"render_frames([{str(MODELS[0])!r}], {str(tmp_path)!r}, to_dict(cfg), [0], lambda p: None, "
            "threading.Event()); assert 'bpy' not in sys.modules, 'bpy imported'; print('ok')")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "ok" in run.stdout, run.stderr[-2000:]
    record = json.loads((tmp_path / "records" / "000000.json").read_text())
    assert record["renderer"] == "raster" and record["scene_gt"]


def test_config_is_checked():
    with pytest.raises(ConfigError, match="upright"):
        small_config("scene.upright=0.7", "scene.resting=0.5")
    with pytest.raises(ConfigError, match="engine"):
        small_config("render.engine=eevee")
    with pytest.raises(ConfigError, match="workers"):
        small_config("workers=-1")


def _lit_plane_scene(albedo: float, power_w: float, height_m: float, bodies=()) -> RasterScene:
    floor = Plane(np.array([-2.0, -2.0, 0.0]), np.eye(3)[0], np.eye(3)[1], (4.0, 4.0),
                  np.full((4, 4, 3), albedo, np.float32), 1.0, Material(roughness=1.0, specular=0.0))
    light = Light(np.full(3, power_w), position=np.array([0.0, 0.0, height_m]))
    return RasterScene(list(bodies), [floor], [light], Sky(np.zeros(3), np.zeros(3), 0.0))


def _top_camera(height_m: float, size: int = 65, focal_px: float = 100.0):
    K = np.array([[focal_px, 0, (size - 1) / 2], [0, focal_px, (size - 1) / 2], [0, 0, 1]])
    T = make_T(np.diag([1.0, -1.0, -1.0]), (0.0, 0.0, height_m))  # looking straight down
    return K, T, size


def test_lambert_floor_under_a_point_light():
    """A matte floor right under a point light of P watts at height d: radiance albedo / pi * P / (4 pi d^2); the
    depth label is the camera's height."""
    K, T, n = _top_camera(1.0)
    image, g = render(_lit_plane_scene(0.5, 100.0, 2.0), K, T, n, n)
    expected = 0.5 / np.pi * 100.0 / (4 * np.pi * 4.0)
    assert image[n // 2, n // 2, 0] == pytest.approx(expected, rel=1e-3)
    assert g.depth[n // 2, n // 2] == pytest.approx(1.0, abs=1e-6) and (g.index == 0).all()


def test_a_body_casts_a_shadow_and_is_labelled():
    """A box between the light and the floor: the floor beside it is lit, the floor hidden from the light by it is
    dark; the box carries its label."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.05))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    body = Body(v, f, corner_normals(v, f), np.zeros((len(f), 3, 2)), np.full((2, 2, 3), 0.5, np.float32),
                make_T(np.eye(3), (0.0, 0.0, 1.0)), label=3)
    K, T, n = _top_camera(3.0, 257, 300.0)
    scene = _lit_plane_scene(0.5, 100.0, 2.0, [body])
    image, g = render(scene, K, T, n, n)
    assert g.index[n // 2, n // 2] == 3 and (g.index == 3).sum() > 500
    # The light is 1 m above the box, the box 1 m above the floor: its shadow is twice its size, 0.2 m from the
    # middle, 20 px in the camera 3 m up; the box itself (2 m from the camera) reaches 15 px.
    shadow, lit = n // 2 + 18, n // 2 + 24
    assert g.index[n // 2, shadow] == 0 and g.index[n // 2, n // 2 + 14] == 3
    assert image[n // 2, shadow, 0] < 0.05 * image[n // 2, lit, 0]


def test_crease_normals_keep_edges_and_smooth_curves():
    cube = trimesh.creation.box()
    n = corner_normals(cube.vertices, cube.faces)
    np.testing.assert_allclose(n, np.repeat(cube.face_normals[:, None], 3, 1), atol=1e-9)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    n = corner_normals(sphere.vertices, sphere.faces)
    radial = sphere.vertices[sphere.faces] / np.linalg.norm(sphere.vertices[sphere.faces], axis=2, keepdims=True)
    assert np.einsum("fkc,fkc->fk", n, radial).min() > 0.999


def test_resting_poses():
    """A 90 x 60 x 140 mm box rests on its six faces, most often on its largest (the x-z faces), least on its
    ends; each pose puts the resting face down; upright keeps the model's Z up."""
    box = trimesh.creation.box(extents=(0.09, 0.06, 0.14))
    poses = resting_poses(box)
    assert len(poses) == 6 and sum(p.probability for p in poses) == pytest.approx(1.0)
    downs = [np.round(p.R.T @ [0, 0, -1]).astype(int).tolist() for p in poses]
    assert sorted(map(abs, map(sum, downs[:2]))) == [1, 1] and all(abs(d[1]) == 1 for d in downs[:2])
    assert all(abs(d[2]) == 1 for d in downs[4:])
    for p in poses:
        assert rest_height(box.vertices, p.R) == pytest.approx(float(-(box.vertices @ p.R.T)[:, 2].min()))
    rng = np.random.default_rng(0)
    R, how = sample_orientation(rng, poses, upright=1.0, resting=0.0)
    assert how == "upright" and R[:, 2] @ [0, 0, 1] == pytest.approx(1.0)


@pytest.mark.slow
def test_mixed_dataset_and_training_mix(tmp_path):
    """A raster dataset with photoreal_frames renders those frames with Cycles; training draws from the two kinds
    by photoreal_mix, and refuses a mix the frames cannot give, or a dataset of another object."""
    out = tmp_path / "mixed"
    cfg = small_config("frames=3", "photoreal_frames=1", "render.samples=2", "camera.width=160", "camera.height=120",
                       "camera.focal_px=150")
    generate_dataset(MODELS[:1], out, cfg)
    assert read_manifest(out)["extra"]["photoreal_frames"] == 1
    info = open_dataset(out)
    assert [f.photoreal for f in info.frames] == [True, False, False]
    frames = info.frames * 20
    order = epoch_order(frames, 0.25, np.random.default_rng(0))
    assert abs(np.mean([frames[i].photoreal for i in order]) - 0.25) < 0.1
    assert sorted(epoch_order(frames, -1, np.random.default_rng(0))) == list(range(len(frames)))
    check_mix(info, info.frames, "box", 0.5)
    with pytest.raises(ConfigError, match="no photoreal"):
        check_mix(info, info.frames[1:], "box", 0.5)
    with pytest.raises(ConfigError, match="every training frame is photoreal"):
        check_mix(info, info.frames[:1], "box", 0.5)
    bottle = tmp_path / "bottle"
    generate_dataset(MODELS[1:], bottle, small_config("frames=2", "camera.width=160", "camera.height=120",
                                                      "camera.focal_px=150"))
    with pytest.raises(ConfigError, match="not box"):
        train([out, bottle], tmp_path / "dope", TrainConfig.preset("tiny"), object_name="box")
    with pytest.raises(ConfigError, match="photoreal_mix"):
        load_config(TrainConfig, overrides=["photoreal_mix=1.5"])
    assert not (tmp_path / "dope").exists() and not (tmp_path / "dope.partial").exists()
    assert open_datasets([out]).sources == {out: ["box"]}


def _plain_box(tmp_path) -> Path:
    """The sample box with its print painted over in one colour: its shape's 4 symmetries hold for its look too."""
    model = tmp_path / "plain_box"
    shutil.copytree(MODELS[0], model)
    img = cv2.imread(str(model / "albedo.png"))
    cv2.imwrite(str(model / "albedo.png"), np.full_like(img, 160))
    mesh = trimesh.load(model / "mesh.obj", force="mesh", process=False)
    sym = find_symmetries(mesh.vertices, mesh.faces, face_uvs=mesh.visual.uv[mesh.faces],
                          texture=cv2.imread(str(model / "albedo.png"))[..., ::-1])
    assert sym.group_order == 4
    info = json.loads((model / "models_info.json").read_text())
    info["1"].update(to_models_info(sym))
    (model / "models_info.json").write_text(json.dumps(info))
    return model


def test_symmetry_aware_targets(tmp_path):
    """A symmetric model's instances are labelled with the canonical of their equivalent poses: the same keypoints
    whichever of the 4 poses the scene used; training samples take them."""
    out = tmp_path / "ds"
    generate_dataset([_plain_box(tmp_path)], out, small_config("frames=2", "scene.instances_per_model=[2,2]"))
    info = open_dataset(out)
    (name, poses), = info.symmetries.items()
    assert len(poses) == 4
    cuboid = info.cuboid_points_m[name]
    annotation = json.loads(info.frames[0].annotation.read_text())
    intrinsics = annotation["camera_data"]["intrinsics"]
    for obj in annotation["objects"]:
        canonical = np.array(canonical_instance(obj, intrinsics, cuboid, poses)["projected_cuboid"])
        T = make_T(R_from_quat(obj["quaternion_xyzw"]), np.array(obj["location"]) / 100.0)
        for S in poses:
            turned = {**obj, "quaternion_xyzw": quat_from_R(T[:3, :3] @ S[:3, :3]).tolist()}
            np.testing.assert_allclose(canonical_instance(turned, intrinsics, cuboid, poses)["projected_cuboid"],
                                       canonical, atol=1e-6)
        T_canonical, _ = canonical_pose(T, poses)
        assert np.trace(T_canonical[:3, :3]) >= max(np.trace(T[:3, :3] @ S[:3, :3]) for S in poses) - 1e-9
    cfg = TrainConfig.preset("tiny")
    plain = DopeSamples(info.frames, name, cfg, augment=False)
    aware = DopeSamples(info.frames, name, cfg, augment=False, symmetric={name: (cuboid, poses)})
    assert aware[0][0].shape == plain[0][0].shape
