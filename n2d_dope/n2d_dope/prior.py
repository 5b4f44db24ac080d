"""The generic prior: a one-stage lite DOPE network trained on other objects, shipped as a warm start.

Training a detector of a new object from ImageNet's weights spends most of a short budget learning what every
object shares: where an object is, that its cuboid's corners sit around its silhouette, and how the affinity
fields point from each corner to the centroid. The prior has learnt that on objects of the suite that the
benchmarks do not score (mug, bracket, remote, spray, gear, book, duck: fast-path frames, every frame labelled with
its object's cuboid, `TrainConfig.any_object`), so a training that starts from it (`init_model: prior`) spends its
minutes on the new object's own corners.

The package keeps its weights (`prior/weights.pt`, float16) and what made them (`prior/prior.json`); the
network it fits is the one the pipeline's recipe trains (`FAST_TRAIN`: lite, one stage, six ImageNet blocks
fixed). Made by

    python -m n2d.make_prior --work DIR [--objects mug,...] [--frames 500] [--minutes 45]

which renders the datasets into DIR, trains, and writes the two files into the package.
"""

from __future__ import annotations

import json
from pathlib import Path

from n2d_common.contracts import atomic_write_json
from n2d_common.errors import ConfigError
from n2d_common.torch_utils import atomic_torch_save, load_checkpoint

PRIOR = "prior"
"""The `TrainConfig.init_model` value that names the shipped prior."""
PRIOR_DIR = Path(__file__).parent / "prior"
WEIGHTS, INFO = "weights.pt", "prior.json"
PRIOR_OBJECTS = ("mug", "bracket", "remote", "spray", "gear", "book", "duck")
"""Suite objects the prior learns from: none of those the estimator benchmark scores (box, bottle, cube_plain,
can), so its figures are those of objects the prior never saw."""


def prior_weights(backbone: str, stages: int) -> dict:
    """The prior's state dict (float32), checked to fit a `backbone` network of `stages` stages."""
    info_path, weights_path = PRIOR_DIR / INFO, PRIOR_DIR / WEIGHTS
    if not info_path.is_file() or not weights_path.is_file():
        raise ConfigError(f"the generic prior is missing from {PRIOR_DIR}",
                          "reinstall n2d_dope, or set init_model to '' (ImageNet) or a DOPE model directory")
    info = json.loads(info_path.read_text())
    if (info["backbone"], info["stages"]) != (backbone, stages):
        raise ConfigError(f"the generic prior is a {info['backbone']} network with {info['stages']} stage(s), the "
                          f"training a {backbone} one with {stages}",
                          f"set backbone: {info['backbone']} and stages: {info['stages']}, or init_model: ''")
    return {k: v.float() if v.is_floating_point() else v for k, v in load_checkpoint(weights_path).items()}


def install_prior(model_dir: Path, summary: dict) -> None:
    """Write a trained any-object DOPE model's weights (float16) and its provenance into the package."""
    config = json.loads((model_dir / "config.json").read_text())
    state = load_checkpoint(model_dir / "checkpoint.pt")["model"]
    PRIOR_DIR.mkdir(exist_ok=True)
    atomic_torch_save({k: v.half() if v.is_floating_point() else v for k, v in state.items()}, PRIOR_DIR / WEIGHTS)
    atomic_write_json(PRIOR_DIR / INFO, {"backbone": config["backbone"], "stages": config["stages"], **summary})
