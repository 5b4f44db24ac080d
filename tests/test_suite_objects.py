"""The object suite: every object generates, deterministically, into a complete ground-truth model directory that
the dataset stage loads; metric, standing Z up on its bottom, closed and wound outwards, textured through UVs, and
of the kinds and symmetries it claims."""

import json
import math

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull, cKDTree

from n2d_common.contracts import MANIFEST, open_stage
from n2d_common.errors import ConfigError
from n2d_dataset.models import load_models
from n2d_sim import suite
from n2d_sim.objects import SAMPLE_OBJECTS, sample_object_dir
from n2d_sim.suite import SUITE, SUITE_OBJECTS, TAGS, suite_object_dir, write_suite_object

GENERATED = tuple(n for n in SUITE if SUITE_OBJECTS[n].maker is not None)
FILES = ("mesh.obj", "mesh.mtl", "albedo.png", "models_info.json", MANIFEST)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A private cache: the tests never touch ~/.cache."""
    return tmp_path_factory.mktemp("suite_cache")


@pytest.fixture(scope="module")
def obj_dir(cache):
    """name -> its model directory, each generated once for the module."""
    return lambda name: suite_object_dir(name, cache)


def _obj(directory):
    """Positions, UVs, normals and (v, vt, vn) corner indices of a model's OBJ."""
    return suite._read_obj(directory / "mesh.obj")


def _solid(directory):
    v, _, _, corners = _obj(directory)
    return trimesh.Trimesh(v, corners[..., 0])


def _albedo_at_faces(directory):
    """The albedo (sRGB uint8) at every face's centroid UV, and the face areas."""
    v, vt, _, corners = _obj(directory)
    image = cv2.cvtColor(cv2.imread(str(directory / "albedo.png")), cv2.COLOR_BGR2RGB)
    uv = vt[corners[..., 1]].mean(1)
    h, w = image.shape[:2]
    px = np.clip((uv[:, 0] * w).astype(int), 0, w - 1), np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1)
    P = v[corners[..., 0]]
    area = np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1) / 2
    return image[px[1], px[0]].astype(float), area


def test_the_suite_is_the_samples_and_at_least_eight_new_objects():
    assert SUITE[:len(SAMPLE_OBJECTS)] == SAMPLE_OBJECTS
    assert len(GENERATED) >= 8 and len(set(SUITE)) == len(SUITE)
    for o in SUITE_OBJECTS.values():
        assert o.description and o.tags and set(o.tags) <= set(TAGS), o.name
    for name in SAMPLE_OBJECTS:
        assert suite_object_dir(name) == sample_object_dir(name)
    with pytest.raises(ConfigError, match="unknown suite object"):
        suite_object_dir("teapot")


def test_the_kinds_cover_what_tuning_needs():
    tags = {t for o in SUITE_OBJECTS.values() for t in o.tags}
    assert {"textureless", "dark", "glossy", "thin", "concave", "fine", "symmetric", "flat", "tall"} <= tags
    labels = {n: SUITE_OBJECTS[n].symmetry.label for n in SUITE}
    assert labels["cube_plain"] == "discrete 24"
    assert labels["can"] == "continuous about z + 2-fold flip"
    assert sum(label == "none" for label in labels.values()) >= 6


@pytest.mark.parametrize("name", SUITE)
def test_object_is_a_complete_textured_model_the_dataset_loads(name, obj_dir):
    directory = obj_dir(name)
    manifest = open_stage(directory, "model")
    assert manifest["extra"]["ground_truth"] is True and manifest["config"]["name"] == name
    assert set(manifest["config"]["material"]) >= {"roughness", "specular"}
    assert sorted(p.name for p in directory.iterdir()) == sorted(FILES)
    (model,) = load_models([directory])  # checks vt and metres
    assert model.name == name

    v, vt, vn, corners = _obj(directory)
    assert corners.shape[1:] == (3, 3) and len(corners) <= 20000  # a UV and a normal at every corner
    assert vt.min() >= 0 and vt.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(vn, axis=1), 1, atol=1e-4)
    image = cv2.imread(str(directory / "albedo.png"))
    assert max(image.shape[:2]) <= 1024

    lo, hi = v.min(0), v.max(0)
    assert 0.03 <= (hi - lo).max() <= 0.25  # 3 to 25 cm
    np.testing.assert_allclose(model.min_m, lo, atol=1e-6)
    np.testing.assert_allclose(model.size_m, hi - lo, atol=1e-6)


@pytest.mark.parametrize("name", SUITE)
def test_mesh_is_closed_outward_and_stands_z_up_on_its_bottom(name, obj_dir):
    directory = obj_dir(name)
    solid = _solid(directory)
    assert solid.is_watertight and solid.is_winding_consistent and solid.volume > 0

    v, _, vn, corners = _obj(directory)
    lo, hi = v.min(0), v.max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-7)  # object frame at the bounding-box centre
    info = json.loads((directory / "models_info.json").read_text())["1"]
    assert lo[2] == pytest.approx(-info["size_z"] / 2000, abs=1e-6)

    # Normals point out: every corner's normal on the outer side of its face.
    P = v[corners[..., 0]]
    face_n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
    assert (np.einsum("fkc,fc->fk", vn[corners[..., 2]], face_n) > 0).all()

    # It stands: the centre of mass is over the footprint (the hull of the lowest vertices), 3 mm inside.
    foot = v[v[:, 2] < lo[2] + 2e-4, :2]
    hull = ConvexHull(foot)
    assert hull.volume > 4e-4  # at least 4 cm^2
    com = solid.center_mass
    assert (hull.equations @ np.array([com[0], com[1], 1.0])).max() < -0.003


@pytest.mark.parametrize("name", SUITE)
def test_models_info_matches_the_mesh_and_declares_the_symmetry(name, obj_dir):
    directory = obj_dir(name)
    info = json.loads((directory / "models_info.json").read_text())
    assert list(info) == ["1"]
    info = info["1"]
    v = _obj(directory)[0] * 1000
    hull = v[ConvexHull(v).vertices]
    diameter = np.sqrt(((hull[:, None] - hull[None]) ** 2).sum(-1)).max()
    assert info["diameter"] == pytest.approx(diameter, abs=1e-3)
    for i, axis in enumerate("xyz"):
        assert info[f"min_{axis}"] == pytest.approx(v[:, i].min(), abs=1e-3)
        assert info[f"size_{axis}"] == pytest.approx(np.ptp(v[:, i]), abs=1e-3)
    symmetry = SUITE_OBJECTS[name].symmetry
    assert ("symmetries_discrete" in info) == (symmetry.order > 1)
    assert ("symmetries_continuous" in info) == (symmetry.continuous_axis is not None)
    for T in info.get("symmetries_discrete", []):
        R = np.array(T).reshape(4, 4)[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.mark.parametrize("name", GENERATED)
def test_generation_is_deterministic(name, obj_dir, tmp_path):
    cached = obj_dir(name)
    fresh = write_suite_object(name, tmp_path / name)
    for file in FILES:
        if file == MANIFEST:
            new, old = (json.loads((d / file).read_text()) for d in (fresh, cached))
            new.pop("created"), old.pop("created")
            assert new == old
        else:
            assert (fresh / file).read_bytes() == (cached / file).read_bytes(), f"{name}/{file} differs"


@pytest.mark.parametrize("name", SUITE)
def test_tags_describe_the_object(name, obj_dir):
    directory = obj_dir(name)
    obj = SUITE_OBJECTS[name]
    tags = set(obj.tags)
    v = _obj(directory)[0]
    size = np.ptp(v, axis=0)
    assert ("flat" in tags) == (size.min() <= 0.4 * np.median(size))
    assert ("tall" in tags) == (size[2] >= 1.45 * size[:2].max())
    colors, area = _albedo_at_faces(directory)
    spread = colors.max(0) - colors.min(0)
    assert ("textureless" in tags) == (spread.max() <= 2), spread
    if "textured" in tags:
        assert np.sqrt(np.average((colors - np.average(colors, 0, area)) ** 2, axis=0, weights=area)).max() > 20
    linear = np.where(colors / 255 <= 0.04045, colors / 255 / 12.92, ((colors / 255 + 0.055) / 1.055) ** 2.4)
    assert ("dark" in tags) == (np.average(linear.mean(1), weights=area) < 0.08)
    solid = _solid(directory)
    assert ("concave" in tags) == (solid.volume < 0.85 * solid.convex_hull.volume)
    material = open_stage(directory, "model")["config"]["material"]
    assert ("glossy" in tags) == (material["roughness"] <= 0.35)
    assert ("metallic" in tags) == (material.get("metallic", 0.0) == 1.0)
    assert ("symmetric" in tags) == (obj.symmetry.label != "none")


@pytest.mark.parametrize("name", ["cube_plain", "can"])
def test_declared_symmetries_hold(name, obj_dir):
    directory = obj_dir(name)
    symmetry = SUITE_OBJECTS[name].symmetry
    v = _obj(directory)[0]
    tree = cKDTree(v)
    for R in symmetry.rotations():  # the finite rotations map the vertex set onto itself
        assert tree.query(v @ R.T)[0].max() < 1e-6
    if symmetry.continuous_axis is not None:
        # A faceted body of revolution: one facet's turn maps the vertices onto themselves, and the facets are
        # within 0.05 mm of the round surface, so any turn keeps the surface in place to that.
        a = 2 * math.pi / suite.CAN_SEGMENTS
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        assert tree.query(v @ Rz.T)[0].max() < 1e-6
        assert np.hypot(v[:, 0], v[:, 1]).max() * (1 - math.cos(a / 2)) < 5e-5
    # ... and the texture is one colour, so the symmetry holds for the appearance too.
    colors, _ = _albedo_at_faces(directory)
    assert np.ptp(colors, axis=0).max() <= 2


def test_a_textureless_object_declared_without_symmetry_has_none_of_a_box(obj_dir):
    v = _obj(obj_dir("bracket"))[0]
    tree = cKDTree(v)
    for R in suite._cube_rotations()[1:]:
        assert tree.query(v @ R.T)[0].max() > 1e-3


def test_cache_is_versioned_atomic_and_reused(tmp_path, monkeypatch):
    monkeypatch.setenv("N2D_SUITE_DIR", str(tmp_path))
    path = suite_object_dir("cube_plain")
    assert path == tmp_path / suite.suite_version() / "cube_plain"
    assert open_stage(path, "model")["extra"]["suite_version"] == suite.suite_version()
    stamp = (path / "mesh.obj").stat().st_mtime_ns
    assert suite_object_dir("cube_plain") == path and (path / "mesh.obj").stat().st_mtime_ns == stamp
    assert [p.name for p in path.parent.iterdir()] == ["cube_plain"]  # no temporary left behind
    # A half-written directory (no manifest) is never taken for the object: it is replaced.
    (path / MANIFEST).unlink()
    assert suite_object_dir("cube_plain") == path and open_stage(path, "model")["complete"]


def test_cli_writes_objects_and_a_contact_sheet(tmp_path):
    suite.main(["--out", str(tmp_path / "objs"), "--sheet", str(tmp_path / "sheet.jpg"), "cube_plain", "bracket"])
    assert sorted(p.name for p in (tmp_path / "objs").iterdir()) == ["bracket", "cube_plain"]
    sheet = cv2.imread(str(tmp_path / "sheet.jpg"))
    assert sheet.shape == (240 + 30, 4 * 2 * 240, 3)
    tile = sheet[:240, :480].astype(int)
    assert (np.abs(tile - 232).max(2) > 20).mean() > 0.05  # the objects are drawn, not just background
