"""Sessions of two placements (the object swept, turned over, swept again): the simulator's placement, the session
contract, registration from the masks against the simulator's truth, refusal of a wrong second placement, and
one-placement sessions left as they were."""

import json
from dataclasses import replace

import numpy as np
import pytest

from n2d_common.errors import ContractError
from n2d_common.formats.session import PLACEMENT_KEY, read_session, transforms_json
from n2d_common.frames import inv_T, transform_points
from n2d_reconstruct.data import load_session
from n2d_reconstruct.hull import HullConfig, VisualHull
from n2d_reconstruct.neus import NeusConfig
from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct
from n2d_reconstruct.placements import PlacementsConfig, fuse, register
from n2d_sim.session import render_session, small_world, turned
from n2d_sim.suite import suite_object_dir
from n2d_sim.world import SimWorldConfig, T_plate_obj, model_vertices, object_info, object_vertices, placement_R

VIEWS = 12
SIZE = (160, 120)
FAST = PlacementsConfig(up_directions=100, yaw_steps=24, starts=4, refined=1, voxel_m=0.002)
"""A smaller search than the default, for the refusals (the right answer is not needed there) and, with two
candidates refined, for the NeuS stage test (the registration itself is tested with the default search)."""


def test_a_turned_placement_lies_on_its_lowest_vertex_and_upright_is_unchanged():
    upright = SimWorldConfig(object="box")
    lift = np.eye(4)
    lift[2, 3] = -object_info(upright)["min_z"] / 1000
    assert np.array_equal(T_plate_obj(upright), lift)
    side = turned(upright)
    assert side.placement_deg == (90.0, 0.0, 0.0)
    T = T_plate_obj(side)
    points = transform_points(T, object_vertices(side))
    assert abs(points[:, 2].min()) < 1e-12 and np.allclose(T[:3, :3], placement_R((90, 0, 0)))
    assert np.ptp(points[:, 2]) == pytest.approx(object_info(side)["size_y"] / 1000, rel=1e-3)  # lying on its side
    with pytest.raises(ValueError, match="placement_deg"):
        SimWorldConfig(placement_deg=(0.0, float("nan"), 0.0))


def test_one_placement_files_are_unchanged():
    frames = [("images/0000.png", "masks/0000.png", np.eye(4))]
    assert PLACEMENT_KEY not in transforms_json(np.eye(3), None, 4, 3, frames)["frames"][0]
    assert PLACEMENT_KEY not in transforms_json(np.eye(3), None, 4, 3, frames, [0])["frames"][0]
    assert transforms_json(np.eye(3), None, 4, 3, frames * 2, [0, 1])["frames"][1][PLACEMENT_KEY] == 1


@pytest.fixture(scope="module")
def mug_world():
    return small_world(str(suite_object_dir("mug")), *SIZE)


@pytest.fixture(scope="module")
def two_placements(tmp_path_factory, mug_world):
    out = tmp_path_factory.mktemp("placements") / "mug"
    return out, render_session(out, mug_world, VIEWS, placements=[turned(mug_world)])


@pytest.mark.slow  # its fixture renders the session (about 12 s)
def test_a_two_placement_session_holds_both_sweeps_each_in_its_own_frame(two_placements):
    out, truth = two_placements
    session = read_session(out)
    assert session.placements == 2 and [v.placement for v in session.views] == [0] * VIEWS + [1] * VIEWS
    capture = json.loads((out / "capture.json").read_text())
    assert [p["simulated_placement_deg"] for p in capture["placements"]] == [[0.0, 0.0, 0.0], [90.0, 0.0, 0.0]]
    data = load_session(out, holdout_every=0)
    assert data.train.placements == 2 and len(data.train.of_placement(1)) == VIEWS
    # each placement's hull, in its own frame, holds the object as that placement stood
    for p in (0, 1):
        hull = VisualHull(data.train.of_placement(p), HullConfig())
        inside = hull(transform_points(truth.placements[p], model_vertices(truth.model_dir)))
        assert np.quantile(inside, 0.95) < 2 * hull.pixel_m


def _errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    E = inv_T(truth) @ T
    return float(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))), 1000 * float(
        np.linalg.norm(E[:3, 3]))


@pytest.mark.slow
def test_registration_from_the_masks_recovers_the_simulators_truth(two_placements):
    out, truth = two_placements
    data = load_session(out, holdout_every=0)
    registration = register(data.train, data.plate_radius_m, PlacementsConfig(), HullConfig())
    deg, mm = _errors(registration.T_first[1], truth.T_first_placement(1))
    # 12 views of 160x120 per placement, a pixel is ~3 mm on the object (measured: 0.3-0.5 degrees, 0.5-1 mm)
    assert deg < 1.5 and mm < 2.0, (deg, mm, registration.report)
    entry = registration.report["registered"][0]
    assert entry["min_view_coverage"] >= 0.95 and 85 < entry["turned_deg"] < 95
    fused = fuse(data, registration)
    assert fused.plates.shape == (2, 4) and np.allclose(fused.plates[0], [0, 0, 1, 0])
    # fused, every view's camera is in the first placement's frame: the object as it stood there projects into
    # the masks of the second placement's views too
    hull = VisualHull(fused.train, HullConfig(), fused.plates)
    points = transform_points(truth.T_turntable_obj, model_vertices(truth.model_dir))
    assert np.quantile(hull(points), 0.9) < 2 * hull.pixel_m
    # the underside (what the first sweep never sees from below) is carved by the second: the fused hull's
    # bottom is the object's own, not the whole footprint of the first hull on the plate
    first = VisualHull(data.train.of_placement(0), HullConfig())
    xy = np.stack(np.meshgrid(np.linspace(-0.06, 0.06, 41), np.linspace(-0.06, 0.06, 41)), -1).reshape(-1, 2)
    low = np.column_stack([xy, np.full(len(xy), 0.002)])
    assert (hull(low) < 0).sum() <= (first(low) < 0).sum()


@pytest.mark.slow
def test_another_object_as_the_second_placement_is_refused_naming_the_check(tmp_path, mug_world):
    out = tmp_path / "wrong"
    render_session(out, mug_world, VIEWS, placements=[turned(replace(mug_world, object="box"))])
    data = load_session(out, holdout_every=0)
    with pytest.raises(ContractError, match=r"silhouette check.*images/00\d\d\.png.*nothing is fused"):
        register(data.train, data.plate_radius_m, FAST, HullConfig())
    # through the stage: refused before anything is written
    model = tmp_path / "model"
    with pytest.raises(ContractError, match="silhouette check"):
        reconstruct(out, model, replace(ReconstructConfig(placements=FAST), holdout_every=0))
    assert not model.exists() and not model.with_name("model.partial").exists()


@pytest.mark.slow
def test_the_first_placement_swept_twice_is_refused_naming_the_check(tmp_path, mug_world):
    out = tmp_path / "twice"
    render_session(out, mug_world, VIEWS, placements=[mug_world])
    data = load_session(out, holdout_every=0)
    with pytest.raises(ContractError, match="turn check.*underside stays unseen"):
        register(data.train, data.plate_radius_m, FAST, HullConfig())


@pytest.mark.slow
def test_a_box_fits_its_masks_in_four_poses_and_the_photos_pick_the_true_one(tmp_path):
    world = small_world("box", *SIZE)
    out = tmp_path / "box"
    truth = render_session(out, world, VIEWS, placements=[turned(world)])
    data = load_session(out, holdout_every=0)
    registration = register(data.train, data.plate_radius_m, PlacementsConfig(), HullConfig())
    entry = registration.report["registered"][0]
    # measured: 4 poses fit by shape, photo differences 1.40, 0.19, 0.56, 1.45; 0.3 degrees, 1.1 mm
    assert entry["fit_by_shape"] >= 2 and min(entry["photo_difference"]) < 0.5, entry
    deg, mm = _errors(registration.T_first[1], truth.T_first_placement(1))
    assert deg < 1.5 and mm < 2.5, (deg, mm, entry)


@pytest.mark.slow
def test_the_stage_reconstructs_a_two_placement_session_in_the_first_placements_frame(two_placements, tmp_path):
    out, truth = two_placements
    cfg = ReconstructConfig(object_name="mug", holdout_every=8)
    cfg.mesh.voxel_m, cfg.mesh.target_faces, cfg.texture.size_px = 0.003, 3000, 128
    # at 160 x 120 a pixel is 3.5 mm at the mug: the facets of a hull from 10 views lie flat within the planes
    # phase's 3-pixel band, and snapping the mug's round sides onto them grows its width by 10 mm (measured: 95 to
    # 105 mm); the phase is tested on its own in test_planes.py
    cfg.refine.enabled = cfg.planes.enabled = False
    report = reconstruct(out, tmp_path / "model", cfg, ground_truth=truth.model_dir)
    assert report["placements"]["registered"][0]["min_view_coverage"] >= 0.95
    assert report["model"]["watertight"] and report["views"]["train"] + report["views"]["heldout"] == 2 * VIEWS
    # the model frame is the first placement's: Z up as the mug first stood (on its side the height would be its
    # 80 mm width); 10 training views per placement leave the hull loose around the handle (measured: 104, 95, 97
    # mm against 111, 80, 95)
    size = np.array(report["model"]["size_mm"])
    true = np.array([object_info(SimWorldConfig(object=str(truth.model_dir)))[f"size_{a}"] for a in "xyz"])
    assert abs(size[2] - true[2]) < 0.05 * true[2] and np.all(np.abs(size - true) < 0.25 * true), (size, true)
    assert report["geometry"]["underside_chamfer_mm"] < 5, report["geometry"]


@pytest.mark.slow
def test_neus_reconstructs_a_two_placement_session_closed_with_the_underside_it_saw(two_placements, tmp_path):
    """NeuS trains on both sweeps in the first placement's frame and is meshed inside their fused hull, above every
    plate: the mesh is closed, with the underside the second sweep saw."""
    out, truth = two_placements
    cfg = ReconstructConfig(object_name="mug", holdout_every=8, method="neus", placements=replace(FAST, refined=2))
    cfg.mesh.voxel_m, cfg.mesh.target_faces, cfg.texture.size_px = 0.003, 3000, 128
    tiny = NeusConfig.preset("tiny")
    cfg.neus = replace(tiny, steps=150, pretrain=replace(tiny.pretrain, steps=60))
    report = reconstruct(out, tmp_path / "model", cfg, ground_truth=truth.model_dir)
    assert report["model"]["watertight"] and report["placements"]["placements"] == 2
    # meshed inside the hull: the hull phase moves no vertex far (measured 2.5 mm; 24 mm when the field was meshed
    # in its whole box, floaters included)
    assert report["hull"]["max_move_mm"] < 5, report["hull"]
    # 150 steps of a tiny field from a hull of 10 views per placement at 160 x 120 (measured: 2.5 %, underside
    # 1.7 mm); benchmarks/reconstruct.py --placements 2 --methods neus measures the real thing
    assert report["geometry"]["chamfer_pct_diameter"] < 4 and report["geometry"]["underside_chamfer_mm"] < 3, \
        report["geometry"]
