"""Flattening planar regions: a rippled, dented box comes out flat with sharp edges and its true size; a rippled
cylinder's body, whose strips sag by more than the ripple, is left as it was."""

import numpy as np
import pytest
import trimesh

from n2d_reconstruct.planes import PlanesConfig, flatten_planes

PIXEL_M = 0.00087
"""A pixel at the object's distance in the 640x480 captures (0.52 m away)."""
BOX_M = np.array([0.09, 0.06, 0.14])


def _ripple(mesh: trimesh.Trimesh, amplitude_m: float, seed: int = 0) -> np.ndarray:
    """Vertices moved along their normals by a smooth random ripple of about `amplitude_m`."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices
    waves = sum(np.sin(v @ rng.normal(0, 120, 3) + rng.uniform(0, 2 * np.pi)) for _ in range(4)) / 2
    return v + (amplitude_m * waves)[:, None] * mesh.vertex_normals


def _off_plane(points: np.ndarray) -> float:
    """The largest distance of `points` from their least-squares plane, metres."""
    centred = points - points.mean(axis=0)
    return float(np.abs(centred @ np.linalg.svd(centred, full_matrices=False)[2][2]).max())


def _fine_box() -> trimesh.Trimesh:
    box = trimesh.creation.box(BOX_M)
    box = box.subdivide_to_size(0.003)
    return trimesh.Trimesh(box.vertices + [0, 0, BOX_M[2] / 2], box.faces)  # standing on the plate


def test_a_rippled_dented_box_comes_out_flat_with_its_true_size():
    box = _fine_box()
    v = _ripple(box, 0.0002)
    # a plain patch the refinement placed 1.5 mm inside the -y face (a fifth of it)
    face = v[:, 1] < -0.029
    v[face, 1] += 0.0015 * np.exp(-((v[face, 0] - 0.025) ** 2 + (v[face, 2] - 0.09) ** 2) / (2 * 0.012 ** 2))
    noisy = trimesh.Trimesh(v, box.faces, process=False)
    assert np.all(np.ptp(v, axis=0) - BOX_M > 0.0003)  # the crests make the box too large
    flat, stats = flatten_planes(noisy, PIXEL_M, PlanesConfig())
    assert stats["planes"] == 6 and stats["face_fraction"] > 0.9, stats
    assert np.abs(np.ptp(flat.vertices, axis=0) - BOX_M).max() < 0.0002, np.ptp(flat.vertices, axis=0)
    centred = np.abs(flat.vertices - [0, 0, BOX_M[2] / 2])
    for axis in range(3):
        for side in (-1, 1):
            on_face = np.isclose(side * (box.vertices[:, axis] - [0, 0, BOX_M[2] / 2][axis]), BOX_M[axis] / 2)
            # flat, edges and corners included, and where the truth is: the dent does not tilt the -y face (the
            # ripple, 0.4 mm at most, is half a wavelength across a face: its mean plane is off by a little)
            assert _off_plane(flat.vertices[on_face]) < 1e-6, (axis, side)
            assert np.abs(centred[on_face, axis] - BOX_M[axis] / 2).max() < 0.00025, (axis, side)
    assert len(flat.faces) == len(box.faces)


def test_a_rippled_cylinder_keeps_its_body_and_flattens_its_caps():
    cylinder = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=128).subdivide_to_size(0.003)
    cylinder.apply_translation([0, 0, 0.06])
    v = _ripple(cylinder, 0.0002, seed=1)
    flat, stats = flatten_planes(trimesh.Trimesh(v, cylinder.faces, process=False), PIXEL_M, PlanesConfig())
    caps = [n for n in stats["normals"] if abs(n[2]) > 0.99]
    assert stats["planes"] == len(caps) == 2, stats
    body = np.abs(cylinder.vertex_normals[:, 2]) < 0.1
    side = body & (v[:, 2] > 0.005) & (v[:, 2] < 0.115)
    assert np.linalg.norm(flat.vertices[side] - v[side], axis=1).max() < 1e-9  # no facets on the body
    top = cylinder.vertices[:, 2] > 0.1199
    assert _off_plane(flat.vertices[top]) < 1e-6 and np.abs(flat.vertices[top, 2] - 0.12).max() < 0.00025


def test_vertices_on_the_plate_cut_stay_and_flattening_can_be_turned_off():
    box = _fine_box()
    v = _ripple(box, 0.0002)
    noisy = trimesh.Trimesh(v, box.faces, process=False)
    fixed = box.vertices[:, 2] < 1e-9
    flat, stats = flatten_planes(noisy, PIXEL_M, PlanesConfig(), fixed)
    assert stats["planes"] == 5  # the bottom is the cut on the plate
    assert np.array_equal(flat.vertices[fixed], v[fixed])
    same, none = flatten_planes(noisy, PIXEL_M, PlanesConfig(enabled=False))
    assert same is noisy and none is None


@pytest.mark.parametrize("kw", [{"distance_px": 0}, {"max_scatter_px": -1}, {"min_width": 0},
                                {"max_angle_deg": 90}])
def test_bad_settings_are_refused(kw):
    with pytest.raises(ValueError, match="planes"):
        PlanesConfig(**kw)


def _turned_over(mesh: trimesh.Trimesh) -> int:
    """Faces of a box centred over the plate whose winding faces inwards (against the nearest box face)."""
    centres = mesh.triangles_center - [0, 0, BOX_M[2] / 2]
    axis = np.argmax(np.abs(centres) / BOX_M, axis=1)
    outward = np.zeros_like(centres)
    outward[np.arange(len(centres)), axis] = np.sign(centres[np.arange(len(centres)), axis])
    return int(np.sum(np.einsum("fx,fx->f", mesh.face_normals, outward) < -0.5))


def test_a_fin_and_a_fold_are_claimed_by_their_plane():
    box = _fine_box()
    v = _ripple(box, 0.0002)
    # a fin along the top (the refined roof's ridge): one row of vertices 2 mm up, its sides steeper than 25 deg
    ridge = (box.vertices[:, 2] > 0.1399) & (np.abs(box.vertices[:, 1]) < 0.001) & (np.abs(box.vertices[:, 0]) < 0.03)
    v[ridge, 2] += 0.002
    # a fold on the +x face: a vertex slid past its neighbours (its faces turn over) and 0.4 mm out
    side = np.nonzero(np.isclose(box.vertices[:, 0], BOX_M[0] / 2))[0]
    fold = side[np.argmin(np.linalg.norm(box.vertices[side] - [BOX_M[0] / 2, 0, 0.07], axis=1))]
    v[fold] += [0.0004, 0.004, 0.0]
    bad = trimesh.Trimesh(v, box.faces, process=False)
    assert ridge.sum() >= 10 and _turned_over(bad) > 0
    assert np.ptp(v, axis=0)[2] - BOX_M[2] > 0.0015

    flat, stats = flatten_planes(bad, PIXEL_M, PlanesConfig())
    assert stats["claimed_faces"] > 0 and stats["turned_faces"] == 0, stats
    assert _turned_over(flat) == 0
    assert np.abs(np.ptp(flat.vertices, axis=0) - BOX_M).max() < 0.0002, np.ptp(flat.vertices, axis=0)
    assert np.abs(flat.vertices[ridge, 2] - BOX_M[2]).max() < 0.00025
    assert abs(flat.vertices[fold, 0] - BOX_M[0] / 2) < 0.00025
