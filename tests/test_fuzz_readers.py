"""Fuzz the readers of every on-disk contract: small valid directories (a capture session, a model, a dataset, a
DOPE model), a board spec and the stage configs, broken on purpose (seeded: `n2d_sim.corrupt`), then read the way
each stage reads them. Every reader either loads the input or refuses it with an N2DError that has a hint: no
other exception escapes, no reader writes into its input, and a stage given a refused input writes nothing."""

import json
import random
import traceback
from pathlib import Path

import numpy as np
import pytest
import yaml

from n2d_common.config import load_config, to_dict
from n2d_common.errors import N2DError
from n2d_common.formats.board import BoardSpec
from n2d_common.formats.model import read_textured_model
from n2d_sim import corrupt
from n2d_sim.objects import sample_object_dir

SEED = 45
RANDOM_TRIALS = 60
"""Random corruptions per directory kind, on top of the aimed ones (`corrupt.CORRUPTIONS`)."""
TINY_DATASET = ["frames=2", "camera.width=64", "camera.height=48", "camera.focal_px=60", "render.engine=raster",
                "workers=1", "scene.boards=0", "scene.distractors=[0,1]"]


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict[str, Path]:
    """One small valid directory of each kind."""
    from n2d_dataset.config import DatasetConfig
    from n2d_dataset.generate import generate_dataset
    from n2d_dope.config import TrainConfig
    from n2d_dope.train import train
    from n2d_sim.session import render_session, small_world

    root = tmp_path_factory.mktemp("valid")
    render_session(root / "session", small_world("box", 64, 48), views=2)
    generate_dataset([sample_object_dir("box")], root / "dataset", load_config(DatasetConfig, overrides=TINY_DATASET))
    cfg = TrainConfig.preset("tiny")
    cfg.epochs, cfg.int8 = 1, False
    train(root / "dataset", root / "dope", cfg)
    return {"capture_session": root / "session", "model": sample_object_dir("box"), "dataset": root / "dataset",
            "dope_model": root / "dope"}


def _read_session(d: Path) -> None:
    from n2d_reconstruct.data import load_session

    load_session(d, holdout_every=0, min_views=1)


def _read_model(d: Path) -> None:
    from n2d_dataset.models import load_models

    load_models([d])
    read_textured_model(d)


def _read_dataset(d: Path) -> None:
    from n2d_dope.config import TrainConfig
    from n2d_dope.data import DopeSamples, open_dataset

    info = open_dataset(d)
    cfg = TrainConfig.preset("tiny")
    cfg.augment.background_swap = 1.0  # read the masks too
    samples = DopeSamples(info.frames, "box", cfg, augment=True)
    for i in range(len(samples)):
        samples[i]


def _check_dataset(d: Path) -> None:
    from n2d_dataset.check import check_dataset

    check_dataset(d)


def _read_dope(d: Path) -> None:
    from n2d_dope.infer import DopeModel

    model = DopeModel(d)
    model.detect(np.full((48, 64, 3), 90, np.uint8), np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]))


READERS = {"capture_session": _read_session, "model": _read_model, "dataset": _read_dataset,
           "dope_model": _read_dope}
"""What the next stage reads of each kind of directory (its checks before it writes anything, and its data)."""
OTHER_READERS = {"dataset": [_check_dataset]}
"""Other readers of a kind: `n2d dataset check`."""


def _entry(kind: str, d: Path, out: Path) -> None:
    """The stage that reads `d`, writing `out`."""
    if kind == "capture_session":
        from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct

        reconstruct(d, out, ReconstructConfig())
    elif kind == "model":
        from n2d_dataset.config import DatasetConfig
        from n2d_dataset.generate import generate_dataset

        generate_dataset([d], out, load_config(DatasetConfig, overrides=TINY_DATASET))
    elif kind == "dataset":
        from n2d_dope.config import TrainConfig
        from n2d_dope.train import train

        train(d, out, TrainConfig.preset("tiny"))


LOADABLE = {
    "n2d.json: no extra", "n2d.json: no config",  # the readers default both to empty
    "mesh.obj: truncated",  # the half of an OBJ file that is left can be a smaller, valid mesh
    # files the next stage does not read (`n2d dataset check` does, and refuses or measures them)
    "train_pbr/000000/scene_camera.json: NaN intrinsics", "train_pbr/000000/scene_gt.json: inf in a pose",
    "train_pbr/000000/depth/000000.png: garbage depth PNG",
    "train_pbr/000000/rgb/000000.json: NaN keypoints",  # keypoints DOPE could not place: no target for them
}
"""The aimed corruptions a reader may accept; every other one must be refused."""


def _snapshot(d: Path) -> dict:
    return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in d.rglob("*")}


def _outcome(read, arg) -> str | None:
    """None when `read(arg)` loads or refuses cleanly, else what went wrong."""
    try:
        read(arg)
    except N2DError as exc:
        if not exc.hint:
            return f"N2DError without a hint: {exc.message}"
        if "this is a bug in n2d" in exc.hint:
            return f"a bug reported through the worker: {exc.message}"
        return None
    except Exception as exc:  # the point: nothing but N2DError may escape
        frame = traceback.extract_tb(exc.__traceback__)[-1]
        return f"{type(exc).__name__}: {exc} ({Path(frame.filename).name}:{frame.lineno})"
    return None


def _refused(read, arg) -> bool:
    try:
        read(arg)
    except N2DError:
        return True
    return False


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(READERS))
def test_corrupted_directories_are_read_or_refused_cleanly(valid, tmp_path, kind):
    rng = random.Random(f"{SEED}-{kind}")
    trials = [(c, None) for c in corrupt.CORRUPTIONS[kind]] + [(None, rng) for _ in range(RANDOM_TRIALS)]
    problems, loaded = [], []
    for i, (aimed, trial_rng) in enumerate(trials):
        d = corrupt.copy_tree(valid[kind], tmp_path / f"t{i}" / valid[kind].name)
        what = aimed(d) if aimed else corrupt.random_corruption(d, trial_rng)
        before = _snapshot(d)
        problem = next(filter(None, (_outcome(read, d) for read in [READERS[kind], *OTHER_READERS.get(kind, [])])),
                       None)
        if problem:
            problems.append(f"{what}: {problem}")
            continue
        if _snapshot(d) != before:
            problems.append(f"{what}: the reader wrote into its input")
        if not _refused(READERS[kind], d):
            loaded += [what] if aimed else []
        elif kind in ("capture_session", "model", "dataset"):
            out = tmp_path / f"t{i}" / "out"
            problem = _outcome(lambda d, out=out: _entry(kind, d, out), d)
            written = [p.name for p in (out, out.with_name("out.partial")) if p.exists()]
            if problem:
                problems.append(f"{what}: the stage: {problem}")
            elif written and not (out / "n2d.json").is_file():  # refused, yet it left something
                problems.append(f"{what}: the stage refused it and left {', '.join(written)}")
    assert not problems, f"{len(problems)} of {len(trials)} corruptions not handled:\n" + "\n".join(problems)
    assert set(loaded) <= LOADABLE, f"aimed corruptions that were not refused: {sorted(set(loaded) - LOADABLE)}"


def _mutated_mappings(data: dict, rng: random.Random, count: int) -> list[tuple[str, object]]:
    """`count` random single-value changes of a nested mapping (and a few whole-document ones)."""
    paths = corrupt._leaves(data)
    out = [("a list", [1, 2]), ("a number", 3), ("unknown key", {**data, "no_such_key": 1})]
    for _ in range(count):
        copy = json.loads(json.dumps(data))
        where = rng.choice(paths)
        parent = copy
        for key in where[:-1]:
            parent = parent[key]
        value = rng.choice(corrupt.ODD_VALUES)
        parent[where[-1]] = value
        out.append((f"{'.'.join(map(str, where))} = {value!r}", copy))
    return out


def _config_classes():
    from n2d.pipeline import PipelineConfig
    from n2d_capture.capture import CaptureConfig
    from n2d_dataset.config import DatasetConfig
    from n2d_dope.config import DetectConfig, TrainConfig
    from n2d_reconstruct.pipeline import ReconstructConfig

    return [CaptureConfig, ReconstructConfig, DatasetConfig, TrainConfig, DetectConfig, PipelineConfig]


def test_corrupted_configs_and_board_specs_are_refused_cleanly(tmp_path):
    rng = random.Random(SEED)
    problems, trials = [], 0
    cases = [(cls.__name__, lambda data, cls=cls: _load_config_text(cls, data, tmp_path), to_dict(cls()))
             for cls in _config_classes()]
    cases.append(("BoardSpec", BoardSpec.from_dict, BoardSpec().to_dict()))
    for name, read, data in cases:
        for what, mutated in _mutated_mappings(data, rng, 25):
            trials += 1
            problem = _outcome(read, mutated)
            if problem:
                problems.append(f"{name}: {what}: {problem}")
    for text in ("key: [unclosed", "\x00\x01\x02", "- just\n- a list\n", "a: b: c"):
        trials += 1
        path = tmp_path / "bad.yaml"
        path.write_text(text)
        problem = _outcome(lambda p: load_config(_config_classes()[2], p), path)
        if problem:
            problems.append(f"{text!r}: {problem}")
    assert not problems, f"{len(problems)} of {trials} corrupted configs not handled:\n" + "\n".join(problems)


def _load_config_text(cls, data, tmp_path: Path):
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data) if not isinstance(data, float) else str(data))
    return load_config(cls, path)


def test_a_refused_input_is_one_error_line_after_the_progress_bar(tmp_path):
    """The CLI ends a progress bar the failing job had drawn, so its error is a line of its own, then the hint."""
    import subprocess
    import sys

    from n2d_sim.session import render_session, small_world

    render_session(tmp_path / "session", small_world("box", 64, 48), views=2)
    corrupt.edit_json(tmp_path / "session" / "transforms.json", lambda t: t["frames"][0].update(file_path=7))
    result = subprocess.run([sys.executable, "-m", "n2d.cli", "reconstruct", str(tmp_path / "session"),
                             str(tmp_path / "model")], capture_output=True, text=True, timeout=300)
    lines = result.stderr.replace("\r", "\n").splitlines()
    errors = [ln for ln in lines if ln.startswith("n2d: error:")]
    assert result.returncode == 2 and len(errors) == 1 and "transforms.json is malformed" in errors[0], result.stderr
    assert lines[lines.index(errors[0]) + 1].startswith("  hint: ")
    assert not (tmp_path / "model").exists() and not (tmp_path / "model.partial").exists()
