"""The models a dataset shows: n2d model directories read into names, BOP object ids, meshes and cuboids.

No bpy here: the writers and the annotation checks use the same meshes the renderer loads.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from n2d_common.contracts import open_stage
from n2d_common.errors import ContractError
from n2d_common.formats.model import read_model_mesh

CUBOID_ORDER = ("front top right", "front top left", "front bottom left", "front bottom right",
                "rear top right", "rear top left", "rear bottom left", "rear bottom right", "centroid")
"""DOPE's keypoint order (NVlabs/Deep_Object_Pose `cuboid.py` after commit 22a2468): right = +x, top = +y,
front = +z of the object frame; the centroid last."""
CUBOID_SIGNS = np.array([[1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1],
                         [1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1], [0, 0, 0]], dtype=float)
"""Corner k of the cuboid is centre + CUBOID_SIGNS[k] * size / 2, in the order of CUBOID_ORDER."""


@dataclass(frozen=True)
class Model:
    """One n2d model directory, as the dataset sees it."""

    name: str
    """Class name in the annotations."""
    obj_id: int
    """BOP object id (1-based, in the order the models were given)."""
    directory: Path
    """The model directory (mesh.obj in metres, object frame)."""
    info: tuple
    """(min xyz, size xyz, diameter) from models_info.json, metres."""
    closed: bool = False
    """Whether the mesh covers the whole object, the side it stood on in the capture included: fused from two
    placements (`placements` in its manifest) or a simulator's whole mesh (`ground_truth`). An open model is cut at
    the plate, so no frame shows it from below (see `poses`)."""

    @property
    def min_m(self) -> np.ndarray:
        return np.array(self.info[0])

    @property
    def size_m(self) -> np.ndarray:
        return np.array(self.info[1])

    @property
    def diameter_m(self) -> float:
        return self.info[2]

    def cuboid(self) -> np.ndarray:
        """9 x 3 keypoints in the object frame (metres): the bounding box's corners and centre, DOPE order."""
        return self.min_m + self.size_m / 2 + CUBOID_SIGNS * self.size_m / 2

    @cached_property
    def mesh(self):
        """The model's trimesh (metres, object frame)."""
        return read_model_mesh(self.directory)


MAX_EXTENT_M = 2.0
"""A model larger than this (metres) is taken for a mesh written in millimetres."""


def _check_mesh(model: Model) -> None:
    """Refuse meshes the renderer would silently get wrong: no texture coordinates, or not in metres."""
    text = (model.directory / "mesh.obj").read_text(errors="replace")
    if "\nvt " not in text:
        raise ContractError(f"{model.directory / 'mesh.obj'} has no texture coordinates (vt): it would render "
                            "untextured", "export the model with its UV atlas (n2d reconstruct writes one)")
    mesh = model.mesh
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise ContractError(f"{model.directory / 'mesh.obj'} has no faces or non-finite vertices",
                            "re-run n2d reconstruct for this model, or check the mesh's export")
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    if extent > MAX_EXTENT_M:
        raise ContractError(f"{model.directory / 'mesh.obj'} is {extent:.1f} units across: it looks like millimetres, "
                            "n2d models are in metres", "scale the mesh by 0.001 (n2d reconstruct writes metres)")


def _finite(value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f"{value!r} is not a finite number")
    return float(value)


def load_models(directories: list[str | Path]) -> list[Model]:
    """Check and read the model directories; refuses duplicates and models that are not complete n2d models."""
    if not directories:
        raise ContractError("no models given", "pass at least one model directory (from n2d reconstruct)")
    models, names = [], set()
    for i, d in enumerate(directories):
        d = Path(d).absolute()
        manifest = open_stage(d, "model")
        name = str(manifest.get("config", {}).get("object_name") or manifest.get("config", {}).get("name") or d.name)
        if name in names:
            name = f"{name}_{i + 1}"
        names.add(name)
        try:
            info = next(iter(json.loads((d / "models_info.json").read_text()).values()))
            number = {k: _finite(info[k]) for k in ("diameter", *(f"{m}_{a}" for m in ("min", "size") for a in "xyz"))}
            lo = [number[f"min_{a}"] / 1000 for a in "xyz"]
            size = [number[f"size_{a}"] / 1000 for a in "xyz"]
            if min(size) < 0 or number["diameter"] <= 0:
                raise ValueError("sizes and diameter must be positive")
            entry = (tuple(lo), tuple(size), number["diameter"] / 1000)
        except (OSError, ValueError, KeyError, TypeError, AttributeError, StopIteration) as exc:
            raise ContractError(f"{d / 'models_info.json'} is missing or malformed ({type(exc).__name__}: {exc})",
                                "re-run n2d reconstruct for this model") from None
        if not (d / "mesh.obj").is_file():
            raise ContractError(f"{d} has no mesh.obj", "re-run n2d reconstruct for this model")
        extra = manifest.get("extra", {})
        model = Model(name, i + 1, d, entry, int(extra.get("placements", 1)) > 1 or bool(extra.get("ground_truth")))
        _check_mesh(model)
        models.append(model)
    return models
