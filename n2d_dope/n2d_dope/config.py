"""Configs of the DOPE stage: training (with its augmentation) and detection."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass
class AugmentConfig:
    """Sim-to-real augmentation, applied on the fly to every training sample (numpy/OpenCV, no torchvision)."""

    scale: tuple[float, float] = (0.7, 1.4)
    """Random zoom range relative to fitting the image to the input size."""
    rotate_deg: float = 15.0
    """Random in-plane rotation, +- degrees."""
    shift: float = 0.15
    """Random translation, as a fraction of the input size."""
    background_swap: float = 0.4
    """Probability of replacing everything outside the annotated objects' masks by another frame or noise."""
    brightness: float = 0.3
    """Random brightness gain range (+-)."""
    contrast: float = 0.3
    """Random contrast range (+-)."""
    saturation: float = 0.3
    """Random saturation range (+-)."""
    hue_deg: float = 8.0
    """Random hue shift, +- degrees."""
    noise: float = 0.03
    """Maximum standard deviation of additive Gaussian noise (0..1 intensities)."""
    blur: float = 0.3
    """Probability of a Gaussian blur (sigma 0.5..1.5 px)."""

    def __post_init__(self):
        if not 0 < self.scale[0] <= self.scale[1]:
            raise ValueError(f"augment.scale must be 0 < min <= max, got {self.scale}")
        for name in ("background_swap", "blur"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"augment.{name} is a probability in 0..1, got {getattr(self, name)}")


TIMED_EPOCHS = 100_000
"""Epochs of a run meant to last a given time (`n2d train --minutes`, a pipeline's `train_minutes`) rather than a
number of passes: `max_minutes` ends it, and the learning rate anneals over those minutes."""


@dataclass
class TrainConfig:
    """Training of one DOPE network for one object."""

    backbone: Literal["lite", "vgg"] = "lite"
    """lite: EfficientNet-Lite0 trunk (ImageNet weights) + separable heads, real time on a CPU; vgg: DOPE as
    published (VGG-19 trunk from scratch, 50M parameters; needs a GPU)."""
    stages: int = 3
    """Belief/affinity stages (DOPE: 6)."""
    frozen_blocks: int = 3
    """lite: keep the stem and this many of its first ImageNet blocks fixed (their low-level features transfer
    to real images as they are, and training runs ~1.4x faster on a CPU); 0 trains the whole trunk."""
    input_size: tuple[int, int] = (240, 240)
    """Network input width, height in pixels during training (multiples of 16)."""
    crop: bool = True
    """Train on input_size windows cut from the frames at their own scale, each centred near one instance of the
    object (then zoomed, rotated and shifted by the augmentation), rather than on whole frames fitted to
    input_size. The network is fully convolutional, so it still runs on whole images; a 160 x 160 window costs a
    third of a 320 x 240 frame, and the object keeps the size in pixels it has at inference."""
    zoom: float = 1.5
    """Crop training: windows are cut from the frames enlarged by this factor, so the model works at zoom times the
    dataset's focal length (`trained_focal_px`; detection resizes camera images to match). Objects then cover
    zoom^2 more map cells, which places corners more precisely, and the network costs zoom^2 more per image
    (docs/experiments.md compares zoom 1 and 1.5)."""
    init_model: str = ""
    """A DOPE model directory (from n2d train) whose weights this training starts from instead of ImageNet's:
    fine-tune a model on more or newer data (same backbone and stages). `prior`: the generic prior shipped with
    n2d_dope (`n2d_dope.prior`: the one-stage lite network trained on other objects, which already finds an
    object's cuboid corners). Empty: start from ImageNet."""
    any_object: bool = False
    """Train one network on every object the datasets show, each frame labelled with all of its objects' cuboids
    (datasets of different objects may be mixed): a generic prior that other trainings start from
    (`init_model`), not a detector of one object."""
    epochs: int = 30
    """Passes over the training frames."""
    max_minutes: float = 0.0
    """Stop (and finish normally) after this much training time; 0 = no limit."""
    batch_size: int = 16
    """Images per step (DOPE: 64 on a GPU)."""
    lr: float = 1e-3
    """Adam learning rate (DOPE: 1e-4 for the VGG network)."""
    lr_final_fraction: float = 0.1
    """The learning rate decays (cosine) to this fraction of `lr` over the run."""
    peak_weight: float = 0.0
    """Belief cells weigh 1 + peak_weight * their target in the loss (0: DOPE's plain MSE): the peaks, a few cells
    among thousands, then drive the early steps (as CenterNet-style heatmap losses do)."""
    sigma_cells: float = 2.0
    """Standard deviation of the belief Gaussians, in output cells (8 input pixels)."""
    affinity_radius_cells: float = 2.5
    """Radius around each corner where the affinity field is set, in output cells."""
    photoreal_mix: float = -1.0
    """Fraction of the training samples drawn from photoreal (Cycles) frames, the rest from fast-path (raster)
    frames, whatever their counts; -1: every frame once per epoch, as they come."""
    symmetry_aware: bool = True
    """For an object with symmetries (the dataset's models_info.json), label each instance with the canonical one of
    its equivalent poses, so the corners a view cannot tell apart get one label, not several."""
    hidden_keypoints: bool = True
    """Also train keypoints hidden by other surfaces (DOPE does; PnP then has all 9 points under occlusion)."""
    min_visibility: float = 0.1
    """Instances with a smaller visible fraction get no targets."""
    holdout: float = 0.05
    """Fraction of the dataset's frames kept out of training (every k-th frame) to report a held-out loss."""
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    """Sim-to-real augmentation."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """auto: CUDA when present."""
    threads: int = 0
    """CPU threads for torch (0: all cores)."""
    seed: int = 0
    """Seed of the initialisation, the frame order and the augmentation."""
    checkpoint_every_s: float = 120.0
    """Save a checkpoint at most this often (and at every epoch end, on cancel and at the end)."""
    opset: int = 17
    """ONNX opset of the exported model."""
    int8: bool = True
    """Also write a statically quantised INT8 ONNX model (calibrated on training frames)."""
    calibration_frames: int = 32
    """Training frames used to calibrate the INT8 model."""

    def __post_init__(self):
        if self.stages < 1:
            raise ValueError(f"stages must be >= 1, got {self.stages}")
        if not 0 <= self.frozen_blocks <= 11:
            raise ValueError(f"frozen_blocks must be in 0..11 (the lite trunk's blocks), got {self.frozen_blocks}")
        if any(v <= 0 or v % 16 for v in self.input_size):
            raise ValueError(f"input_size must be positive multiples of 16, got {list(self.input_size)}")
        for name in ("epochs", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.zoom <= 0 or (self.zoom != 1.0 and not self.crop):
            raise ValueError(f"zoom must be positive, and 1 without crop training (set zoom=1 with crop=false), "
                             f"got {self.zoom}")
        if self.peak_weight < 0:
            raise ValueError(f"peak_weight must be >= 0, got {self.peak_weight}")
        if self.lr <= 0 or self.sigma_cells <= 0 or self.affinity_radius_cells <= 0:
            raise ValueError("lr, sigma_cells and affinity_radius_cells must be positive")
        if not (0.0 <= self.photoreal_mix <= 1.0 or self.photoreal_mix == -1.0):
            raise ValueError(f"photoreal_mix is a probability in 0..1, or -1 for the frames as they come; got "
                             f"{self.photoreal_mix}")
        if not 0.0 <= self.holdout < 0.5:
            raise ValueError(f"holdout must be in 0..0.5, got {self.holdout}")

    @classmethod
    def preset(cls, name: str) -> TrainConfig:
        """lite (CPU, ~an hour), vgg (DOPE as published: 6 stages, lr 1e-4, batch 64, 100 epochs, a GPU), tiny
        (tests)."""
        if name == "lite":
            return cls()
        if name == "vgg":
            return cls(backbone="vgg", stages=6, lr=1e-4, batch_size=64, epochs=100, input_size=(400, 400),
                       zoom=1.0, frozen_blocks=0)
        if name == "tiny":
            return cls(stages=1, epochs=2, batch_size=4, input_size=(160, 128), crop=False, zoom=1.0,
                       calibration_frames=4, checkpoint_every_s=1.0)
        raise ValueError(f"unknown preset {name!r}: use lite, vgg or tiny")


@dataclass
class DetectConfig:
    """Turning the network's maps into poses."""

    peak_threshold: float = 0.1
    """Minimum belief (after smoothing) for a keypoint peak."""
    smooth_sigma_cells: float = 0.5
    """Gaussian smoothing of the belief maps before peak finding, in output cells (0 = none)."""
    affinity_threshold: float = 0.5
    """Maximum angle (radians) between a corner's affinity vector and the direction to a centroid."""
    min_keypoints: int = 5
    """Detections with fewer keypoints (centroid included) are dropped; PnP needs at least 4."""
    ransac_px: float = 10.0
    """Keypoints further than this (network-input pixels) from the pose that EPnP-RANSAC fits to most of them are
    left out of PnP (0: always use all): a corner the network put on the wrong side of the object would pull the
    whole pose. Chosen on a validation set for networks working at 900 px (docs/experiments.md)."""
    min_inliers: int = 5
    """Detections whose pose lands fewer than this many of their keypoints within `ransac_px` are dropped (groups
    of stray peaks give such poses); it removes most false detections at no cost in ADD-S accuracy
    (docs/experiments.md)."""
    max_instances: int = 8
    """At most this many detections per object and image."""
    net_scale: float = 0.0
    """Resize factor from the camera image to the network input; 0 = automatic: match the focal length the
    model was trained at, so objects appear at the sizes they had in training."""
    scales: tuple[float, ...] = (1.0, 0.6, 0.4)
    """The network runs once per factor of this image pyramid, each a multiple of `net_scale`: an object nearer
    the camera than the training windows showed whole is found at the smaller ones. Detections of one instance
    at several scales are merged (`n2d_dope.infer.merge_detections`). Chosen on a validation set
    (docs/experiments.md); (1.0,) runs the network once."""

    def __post_init__(self):
        if self.min_keypoints < 4:
            raise ValueError(f"min_keypoints must be >= 4 (PnP), got {self.min_keypoints}")
        if not 0 <= self.min_inliers <= 9:
            raise ValueError(f"min_inliers must be in 0..9 (of the 9 keypoints), got {self.min_inliers}")
        if self.ransac_px < 0:
            raise ValueError(f"ransac_px must be >= 0, got {self.ransac_px}")
        if self.net_scale < 0:
            raise ValueError(f"net_scale must be >= 0, got {self.net_scale}")
        self.scales = tuple(float(s) for s in self.scales)
        if not self.scales or any(not 0 < s <= 4 for s in self.scales):
            raise ValueError(f"scales must be one or more factors in (0, 4], got {self.scales}")


@dataclass
class FlowConfig:
    """Texture points followed by optical flow from one tracked frame to the next (`n2d_dope.flow`)."""

    points: int = 80
    """Corners picked inside the silhouette per frame (0: no texture term, silhouette only)."""
    quality: float = 0.01
    """Shi-Tomasi quality level: corners weaker than this share of the strongest are not picked."""
    min_distance_px: int = 6
    """Least distance between picked corners."""
    edge_px: int = 3
    """Corners this close to the silhouette's edge are not picked (their neighbourhood is partly background)."""
    window_px: int = 15
    """Lucas-Kanade window."""
    levels: int = 2
    """Pyramid levels above the image (each halves it): motions up to about window x 2^levels px."""
    fb_px: float = 1.0
    """A point that flow does not bring back within this many pixels of where it started is dropped."""
    min_points: int = 8
    """Fewer points than this: no texture term in that frame."""
    sigma_px: float = 1.0
    """Standard deviation of a followed point's pixel, which weighs the term against the contour lines
    (robust: a point further off than 2 sigma counts less, Huber)."""

    def __post_init__(self):
        if self.points < 0 or self.min_points < 1 or self.window_px < 3 or self.levels < 0:
            raise ValueError("flow: points >= 0, min_points >= 1, window_px >= 3 and levels >= 0")
        if self.fb_px <= 0 or self.sigma_px <= 0 or not 0 < self.quality < 1:
            raise ValueError("flow: fb_px and sigma_px must be > 0 and quality in 0..1")


@dataclass
class RefineConfig:
    """Region-based refinement of a detected pose (`n2d_dope.pose_refine`)."""

    scales: tuple[int, ...] = (6, 4, 2, 1)
    """Pixels per line segment, coarse to fine: the first scale finds a contour up to `search_segments` x 6 px
    away."""
    iterations: int = 4
    """Gauss-Newton steps per scale."""
    search_segments: int = 5
    """Candidate contour positions each side of the projected contour, in segments."""
    window_segments: int = 4
    """Segments each side of a candidate position that score it."""
    bins: int = 16
    """Histogram bins per colour channel."""
    histogram_px: int = 24
    """Pixels each side of the contour whose colours make the foreground and background histograms."""
    histogram_gap_px: int = 1
    """Pixels next to the projected contour left out of the histograms (where a pose still off puts the wrong
    side's colours)."""
    min_variance: float = 0.25
    """Floor of a contour position's variance, in segments squared: no line is trusted beyond half a segment."""
    damping: float = 0.05
    """Damping of each step, as a share of each diagonal entry of the Gauss-Newton matrix (rotations and
    translations have their own units, so the damping is relative to each)."""
    min_lines: int = 20
    """Fewer contour lines than this inside the image: no refinement, score 0."""
    score_px: int = 4
    """Pixels each side of the contour that the score looks at."""
    texture_turns: bool = False
    """Also refine the half turns of the cuboid and keep the pose whose rendered albedo agrees best with the image
    (for detectors that confuse them; off: the networks n2d trains keep the turns apart, and the albedo of a lit
    photo picks the wrong turn in about a quarter of cases, docs/experiments.md)."""
    turn_score_margin: float = 0.05
    """Turns whose silhouette score is this far below the best are not compared by texture."""
    min_score: float = 0.6
    """Refined poses whose silhouette score is below this are rejected as not believable."""
    min_texture: float = 0.1
    """Refined poses whose texture agreement (`texture_agreement`: local normalised cross-correlation with the
    rendered albedo) is below this are rejected; not applied where the model is plain."""
    keep_start: bool = True
    """When a refined pose fails these checks, check the detector's own pose too and keep it when it passes:
    refinement can slide off a right pose (a highlight, an occluder's edge, a background of the object's colours),
    and a pose the texture confirms is worth more than none (docs/experiments.md)."""
    texture_rounds: int = 1
    """Rounds of render-and-compare after the silhouette refinement (`n2d_dope.pose_refine.align_texture`): the
    model's albedo rendered at the pose, its corners followed into the image by optical flow, the pose fitted to
    them (PnP) and refined again with them as a reprojection term beside the contour; a round is kept when the
    texture agrees better.
    It holds what the outline alone cannot (a box seen face on). One round, chosen on a validation sweep (a second
    gained nothing there, docs/experiments.md); 0: off."""

    def __post_init__(self):
        if not self.scales or any(int(s) < 1 for s in self.scales):
            raise ValueError(f"scales must be positive integers, got {self.scales}")
        if self.texture_rounds < 0:
            raise ValueError(f"texture_rounds must be >= 0, got {self.texture_rounds}")
        if self.iterations < 0 or self.search_segments < 1 or self.window_segments < 1:
            raise ValueError("iterations must be >= 0, search_segments and window_segments >= 1")
        if not 2 <= self.bins <= 64:
            raise ValueError(f"bins must be in 2..64, got {self.bins}")
        if not 0.0 <= self.min_score <= 1.0:
            raise ValueError(f"min_score must be in 0..1, got {self.min_score}")
        if not -1.0 <= self.min_texture <= 1.0:
            raise ValueError(f"min_texture must be in -1..1, got {self.min_texture}")
