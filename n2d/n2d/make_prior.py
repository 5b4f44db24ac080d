"""Make the generic DOPE prior that n2d_dope ships (`n2d_dope.prior`): render fast-path datasets of suite objects
the benchmarks do not score, train one any-object network on them, and write its weights into the package.

    python -m n2d.make_prior --work DIR [--objects mug,...] [--frames 500] [--minutes 45]

It lives in the bringup package because it composes three stages (the simulator's suite, the dataset, training).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from n2d_common.contracts import read_manifest
from n2d_dope.prior import PRIOR_DIR, PRIOR_OBJECTS, install_prior


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
