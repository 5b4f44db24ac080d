"""Symmetries found from meshes built with trimesh (n2d_common.symmetry), BOP's models_info fields, the
symmetric and canonical poses, and BOP's MSSD / MSPD errors (n2d_dope.metrics)."""

import json
import math
import time

import numpy as np
import pytest
import trimesh

from n2d_common.errors import ConfigError, ContractError
from n2d_common.frames import make_T, transform_points
from n2d_common.symmetry import (
    AmbiguousSymmetry,
    Symmetries,
    SymmetryError,
    canonical_pose,
    find_symmetries,
    from_models_info,
    symmetric_poses,
    to_models_info,
)
from n2d_dope.metrics import bop_recall, mspd, mspd_thresholds, mssd, mssd_thresholds

FLIPS = [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
SIDE_COLOURS = [(220, 30, 30), (30, 200, 30), (30, 30, 220), (230, 220, 40), (200, 40, 200), (40, 210, 210)]


def detect(mesh: trimesh.Trimesh, **kwargs):
    return find_symmetries(mesh.vertices, mesh.faces, **kwargs)


def random_pose(seed: int) -> np.ndarray:
    R = trimesh.transformations.random_rotation_matrix(np.random.default_rng(seed).random(3))[:3, :3]
    return make_T(R, [0.02, -0.01, 0.5])


def maps_onto_itself(S: np.ndarray, vertices: np.ndarray, atol: float = 1e-9) -> bool:
    """Whether S permutes the points (a box's or prism's vertices)."""
    moved = transform_points(S, vertices)
    return bool(np.all(np.min(np.linalg.norm(moved[:, None] - vertices[None], axis=2), axis=1) < atol))


def textured_box(extents, colours):
    """A box whose sides (+x, -x, +y, -y, +z, -z) are painted colours[0..5]: per-face-corner UVs (v up) into
    a 3 x 2 atlas of tiles, each side drawn inside its tile with a margin so that bilinear sampling stays in."""
    box = trimesh.creation.box(extents=extents)
    tile = 16
    texture = np.zeros((2 * tile, 3 * tile, 3), np.uint8)
    uvs = np.zeros((len(box.faces), 3, 2))
    for f, (face, normal) in enumerate(zip(box.faces, box.face_normals)):
        axis = int(np.argmax(np.abs(normal)))
        side = 2 * axis + int(normal[axis] < 0)
        row, col = divmod(side, 3)
        texture[row * tile:(row + 1) * tile, col * tile:(col + 1) * tile] = colours[side]
        others = [a for a in range(3) if a != axis]
        inside = box.vertices[face][:, others] / np.asarray(extents, float)[others] + 0.5
        uvs[f, :, 0] = (col + 0.1 + 0.8 * inside[:, 0]) / 3
        uvs[f, :, 1] = 1 - (row + 0.1 + 0.8 * inside[:, 1]) / 2
    return box, uvs, texture


def mug(sections: int = 64, handle_sections: int = 32) -> trimesh.Trimesh:
    """A cup: a cylindrical wall, a bottom and a torus handle half outside the wall (concatenated, no boolean)."""
    wall = trimesh.creation.annulus(r_min=0.035, r_max=0.04, height=0.1, sections=sections)
    bottom = trimesh.creation.cylinder(radius=0.04, height=0.005, sections=64)
    bottom.apply_translation([0, 0, -0.0475])
    handle = trimesh.creation.torus(major_radius=0.025, minor_radius=0.006, major_sections=handle_sections,
                                    minor_sections=handle_sections)
    handle.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    handle.apply_translation([0.04, 0, 0])
    return trimesh.util.concatenate([wall, bottom, handle])


def test_cube_has_the_24_rotations_of_the_octahedral_group():
    cube = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    sym = detect(cube)
    assert sym.group_order == 24 and len(sym.discrete) == 23 and not sym.continuous
    rotations = [np.eye(3)] + [S[:3, :3] for S in sym.discrete]
    for S in sym.discrete:
        assert np.allclose(S[:3, :3].T @ S[:3, :3], np.eye(3), atol=1e-9) and np.linalg.det(S[:3, :3]) > 0
        assert np.allclose(S[3], [0, 0, 0, 1]) and np.allclose(S[:3, 3], 0, atol=1e-9)
        assert maps_onto_itself(S, cube.vertices)
    for A in rotations:  # closed: a group
        for B in rotations:
            assert min(np.abs(A @ B - C).max() for C in rotations) < 1e-6
    assert sym.diameter == pytest.approx(0.1 * math.sqrt(3))


def test_box_with_three_distinct_sides_has_the_three_half_turns():
    box = trimesh.creation.box(extents=[0.06, 0.1, 0.16])
    sym = detect(box)
    assert sym.group_order == 4 and not sym.continuous
    found = sorted((S[:3, :3] for S in sym.discrete), key=lambda R: tuple(np.diag(R)), reverse=True)
    assert np.allclose(found, FLIPS, atol=1e-9)
    assert all(r["verdict"] == "symmetric" for r in sym.residuals)


def test_cylinder_is_continuous_about_its_axis_with_a_half_turn_across():
    cylinder = trimesh.creation.cylinder(radius=0.04, height=0.12, sections=64)
    cylinder.apply_translation([0.01, -0.02, 0.03])  # object frame elsewhere: the offsets follow
    sym = detect(cylinder)
    assert sym.group_order == math.inf
    (axis, offset), = sym.continuous
    assert np.allclose(axis, [0, 0, 1], atol=1e-6)
    assert np.allclose(offset, [0.01, -0.02, 0], atol=1e-6)  # the point of the axis nearest the origin
    (flip,) = sym.discrete
    assert np.allclose(flip[:3, :3], FLIPS[0], atol=1e-6)
    assert maps_onto_itself(flip, cylinder.vertices, atol=1e-6)


def test_mug_has_no_symmetry():
    sym = detect(mug())
    assert sym.group_order == 1 and not sym.discrete and not sym.continuous
    assert to_models_info(sym) == {}


def test_hexagonal_prism_is_discrete_not_continuous():
    prism = trimesh.creation.cylinder(radius=0.04, height=0.12, sections=6)
    sym = detect(prism)
    assert sym.group_order == 12 and not sym.continuous  # D6: 6 turns about z, 6 half turns across
    assert all(maps_onto_itself(S, prism.vertices, atol=1e-6) for S in sym.discrete)


def test_texture_decides_which_shape_symmetries_count():
    extents = [0.06, 0.1, 0.16]
    box, uvs, texture = textured_box(extents, SIDE_COLOURS)
    assert detect(box, face_uvs=uvs, texture=texture).group_order == 1  # every half turn swaps two colours
    box, uvs, texture = textured_box(extents, [(128, 128, 128)] * 6)
    assert detect(box, face_uvs=uvs, texture=texture).group_order == 4
    grey = (128, 128, 128)
    box, uvs, texture = textured_box(extents, [grey, grey, grey, grey, SIDE_COLOURS[0], SIDE_COLOURS[2]])
    sym = detect(box, face_uvs=uvs, texture=texture)  # only the half turn about z keeps the top and bottom
    assert len(sym.discrete) == 1 and np.allclose(sym.discrete[0][:3, :3], FLIPS[2], atol=1e-9)
    with pytest.raises(ConfigError, match="go together"):
        detect(box, texture=texture)
    with pytest.raises(ContractError, match="face_uvs"):
        detect(box, face_uvs=uvs[:3], texture=texture)


def test_a_nearly_square_box_is_ambiguous_until_the_tolerance_decides():
    box = trimesh.creation.box(extents=np.array([1.0, 1.09, 2.0]) * 0.05)
    with pytest.raises(AmbiguousSymmetry, match=r"90\.0 degree rotation about axis") as info:
        detect(box)
    assert "by hand" in info.value.hint and "tolerance" in info.value.hint
    assert 1.0 < info.value.residual["score"] <= 2.0
    assert isinstance(info.value, ConfigError)
    assert detect(box, tolerance=0.005, tail_tolerance=0.008).group_order == 4
    assert detect(box, tolerance=0.03, tail_tolerance=0.05, normal_fraction=0.2).group_order == 8


def test_bad_meshes_and_parameters_are_clear_errors():
    box = trimesh.creation.box(extents=[0.06, 0.1, 0.16])
    with pytest.raises(ContractError, match="no faces"):
        find_symmetries(box.vertices, np.zeros((0, 3), int))
    vertices = box.vertices.copy()
    vertices[2, 1] = np.nan
    with pytest.raises(ContractError, match="not finite"):
        find_symmetries(vertices, box.faces)
    with pytest.raises(ContractError, match="index vertices"):
        find_symmetries(box.vertices, box.faces + 100)
    with pytest.raises(ConfigError, match="tolerance"):
        detect(box, tolerance=-1)
    with pytest.raises(SymmetryError, match="sphere"):
        detect(trimesh.creation.icosphere(subdivisions=3, radius=0.05))


def test_models_info_round_trip_in_millimetres():
    cylinder = trimesh.creation.cylinder(radius=0.04, height=0.12, sections=64)
    cylinder.apply_translation([0.01, -0.02, 0.03])
    sym = detect(cylinder)
    info = json.loads(json.dumps(to_models_info(sym)))
    assert set(info) == {"symmetries_discrete", "symmetries_continuous"}
    assert info["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [10.0, -20.0, 0.0]}]
    (flip,) = info["symmetries_discrete"]
    assert len(flip) == 16 and np.allclose(np.reshape(flip, (4, 4))[:3, 3], 1000 * sym.discrete[0][:3, 3])
    back = from_models_info({"diameter": 1000 * sym.diameter, **info})
    assert back.diameter == pytest.approx(sym.diameter)
    assert np.allclose(back.discrete[0], sym.discrete[0], atol=1e-8)
    assert np.allclose(back.continuous[0][0], sym.continuous[0][0]) and np.allclose(back.continuous[0][1],
                                                                                    sym.continuous[0][1])
    assert "symmetries_continuous" not in to_models_info(detect(trimesh.creation.box(extents=[0.06, 0.1, 0.16])))
    # as BOP's own files write them
    bop = from_models_info({"symmetries_discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]],
                            "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 0]}]})
    assert np.allclose(bop.discrete[0], np.diag([-1.0, -1, 1, 1])) and np.allclose(bop.continuous[0][0], [0, 0, 1])
    assert from_models_info({"diameter": 50.0}).group_order == 1


@pytest.mark.parametrize("entry, match", [
    ({"symmetries_discrete": [[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]]}, "16 finite numbers"),
    ({"symmetries_discrete": [[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]]}, "proper rigid"),
    ({"symmetries_discrete": [[2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}, "proper rigid"),
    ({"symmetries_discrete": [[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1]]}, "proper rigid"),
    ({"symmetries_discrete": "none"}, "must be a list"),
    ({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]}, "axis is zero"),
    ({"symmetries_continuous": [{"axis": [0, 0, 1]}]}, "needs 'axis' and 'offset'"),
    ({"symmetries_continuous": [{"axis": [0, 1], "offset": [0, 0, 0]}]}, "3 finite numbers"),
    ({"symmetries_continuous": [{"axis": ["z", 0, 1], "offset": [0, 0, 0]}]}, "3 numbers"),
    ({"diameter": -3}, "positive"),
    ([1, 2], "mapping"),
])
def test_malformed_models_info_entries_are_clear_errors(entry, match):
    with pytest.raises(ContractError, match=match) as info:
        from_models_info(entry)
    assert "row-major" in info.value.hint


def test_symmetric_poses_as_bop_discretises_them():
    box = trimesh.creation.box(extents=[0.06, 0.1, 0.16])
    poses = symmetric_poses(detect(box))
    assert len(poses) == 4 and np.allclose(poses[0], np.eye(4))
    assert all(maps_onto_itself(S, box.vertices) for S in poses)
    cylinder = Symmetries(discrete=[np.diag([1.0, -1, -1, 1])],
                          continuous=[(np.array([0.0, 0, 1]), np.array([0.01, 0.0, 0.0]))])
    assert len(symmetric_poses(cylinder)) == 2 * math.ceil(math.pi / 0.01)  # 315 turns, with and without the flip
    poses = symmetric_poses(cylinder, continuous_steps=8)
    assert len(poses) == 16 and np.allclose(poses[0], np.eye(4))
    on_axis = np.array([[0.01, 0.0, 0.05], [0.01, 0.0, -0.02]])
    for S in poses[:8]:  # turns about the axis through the offset keep its points
        assert np.allclose(transform_points(S, on_axis), on_axis)
    assert np.allclose(poses[3][:3, :3], trimesh.transformations.rotation_matrix(3 * math.pi / 4, [0, 0, 1])[:3, :3])
    with pytest.raises(ConfigError):
        symmetric_poses(cylinder, continuous_steps=0)


@pytest.mark.parametrize("kind", ["box", "cylinder"])
def test_canonical_pose_does_not_depend_on_the_equivalent_pose_given(kind):
    if kind == "box":
        sym = detect(trimesh.creation.box(extents=[0.06, 0.1, 0.16]))
        poses = symmetric_poses(sym)
    else:
        sym = detect(trimesh.creation.cylinder(radius=0.04, height=0.12, sections=64))
        poses = symmetric_poses(sym, continuous_steps=36)
    for seed in range(3):
        T = random_pose(seed)
        canonical, S = canonical_pose(T, poses)
        assert np.allclose(canonical, T @ S)
        traces = [np.trace(T[:3, :3] @ P[:3, :3]) for P in poses]
        assert np.trace(canonical[:3, :3]) == pytest.approx(max(traces))  # axes closest to the camera's
        for P in poses:
            again, _ = canonical_pose(T @ P, poses)
            assert np.allclose(again, canonical, atol=1e-9)
        R, _ = canonical_pose(T[:3, :3], poses)
        assert np.allclose(R, canonical[:3, :3])


def test_mssd_and_mspd_against_their_definitions():
    box = trimesh.creation.box(extents=[0.06, 0.1, 0.16])
    points = trimesh.sample.sample_surface(box, 500, seed=1)[0]
    poses = symmetric_poses(detect(box))
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    T_gt = random_pose(4)
    for S in poses:  # an estimate off by a symmetry is no error
        assert mssd(T_gt @ S, T_gt, points, poses) == pytest.approx(0.0, abs=1e-12)
        assert mspd(T_gt @ S, T_gt, points, K, poses) == pytest.approx(0.0, abs=1e-9)
    flipped = T_gt @ poses[1]
    far = transform_points(flipped, points) - transform_points(T_gt, points)
    assert mssd(flipped, T_gt, points) == pytest.approx(np.linalg.norm(far, axis=1).max())  # no symmetries: max
    uv = lambda T: (transform_points(T, points) @ K.T)[:, :2] / (transform_points(T, points) @ K.T)[:, 2:]  # noqa: E731
    assert mspd(flipped, T_gt, points, K) == pytest.approx(np.linalg.norm(uv(flipped) - uv(T_gt), axis=1).max())
    nudged = make_T(np.eye(3), [0.003, 0, 0]) @ flipped
    assert mssd(nudged, T_gt, points, poses) == pytest.approx(0.003)
    assert mspd(nudged, T_gt, points, K, poses) > 0
    assert np.allclose(mssd_thresholds(0.2), np.arange(1, 11) * 0.01)
    assert np.allclose(mspd_thresholds(1280), np.arange(1, 11) * 10.0)
    errors = np.array([0.004, 0.012, 0.5, np.inf])  # metres, diameter 0.1 -> thresholds 5 .. 50 mm
    assert bop_recall(errors, mssd_thresholds(0.1)) == pytest.approx((10 + 8) / 40)


def test_a_40k_face_mesh_takes_at_most_a_few_seconds():
    big = mug(sections=2500, handle_sections=100)
    assert 39000 < len(big.faces) < 42000
    start = time.perf_counter()
    sym = detect(big)
    elapsed = time.perf_counter() - start
    assert sym.group_order == 1
    assert elapsed < 6.0, f"{elapsed:.1f} s"


@pytest.mark.parametrize("shape, order", [("cylinder", math.inf), ("box", 4)])
def test_reconstruction_like_meshes_keep_their_symmetries(shape, order):
    """Marching cubes of a noisy signed distance (2 mm voxels, 0.5 mm noise): ~40k small, noisy triangles."""
    from skimage.measure import marching_cubes

    h = 0.002
    g = np.arange(-0.07, 0.07 + h, h)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    if shape == "cylinder":
        sdf = np.maximum(np.hypot(X, Y) - 0.04, np.abs(Z) - 0.06)
    else:
        sdf = np.max([np.abs(X) - 0.03, np.abs(Y) - 0.05, np.abs(Z) - 0.065], axis=0)
    noisy = sdf + np.random.default_rng(0).normal(0, 0.0005, sdf.shape)
    vertices, faces, _, _ = marching_cubes(noisy, 0.0, spacing=(h, h, h))
    sym = find_symmetries(vertices + g[0], faces)
    assert sym.group_order == order
    if shape == "cylinder":
        assert np.allclose(sym.continuous[0][0], [0, 0, 1], atol=0.01)


def test_whole_models_info_file_is_refused():
    with pytest.raises(ContractError, match="one object's entry"):
        from_models_info({"1": {"diameter": 10.0}, "2": {"diameter": 12.0}})
