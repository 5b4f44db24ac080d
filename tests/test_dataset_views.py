"""The views a dataset draws of a model: a closed model (its underside modelled: fused from two placements, or a
simulator's whole mesh) is seen from every side, in-hand frames from below included; an open model (one placement,
cut at the plate) is never seen from below its cut. Real raster datasets, poses read back from their annotations."""

import shutil

import numpy as np
import pytest

from n2d_common.config import load_config
from n2d_common.contracts import read_manifest, write_manifest
from n2d_dataset.check import frames, pose
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dataset.models import load_models
from n2d_dataset.poses import view_elevation_deg
from n2d_sim.objects import sample_object_dir

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

IN_HAND = ["frames=24", "camera.width=80", "camera.height=60", "camera.focal_px=75", "render.engine=raster",
           "scene.in_hand=1.0", "scene.instances_per_model=[1,1]", "scene.distractors=[0,0]", "scene.boards=0",
           "workers=1"]


def _one_placement(tmp_path):
    """The sample box as a reconstruction of one placement records it: cut at the plate, so open."""
    model = tmp_path / "box_open"
    shutil.copytree(sample_object_dir("box"), model)
    manifest = read_manifest(model)
    write_manifest(model, "model", config=manifest["config"], extra={"placements": 1, "method": "fast"})
    return model


def _elevations(dataset):
    return np.array([view_elevation_deg(pose(gt[0])) for _, _, _, gt, _, _ in frames(dataset)])


def test_a_closed_model_is_seen_from_below_an_open_one_never(tmp_path):
    closed, open_ = sample_object_dir("box"), _one_placement(tmp_path)
    assert [m.closed for m in load_models([closed, open_])] == [True, False]
    views = {}
    for name, model in (("closed", closed), ("open", open_)):
        generate_dataset([model], tmp_path / name, load_config(DatasetConfig, overrides=IN_HAND))
        views[name] = _elevations(tmp_path / name)
    assert len(views["closed"]) == len(views["open"]) == 24
    assert (views["closed"] < -20).sum() >= 3, views["closed"]  # in-hand frames from below
    assert (views["closed"] > 20).sum() >= 3, views["closed"]
    base_m = load_models([open_])[0].min_m[2]
    # never below the plane of the open model's base, so never from more than a few degrees below its centre
    assert views["open"].min() > -20, views["open"]
    for _, _, _, gt, _, _ in frames(tmp_path / "open"):
        eye = np.linalg.inv(pose(gt[0]))[:3, 3]
        assert eye[2] >= base_m
