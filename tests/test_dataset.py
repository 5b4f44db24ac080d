"""The dataset stage on small real Cycles renders: the contract on disk, annotation accuracy against the
meshes (mask boundaries, depth, visibility, DOPE vs BOP), reproducibility, resume after a cancel, bad
input, and the `n2d dataset` CLI."""

import json
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from n2d_common.config import load_config
from n2d_common.contracts import read_manifest
from n2d_common.errors import Cancelled, ConfigError, ContractError
from n2d_common.frames import project, transform_points
from n2d_common.images import read_png
from n2d_dataset.check import check_dataset, frames, pose
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dataset.models import load_models
from n2d_dataset.textures import FIDUCIAL_DICTIONARIES, random_fiducial_sheet
from n2d_sim.objects import sample_object_dir

MODELS = [sample_object_dir("box"), sample_object_dir("bottle")]
SMALL = ["frames=3", "camera.width=320", "camera.height=240", "camera.focal_px=300", "render.samples=4",
         "scene.in_hand=0.5", "scene.distractors=[2,4]", "scene.boards=1.0"]


def small_config(*more: str) -> DatasetConfig:
    return load_config(DatasetConfig, overrides=SMALL + list(more))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dataset") / "ds"
    generate_dataset(MODELS, out, small_config())
    return out


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
    written = list(frames(dataset))
    assert len(written) == 3
    for chunk, im, dope, gt, info, _ in written:
        assert len(gt) == len(info) == len(dope["objects"]) >= 2
        assert cv2.imread(str(chunk / "rgb" / f"{im:06d}.jpg")).shape == (240, 320, 3)
        depth = cv2.imread(str(chunk / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (240, 320)
        for k in range(len(gt)):
            assert (chunk / "mask" / f"{im:06d}_{k:06d}.png").is_file()
            assert (chunk / "mask_visib" / f"{im:06d}_{k:06d}.png").is_file()


def test_annotations_match_the_meshes(dataset):
    """Masks fall on the projected meshes (mean boundary offset <= 0.5 px), depth matches the meshes within
    1 mm, visib_fract matches a BOP-style recount, DOPE JSON encodes the BOP pose."""
    report = check_dataset(dataset)
    assert report["instances"] >= 6 and report["fully_visible_instances"] >= 1, report
    assert report["mask_boundary_offset_px"]["mean"] <= 0.5, report
    assert report["depth_error_mm"]["mean"] < 1.0 and report["depth_error_mm"]["p95"] < 1.0, report
    assert report["visib_fract_error"]["max"] < 0.03, report
    assert report["dope_vs_pose_px_max"] < 1e-3, report


def _fiducial_markers(gray: np.ndarray) -> int:
    """Most ArUco markers found in `gray` by any of the dictionaries fiducial sheets use."""
    found = [cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, d))).detectMarkers(gray)[1]
             for d in FIDUCIAL_DICTIONARIES]
    return max(0 if ids is None else len(ids) for ids in found)


@pytest.mark.slow
@pytest.mark.parametrize("engine", ["cycles", "raster"])
def test_fiducial_sheets(tmp_path, engine):
    """Fiducial sheets are real, decodable ChArUco boards and ArUco grids, and with scene.boards=1 they lie in
    the rendered frames of both renderers, markers readable (the annotation tests run on frames with sheets, so
    the sheets spoil no mask or depth)."""
    for seed in range(8):
        sheet = random_fiducial_sheet(np.random.default_rng(seed))
        assert _fiducial_markers(sheet) >= 8, seed
    out = tmp_path / "sheets"
    generate_dataset(MODELS[:1], out, load_config(DatasetConfig, overrides=[
        "frames=2", "render.samples=4", "scene.boards=1.0", "scene.in_hand=0", "scene.distractors=[0,1]",
        "scene.instances_per_model=[1,1]", f"render.engine={engine}"]))
    seen = [_fiducial_markers(cv2.imread(str(chunk / "rgb" / f"{im:06d}.jpg"), cv2.IMREAD_GRAYSCALE))
            for chunk, im, *_ in frames(out)]
    assert sum(seen) >= 1, seen
    with pytest.raises(ConfigError, match="scene.boards is a probability"):
        small_config("scene.boards=1.5")


def test_dope_corner_order(dataset):
    """DOPE JSON: metres -> cm, corner 0 is front (+z) top (+y) right (+x) of the object frame, centroid last."""
    models = {m.obj_id: m for m in load_models(MODELS)}
    for _, _, dope, gt, _, K in frames(dataset):
        assert dope["camera_data"]["intrinsics"]["fx"] == K[0, 0]
        for obj, g in zip(dope["objects"], gt):
            T, m = pose(g), models[g["obj_id"]]
            assert obj["class"] == m.name
            np.testing.assert_allclose(np.array(obj["location"]) / 100.0, T[:3, 3], atol=1e-9)
            np.testing.assert_allclose(np.array(obj["cuboid"][0]) / 100.0,
                                       transform_points(T, (m.min_m + m.size_m)[None])[0], atol=1e-9)
            np.testing.assert_allclose(obj["projected_cuboid"][8], project(K, T, np.zeros((1, 3)))[0], atol=1e-6)
            assert len(obj["keypoint_visibility"]) == 9 and set(obj["keypoint_visibility"]) <= {0, 1}


def test_nvlabs_dope_loader_reads_it(dataset):
    """What NVlabs' DOPE training scripts read, read the way they read it: per image objects[].class,
    projected_cuboid (9 points: nvisii style, centroid last), location, quaternion_xyzw; next to the images
    _camera_settings.json (intrinsics) and _object_settings.json (cuboid_dimensions, cm)."""
    models = {m.name: m for m in load_models(MODELS)}
    for chunk, im, _, _, _, K in frames(dataset):
        data = json.loads((chunk / "rgb" / f"{im:06d}.json").read_text())
        camera = json.loads((chunk / "rgb" / "_camera_settings.json").read_text())["camera_settings"][0]
        intrinsics = camera["intrinsic_settings"]
        assert [intrinsics[k] for k in ("fx", "fy", "cx", "cy")] == [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        settings = json.loads((chunk / "rgb" / "_object_settings.json").read_text())
        for info in data["objects"]:
            assert len(info["projected_cuboid"]) == 9 and len(info["location"]) == 3
            assert len(info["quaternion_xyzw"]) == 4
            dims = next(o["cuboid_dimensions"] for o in settings["exported_objects"] if o["class"] == info["class"])
            np.testing.assert_allclose(np.array(dims) / 100.0, models[info["class"]].size_m)


@pytest.mark.slow
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
    for (_, im, dope, gt, _, _), (_, _, dope0, gt0, _, _) in zip(frames(out), frames(dataset)):
        assert gt == gt0 and dope == dope0
        a, b = (cv2.imread(str(d / "train_pbr/000000/rgb" / f"{im:06d}.jpg")).astype(float) for d in (out, dataset))
        assert np.abs(a - b).mean() < 1.0


def _broken_copy(tmp_path: Path, name: str, edit) -> Path:
    model = tmp_path / name
    shutil.copytree(MODELS[0], model)
    obj = model / "mesh.obj"
    obj.write_text("\n".join(edit(line) for line in obj.read_text().splitlines()) + "\n")
    return model


def test_bad_input_writes_nothing(dataset, tmp_path):
    not_a_model = tmp_path / "photos"
    not_a_model.mkdir()
    with pytest.raises(ContractError, match="no n2d.json"):
        generate_dataset([not_a_model], tmp_path / "ds", small_config())
    with pytest.raises(ContractError, match="no models"):
        generate_dataset([], tmp_path / "ds", small_config())
    in_mm = _broken_copy(tmp_path, "mm", lambda line: "v " + " ".join(str(1000 * float(v)) for v in line.split()[1:])
                         if line.startswith("v ") else line)
    with pytest.raises(ContractError, match="millimetres"):
        generate_dataset([in_mm], tmp_path / "ds", small_config())
    no_uv = _broken_copy(tmp_path, "nouv", lambda line: "" if line.startswith("vt ") else
                         " ".join(c.split("/")[0] for c in line.split()) if line.startswith("f ") else line)
    with pytest.raises(ContractError, match="texture coordinates"):
        generate_dataset([no_uv], tmp_path / "ds", small_config())
    with pytest.raises(ConfigError, match="frames"):
        load_config(DatasetConfig, overrides=["frames=0"])
    assert not (tmp_path / "ds").exists() and not (tmp_path / "ds.partial").exists()
    # an existing dataset is never overwritten without --overwrite, and stays intact
    with pytest.raises(ContractError, match="already exists"):
        generate_dataset(MODELS, dataset, small_config())
    assert read_manifest(dataset)["complete"]


@pytest.mark.slow
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
