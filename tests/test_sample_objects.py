"""The shipped sample objects: complete model directories, watertight textured metric meshes, reproducible."""

import json
import math

import numpy as np
import pytest
import trimesh

from n2d_common.contracts import MANIFEST, open_stage
from n2d_common.errors import ConfigError
from n2d_sim.objects import SAMPLE_OBJECTS, generate_object, sample_object_dir

SIZE_MM = {"box": (90.0, 60.0, 140.0), "bottle": (70.0, 70.0, 150.0)}
"""The documented sizes (x, y, z) in millimetres."""
FILES = ("mesh.obj", "mesh.mtl", "albedo.png", "models_info.json", MANIFEST)


def test_there_are_two_objects_of_different_shape_and_size():
    assert set(SAMPLE_OBJECTS) == set(SIZE_MM)
    with pytest.raises(ConfigError, match="unknown sample object"):
        sample_object_dir("teapot")


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_directory_is_a_complete_small_ground_truth_model(name):
    directory = sample_object_dir(name)
    manifest = open_stage(directory, "model")
    assert manifest["extra"]["source"] == "n2d_sim.objects"
    assert manifest["extra"]["ground_truth"] is True
    assert sorted(p.name for p in directory.iterdir()) == sorted(FILES)
    assert sum(p.stat().st_size for p in directory.iterdir()) < 1_000_000


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_mesh_is_textured_watertight_metric_and_centred(name):
    directory = sample_object_dir(name)
    mesh = trimesh.load(directory / "mesh.obj", force="mesh")
    assert isinstance(mesh.visual, trimesh.visual.TextureVisuals)
    uv = mesh.visual.uv
    assert uv.shape == (len(mesh.vertices), 2) and uv.min() >= 0 and uv.max() <= 1
    image = mesh.visual.material.image
    assert image is not None and max(image.size) <= 1024
    assert len(mesh.faces) <= 5000

    # UV seams split vertices; the surface itself must be closed and consistently wound outwards.
    solid = trimesh.Trimesh(mesh.vertices, mesh.faces)
    assert solid.is_watertight and solid.is_winding_consistent and solid.volume > 0

    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-7)
    np.testing.assert_allclose((hi - lo) * 1000, SIZE_MM[name], atol=1e-3)
    if name == "box":
        assert solid.volume == pytest.approx(0.09 * 0.06 * 0.14, rel=1e-6)
    else:
        assert 0.5 * math.pi * 0.035**2 * 0.15 < solid.volume < math.pi * 0.035**2 * 0.15


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_models_info_matches_the_mesh(name):
    directory = sample_object_dir(name)
    info = json.loads((directory / "models_info.json").read_text())
    assert list(info) == ["1"]
    info = info["1"]
    v = trimesh.load(directory / "mesh.obj", force="mesh").vertices * 1000
    diameter = max(np.linalg.norm(v - p, axis=1).max() for p in v)
    assert info["diameter"] == pytest.approx(diameter, abs=1e-3)
    for i, axis in enumerate("xyz"):
        assert info[f"min_{axis}"] == pytest.approx(v[:, i].min(), abs=1e-3)
        assert info[f"size_{axis}"] == pytest.approx(SIZE_MM[name][i], abs=1e-3)
    # The labels break every symmetry, so none is declared.
    assert "symmetries_discrete" not in info and "symmetries_continuous" not in info


def test_regenerating_gives_identical_files(tmp_path):
    for name in SAMPLE_OBJECTS:
        fresh = generate_object(name, tmp_path)
        shipped = sample_object_dir(name)
        for file in FILES:
            if file == MANIFEST:
                new, old = (json.loads((d / file).read_text()) for d in (fresh, shipped))
                new.pop("created"), old.pop("created")
                assert new == old
            else:
                assert (fresh / file).read_bytes() == (shipped / file).read_bytes(), f"{name}/{file} differs"
