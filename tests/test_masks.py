"""Foreground masks on rendered turntable views, checked against the simulator's exact object mask.

The views are 480x360 (focal scaled, the whole plate in view), with independent sensor noise on
the view and on the empty-plate reference. Not smaller: the masks miss about a third of a pixel
along the outline, so IoU falls with the image size, and at 320x240 the bottle's mean (0.980) sits
right on the 0.98 bound. benchmarks/masks.py reports 640x480.
"""

import math

import numpy as np
import pytest

from n2d_capture.masks import (
    EXPECTED_IOU,
    MaskConfig,
    ViewGeometry,
    difference_seed,
    foreground_mask,
    foreground_mask_no_reference,
    iou,
    object_region,
    plate_region,
    predicted_board,
    shadowed_pattern,
    write_mask,
)
from n2d_common.config import ConfigError, from_dict, to_dict
from n2d_common.images import linear_to_srgb, read_png
from n2d_sim.camera import SimCamera
from n2d_sim.objects import SAMPLE_OBJECTS
from n2d_sim.world import SimWorldConfig

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

SIZE = dict(width=480, height=360, focal_px=450.0)
"""Three quarters of the default camera, same field of view."""
ANGLES = (0.5, 2.6, 4.7)
MISREGISTRATION_DEG = 0.3
"""Plate angle error of a reference the masks must tolerate (a Dynamixel repeats to ~0.1 degree)."""


class View:
    """One plate angle: noisy view and reference, the noise-free frames, the geometry."""

    def __init__(self, cam: SimCamera, angle: float, rng: np.random.Generator):
        self.frame = cam.render(angle)
        self.empty = cam.render(angle, object_visible=False)
        self.rgb = cam.noisy(self.frame.rgb, rng)
        self.reference = cam.noisy(self.empty.rgb, rng)
        self.off_reference: np.ndarray | None = None
        """The reference taken MISREGISTRATION_DEG past the view's plate angle (first view only)."""
        self.geometry = ViewGeometry.from_turntable(self.frame.K, self.frame.T_cam_turntable, angle,
                                                    cam.cfg.board)


@pytest.fixture(scope="module")
def views() -> dict[str, list[View]]:
    """Per sample object, the views at ANGLES; one camera per object, also checked for its cache."""
    rng = np.random.default_rng(0)
    out = {}
    for name in SAMPLE_OBJECTS:
        with SimCamera(SimWorldConfig(object=name, **SIZE)) as cam:
            out[name] = [View(cam, a, rng) for a in ANGLES]
            off = cam.render(ANGLES[0] + math.radians(MISREGISTRATION_DEG), object_visible=False)
            out[name][0].off_reference = cam.noisy(off.rgb, rng)
            again = cam.render(ANGLES[0] + 2 * math.pi, object_visible=False)
            assert again.render_s == 0.0 and again.rgb is out[name][0].empty.rgb
            assert cam.render(ANGLES[0]).rgb is out[name][0].frame.rgb  # cached apart from the empty plate
    return out


# ---------------------------------------------------------------------------------------------
# The empty plate from the simulator


def test_empty_plate_render_leaves_out_only_the_object(views):
    for view in views["box"]:
        frame, empty = view.frame, view.empty
        assert frame.object_visible and not empty.object_visible
        assert frame.mask.any() and not empty.mask.any()
        np.testing.assert_array_equal(empty.T_cam_obj, frame.T_cam_obj)  # where the object would stand
        assert empty.angle_rad == frame.angle_rad
        # The room is the same cached render; the plate and board are rendered anew and differ by the
        # renderer's noise, except under the object's shadow.
        shape = frame.mask.shape
        away = ~object_region(shape, view.geometry, MaskConfig(object_radius_m=0.08))
        plate = plate_region(shape, view.geometry)
        diff = np.abs(frame.rgb.astype(int) - empty.rgb.astype(int)).max(-1)
        assert diff[away & ~plate].max() <= 3
        assert np.median(diff[away & plate]) <= 2


# ---------------------------------------------------------------------------------------------
# Geometry


def test_geometry_regions_hold_the_object_and_the_board(views):
    for view in views["bottle"]:
        shape = view.rgb.shape[:2]
        region = object_region(shape, view.geometry, MaskConfig())
        assert region[view.frame.mask].all()
        assert not region.all()
        plate = plate_region(shape, view.geometry)
        assert (plate & ~region).sum() == 0  # the cylinder stands on the whole plate
        pattern, sheet = predicted_board(shape, view.geometry)
        gray = view.empty.rgb.mean(-1)
        assert sheet.sum() > 0.2 * plate.sum() and (sheet <= plate).all()
        assert np.corrcoef(pattern[sheet], gray[sheet])[0, 1] > 0.9


# ---------------------------------------------------------------------------------------------
# With a reference


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_mask_with_reference_matches_the_exact_mask(views, name):
    scores = [iou(foreground_mask(v.rgb, v.reference, v.geometry), v.frame.mask) for v in views[name]]
    assert np.mean(scores) >= EXPECTED_IOU["reference"], scores
    assert min(scores) >= EXPECTED_IOU["reference"] - 0.01, scores


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_a_slightly_misregistered_reference_is_tolerated(views, name):
    view = views[name][0]
    score = iou(foreground_mask(view.rgb, view.off_reference, view.geometry), view.frame.mask)
    assert score >= EXPECTED_IOU["reference"] - 0.01


def test_mask_without_geometry_is_nearly_as_good(views):
    view = views["box"][1]
    assert iou(foreground_mask(view.rgb, view.reference), view.frame.mask) >= EXPECTED_IOU["reference"] - 0.01


def test_shadows_do_not_seed_the_object_but_the_object_does(views):
    view = views["box"][0]
    seed = difference_seed(view.rgb, view.reference, view.geometry)
    away = ~object_region(seed.shape, view.geometry, MaskConfig(object_radius_m=0.07, max_object_height_m=0.16))
    assert seed[away].mean() < 0.001  # the board and plate around the box, shadow included
    assert seed[view.frame.mask].mean() > 0.8


def test_empty_plate_against_itself_gives_an_empty_mask(views):
    view = views["bottle"][0]
    other = SimCamera(SimWorldConfig(object="bottle", **SIZE)).noisy(view.empty.rgb, np.random.default_rng(7))
    for geometry in (view.geometry, None):
        mask = foreground_mask(other, view.reference, geometry)
        assert mask.dtype == bool and mask.shape == view.rgb.shape[:2] and not mask.any()
    assert not foreground_mask(view.reference, view.reference).any()


def test_masks_are_reproducible(views):
    view = views["bottle"][1]
    a = foreground_mask(view.rgb, view.reference, view.geometry)
    foreground_mask_no_reference(view.rgb, view.geometry)  # moves OpenCV's RNG in between
    np.testing.assert_array_equal(foreground_mask(view.rgb, view.reference, view.geometry), a)


# ---------------------------------------------------------------------------------------------
# Without a reference


@pytest.mark.parametrize("name", SAMPLE_OBJECTS)
def test_mask_without_reference_reaches_its_documented_bound(views, name):
    scores = [iou(foreground_mask_no_reference(v.rgb, v.geometry), v.frame.mask) for v in views[name]]
    assert np.mean(scores) >= EXPECTED_IOU["no_reference"], scores


def test_empty_plate_without_reference_gives_an_empty_mask(views):
    view = views["box"][2]
    assert not foreground_mask_no_reference(view.reference, view.geometry).any()


# ---------------------------------------------------------------------------------------------
# Inputs, config, output


def test_bad_inputs_are_refused():
    rgb = np.zeros((60, 80, 3), np.uint8)
    with pytest.raises(ValueError, match="same camera"):
        foreground_mask(rgb, np.zeros((60, 81, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        foreground_mask(rgb.astype(np.float32), rgb)
    with pytest.raises(ValueError, match="HxWx3"):
        foreground_mask(rgb, rgb[..., 0])


def test_a_shadow_keeps_the_reference_pattern_an_object_does_not():
    """The plate's pattern darkened by a shadow is told from an object, even a dark or patterned one."""
    rng = np.random.default_rng(0)
    pattern = np.kron(rng.choice([40.0, 230.0], (60, 320)), np.ones((2, 2)))  # printed everywhere, fine
    reference = np.repeat(pattern[..., None], 3, axis=2)  # 640 wide: the default 5x5 window
    view = reference.copy()
    view[:, :160] *= 0.6                                             # a shadow: same pattern, darker
    view[:, 240:400] = 35                                            # a dark plain object
    view[:, 480:] = np.roll(pattern, 4, axis=0)[:, 480:, None]       # a patterned object, not the plate's
    noisy = [np.clip(x + rng.normal(0, 2, x.shape), 0, 255).astype(np.uint8) for x in (reference, view)]
    shadowed = shadowed_pattern(noisy[1], noisy[0])
    assert shadowed[:, 4:156].mean() > 0.99
    assert not shadowed[:, 244:396].any()
    assert shadowed[:, 484:636].mean() < 0.005  # a chance match of 5x5 windows of two random patterns
    brighter = np.clip(noisy[0].astype(int) + 30, 0, 255).astype(np.uint8)
    assert not shadowed_pattern(brighter, noisy[0]).any()            # a shadow never brightens
    assert not shadowed_pattern(noisy[1], noisy[0], MaskConfig(shadow_pattern_ncc=0)).any()
    with pytest.raises(ValueError, match="same camera"):
        shadowed_pattern(noisy[1], noisy[0][:, :320])


@pytest.mark.parametrize("edge, tint", [(160.9, 0.2), (160.7, 0.4)])
def test_light_bounced_off_the_object_does_not_widen_the_mask(edge, tint):
    """A coloured object lights the plate beside it in its own colour (Cycles frames do, and real ones): the
    edge step takes the plate's tint from the view just outside, so the first plate pixel, 30-40 % covered by
    the object and tinted, stays plate (with one gain for all channels it is taken for the object)."""
    rng = np.random.default_rng(0)
    x = np.arange(320.0)
    cover = np.clip(edge + 0.5 - x, 0, 1)[:, None]                   # the object's share; x < edge is the object
    plate, yellow = np.array([0.75, 0.75, 0.72]), np.array([0.65, 0.50, 0.12])  # linear RGB
    tinted = plate * (1 - tint * np.exp(-np.maximum(x - edge, 0) / 6.0)[:, None] * (1 - yellow / plate.max()))

    def photo(row: np.ndarray) -> np.ndarray:
        image = np.repeat(255 * linear_to_srgb(row)[None], 240, axis=0) + rng.normal(0, 1.5, (240, 320, 3))
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)

    reference = photo(np.repeat(plate[None], 320, axis=0))
    view = photo(cover * yellow + (1 - cover) * tinted)
    view[:40], view[-40:] = reference[:40], reference[-40:]           # the object: rows 40-199
    mask = foreground_mask(view, reference)
    right = 319 - np.argmax(mask[60:-60, ::-1], axis=1)               # the last object pixel of each row
    assert np.mean(right == int(edge)) > 0.95


def test_config_checks_and_round_trips():
    cfg = MaskConfig(close_px=4.0, grabcut_iterations=2)
    assert from_dict(MaskConfig, to_dict(cfg)) == cfg
    for bad in ({"shadow_ratio_min": 1.2}, {"chroma_threshold": 0}, {"band_px": -1}, {"shadow_pattern_ncc": 1.5},
                {"board_hidden_ncc": 0.7}, {"min_component_fraction": 2}):
        with pytest.raises(ConfigError):
            from_dict(MaskConfig, {**to_dict(cfg), **bad})


def test_write_mask_stores_0_and_255(tmp_path):
    mask = np.zeros((40, 50), bool)
    mask[10:30, 5:20] = True
    write_mask(tmp_path / "m.png", mask)
    png = read_png(tmp_path / "m.png")
    assert png.dtype == np.uint8 and png.shape == mask.shape
    assert set(np.unique(png)) == {0, 255}
    np.testing.assert_array_equal(png == 255, mask)
