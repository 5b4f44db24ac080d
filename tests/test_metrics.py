"""Image and geometry metrics of the reconstruction stage against their definitions and reference
implementations (skimage SSIM, NVIDIA FLIP) and against analytic distances between boxes."""

import math

import flip_evaluator
import numpy as np
import pytest
import trimesh
from skimage.metrics import structural_similarity

from n2d_common.geometry import sample_surface
from n2d_reconstruct.metrics import chamfer, flip, fscore, mesh_distances, psnr, ssim


@pytest.fixture(scope="module")
def images():
    """(reference, test, mask): a smooth uint8 image, a noisy copy, a blob mask off the border."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:96, 0:128]
    ref = np.stack([128 + 100 * np.sin(x / 9.0), 128 + 100 * np.cos(y / 7.0), (x + y) % 256], -1)
    ref = np.clip(ref, 0, 255).astype(np.uint8)
    test = np.clip(ref + rng.normal(0, 12, ref.shape), 0, 255).astype(np.uint8)
    mask = (x - 70) ** 2 + (y - 40) ** 2 < 25**2
    return ref, test, mask


def test_psnr():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.2, 0.8, (32, 48, 3))
    noise = rng.uniform(-0.05, 0.05, ref.shape)
    assert psnr(ref, ref) == math.inf
    assert psnr(ref, ref + noise) == pytest.approx(10 * math.log10(1 / np.mean(noise**2)), rel=1e-12)
    mask = np.zeros((32, 48), bool)
    mask[5:20, 10:30] = True
    assert psnr(ref, ref + noise * ~mask[..., None], mask) == math.inf
    assert psnr(ref, ref + noise, mask) == pytest.approx(10 * math.log10(1 / np.mean(noise[mask] ** 2)), rel=1e-12)
    ref8, test8 = (ref * 255).astype(np.uint8), ((ref + noise) * 255).astype(np.uint8)
    assert psnr(ref8, test8) == pytest.approx(psnr(ref8 / 255.0, test8 / 255.0), rel=1e-12)


def test_ssim(images):
    ref, test, mask = images
    assert ssim(ref, ref) == pytest.approx(1.0, abs=1e-12)
    assert ssim(ref, ref, mask) == pytest.approx(1.0, abs=1e-12)
    kwargs = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, channel_axis=-1, data_range=255)
    expected, full_map = structural_similarity(ref, test, full=True, **kwargs)
    assert ssim(ref, test) == pytest.approx(expected, abs=1e-9)
    assert ssim(ref, test, np.ones(mask.shape, bool)) == pytest.approx(expected, abs=1e-9)
    assert ssim(ref, test, mask) == pytest.approx(full_map[mask].mean(), abs=1e-9)  # the crop changes nothing
    assert 0.0 < ssim(ref, test, mask) < 0.99


def test_flip(images):
    ref, test, mask = images
    assert flip(ref, ref) == 0.0
    assert flip(ref, ref, mask) == 0.0
    error, _, _ = flip_evaluator.evaluate(ref / 255.0, test / 255.0, "LDR", applyMagma=False)
    assert flip(ref, test) == pytest.approx(error.mean(), rel=1e-6) and flip(ref, test) > 0.01
    assert flip(ref, test, mask) == pytest.approx(error[mask].mean(), rel=1e-6)


def test_sample_surface_is_uniform_on_the_surface():
    box = trimesh.creation.box(extents=(0.4, 0.2, 0.1))
    points = sample_surface(box.vertices, box.faces, 60_000, seed=3)
    np.testing.assert_array_equal(points, sample_surface(box.vertices, box.faces, 60_000, seed=3))
    on_face = np.isclose(np.abs(points), [0.2, 0.1, 0.05], atol=1e-12)
    assert on_face.any(1).all() and (np.abs(points) <= np.array([0.2, 0.1, 0.05]) + 1e-12).all()
    share = on_face.mean(0) / on_face.mean(0).sum()
    expected = np.array([0.2 * 0.1, 0.4 * 0.1, 0.4 * 0.2]) / (0.2 * 0.1 + 0.4 * 0.1 + 0.4 * 0.2)
    np.testing.assert_allclose(share, expected, atol=0.01)
    np.testing.assert_allclose(points.mean(0), 0, atol=0.003)


def test_chamfer_and_fscore_of_point_sets():
    a = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 0.0005], [0.0, 0.0, 0.004], [0.01, 0.0, 0.0]])
    assert chamfer(a, b) == pytest.approx({"a_to_b": 0.00025, "b_to_a": 0.0015, "chamfer": 0.000875})
    assert chamfer(a, a) == {"a_to_b": 0.0, "b_to_a": 0.0, "chamfer": 0.0}
    assert fscore(a, b, 0.001) == pytest.approx({"precision": 1.0, "recall": 2 / 3, "fscore": 0.8})
    assert fscore(a, b + 1.0, 0.001) == {"precision": 0.0, "recall": 0.0, "fscore": 0.0}


def test_mesh_distances_of_identical_meshes():
    """Exact point-to-surface distances: 0, also against the same surface as a soup of unwelded faces."""
    sphere = trimesh.creation.icosphere(3, 0.1)
    soup = sphere.vertices[sphere.faces].reshape(-1, 3)
    for vertices, faces in ((sphere.vertices, sphere.faces), (soup, np.arange(len(soup)).reshape(-1, 3))):
        d = mesh_distances(vertices, faces, sphere.vertices, sphere.faces, n=20_000, threshold=0.001)
        assert d["chamfer"] < 1e-12 and d["a_to_b"] < 1e-12 and d["b_to_a"] < 1e-12
        assert d["precision"] == d["recall"] == d["fscore"] == 1.0


def test_mesh_distances_of_a_box_and_the_box_scaled_by_one_percent():
    """A cube of half size s inside one of half size s + h: every inner point is h from the outer
    surface; outer points over the inner faces are h away, those past an edge or corner a bit more."""
    s, h = 0.1, 0.001
    inner = trimesh.creation.box(extents=(2 * s,) * 3)
    outer_vertices = inner.vertices * (1 + h / s)
    d = mesh_distances(inner.vertices, inner.faces, outer_vertices, inner.faces, n=50_000, threshold=1.2 * h)
    t = (np.arange(2000) + 0.5) / 2000  # midpoint rule on [0, 1]^2, in units of h
    corner = np.sqrt(1 + t[:, None] ** 2 + t[None, :] ** 2)
    strip_mean = (math.sqrt(2) + math.asinh(1)) / 2
    S = s + h
    strips, corners = 4 * 2 * s * h / (2 * S) ** 2, 4 * h * h / (2 * S) ** 2  # shares of the outer area
    outer_to_inner = h * (1 - strips - corners + strips * strip_mean + corners * corner.mean())
    assert d["a_to_b"] == pytest.approx(h, rel=1e-9)  # the rest within sampling error (1e-4 relative)
    assert d["b_to_a"] == pytest.approx(outer_to_inner, rel=1e-3)
    assert d["chamfer"] == pytest.approx((h + outer_to_inner) / 2, rel=1e-3)
    recall = 1 - strips * (1 - math.sqrt(1.2**2 - 1)) - corners * (corner >= 1.2).mean()
    assert d["precision"] == 1.0 and d["recall"] == pytest.approx(recall, abs=1.5e-3) and d["recall"] < 0.996
    thin = mesh_distances(inner.vertices, inner.faces, outer_vertices, inner.faces, n=1000, threshold=0.9 * h)
    assert thin["fscore"] == 0.0
