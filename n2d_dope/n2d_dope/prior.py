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

    python -m n2d_dope.prior --work DIR [--objects mug,...] [--frames 500] [--minutes 45]

which renders the datasets into DIR, trains, and writes the two files into the package.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from n2d_common.contracts import atomic_write_json, read_manifest
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


def main(argv: list[str] | None = None) -> None:
    from n2d.pipeline import FAST_DATASET, FAST_TRAIN
    from n2d_common.config import from_dict, merge, to_dict
    from n2d_dataset.config import DatasetConfig
    from n2d_dataset.generate import generate_dataset
    from n2d_dope.config import TIMED_EPOCHS, TrainConfig
    from n2d_dope.train import train
    from n2d_sim.suite import suite_object_dir

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="directory for the datasets and the model")
    parser.add_argument("--objects", default=",".join(PRIOR_OBJECTS), help="suite objects, comma-separated")
    parser.add_argument("--frames", type=int, default=500, help="fast-path frames per object")
    parser.add_argument("--minutes", type=float, default=45.0, help="training time")
    args = parser.parse_args(argv)
    names = [n for n in args.objects.split(",") if n]
    for i, name in enumerate(names):
        cfg = from_dict(DatasetConfig, merge(to_dict(DatasetConfig()),
                                             {**FAST_DATASET, "frames": args.frames, "seed": 100 + i}))
        manifest = read_manifest(args.work / name) if (args.work / name).is_dir() else None
        if not (manifest and manifest.get("complete")):  # a dataset rendered before is kept
            generate_dataset([suite_object_dir(name)], args.work / name, cfg)
    tcfg = from_dict(TrainConfig, merge(to_dict(TrainConfig()), {**FAST_TRAIN, "init_model": "", "any_object": True,
                                                                 "epochs": TIMED_EPOCHS, "max_minutes": args.minutes,
                                                                 "int8": False}))
    summary = train([args.work / n for n in names], args.work / "prior_dope", tcfg)
    install_prior(args.work / "prior_dope", {"objects": names, "frames_per_object": args.frames,
                                             "minutes": args.minutes, "steps": summary["steps"],
                                             "held_out_loss": summary["held_out_loss"], "train": to_dict(tcfg)})
    print(f"prior: {summary['steps']} steps on {summary['train_frames']} frames of {len(names)} objects, "
          f"held-out loss {summary['held_out_loss']:.4f}; written to {PRIOR_DIR}")


if __name__ == "__main__":
    main()
