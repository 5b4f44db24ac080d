"""The generic prior: one network trained on several objects' datasets (`any_object`), and trainings that start
from the prior the package ships (`init_model: prior`)."""

import json

import numpy as np
import pytest
import torch

from n2d_common.config import load_config
from n2d_common.errors import ConfigError
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dope.config import TrainConfig
from n2d_dope.data import ANY_OBJECT, DopeSamples, instances, open_datasets
from n2d_dope.network import DopeNet
from n2d_dope.prior import PRIOR, PRIOR_DIR, prior_weights
from n2d_dope.train import train
from n2d_sim.objects import sample_object_dir

SMALL = ["frames=3", "camera.width=160", "camera.height=128", "camera.focal_px=150", "render.engine=raster",
         "workers=1"]


@pytest.fixture(scope="module")
def two_objects(tmp_path_factory):
    """A raster dataset of the box and one of the bottle, rendered with the same camera."""
    root = tmp_path_factory.mktemp("prior")
    out = []
    for i, name in enumerate(("box", "bottle")):
        generate_dataset([sample_object_dir(name)], root / name,
                         load_config(DatasetConfig, overrides=SMALL + [f"seed={i}"]))
        out.append(root / name)
    return out


def test_any_object_labels_every_object(two_objects, tmp_path):
    """With any_object, datasets of different objects train together, each frame labelled with its own object's
    cuboid; the result is a prior (no cuboid, no object model), and naming an object with it is refused."""
    info = open_datasets(two_objects)
    cfg = load_config(TrainConfig, overrides=["any_object=true", "stages=1", "epochs=1", "batch_size=3",
                                               "input_size=[160,128]", "crop=false", "zoom=1.0", "int8=false"])
    samples = DopeSamples(info.frames, ANY_OBJECT, cfg, augment=False)
    for i, frame in enumerate(info.frames):
        shown = instances(json.loads(frame.annotation.read_text()), ANY_OBJECT, cfg.min_visibility)
        assert {o["class"] for o in shown} <= {"box", "bottle"}
        if shown:  # a labelled instance puts a belief peak in the centroid's map
            assert samples[i][1][8].max() > 0.5
    with pytest.raises(ConfigError, match="not box|any_object"):
        train(two_objects, tmp_path / "named", cfg, object_name="box")
    summary = train(two_objects, tmp_path / "prior_dope", cfg)
    assert summary["object"] == ANY_OBJECT and summary["train_frames"] >= 4
    config = json.loads((tmp_path / "prior_dope" / "config.json").read_text())
    assert config["cuboid_points_m"] is None and "object_model" not in config


def test_shipped_prior_fits_the_recipe_network(two_objects, tmp_path):
    """The package's prior loads into the pipeline recipe's network (lite, one stage) exactly; a training from it
    starts at the prior's weights (not ImageNet's); another network shape is refused with a hint."""
    state = prior_weights("lite", 1)
    net = DopeNet("lite", 1, imagenet_weights=False)
    net.load_state_dict(state)  # strict: every tensor present and shaped alike
    assert all(v.dtype == torch.float32 for v in state.values() if v.is_floating_point())
    info = json.loads((PRIOR_DIR / "prior.json").read_text())
    assert info["objects"] and "box" not in info["objects"]
    with pytest.raises(ConfigError, match="stage"):
        prior_weights("lite", 3)
    cfg = load_config(TrainConfig, overrides=[f"init_model={PRIOR}", "stages=1", "epochs=1", "batch_size=3",
                                               "input_size=[160,128]", "crop=false", "zoom=1.0", "int8=false",
                                               "lr=1e-12", "frozen_blocks=6"])
    train(two_objects[:1], tmp_path / "box_dope", cfg)
    from n2d_common.torch_utils import load_checkpoint

    trained = load_checkpoint(tmp_path / "box_dope" / "checkpoint.pt")["model"]
    head = [k for k in state if k.startswith("beliefs")][0]
    np.testing.assert_allclose(trained[head].numpy(), state[head].numpy(), atol=1e-6)  # a vanishing lr: still the prior
