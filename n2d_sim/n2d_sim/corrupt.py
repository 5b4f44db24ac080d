"""Bad input on purpose: seeded corruptions of n2d's on-disk contracts, for the fuzz test and the fault campaign.

`copy_tree` makes a cheap copy of a stage directory (hard links); every corruption replaces the file it changes
(write to a new file, rename over), so the original behind the links stays intact. `corruptions(kind)` lists the
corruptions aimed at a kind of directory (a newer format, another kind, NaN in a pose, a mesh without faces, an
ONNX model of another shape, ...); `random_corruption` picks a file of the directory and breaks it in one of the
ways its type can break (truncated or garbage bytes, a JSON value of another type or a missing key, ...).
Each returns a one-line description of what it did.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

Corruption = Callable[[Path], str]
"""Breaks the directory it is given, in place; returns what it did."""

ODD_VALUES = (None, "x", "", -1, 0, 1e300, math.nan, math.inf, -math.inf, [], {}, True, [0.5, 0.5, 0.5], {"a": 1})
"""JSON values a reader may find where it expects another: other types, NaN/inf, empty containers."""


def copy_tree(src: Path, dst: Path) -> Path:
    """A copy of the directory `src` at `dst` whose files are hard links (corruptions replace files, never edit)."""
    shutil.copytree(src, dst, copy_function=os.link)
    return dst


def _replace(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.corrupt")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _write_json(path: Path, obj) -> None:
    _replace(path, json.dumps(obj).encode())  # NaN and Infinity as Python's json writes them


def edit_json(path: Path, edit: Callable[[object], object | None]) -> None:
    """Replace the JSON file `path` with `edit(its content)` (or the content `edit` changed in place)."""
    data = json.loads(path.read_text())
    out = edit(data)
    _write_json(path, data if out is None else out)


def _leaves(node, prefix=()) -> list[tuple]:
    """Every path (keys and indices) into a JSON value, the containers' own included."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _leaves(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node[:4]):  # a few elements of long lists are enough
            out += _leaves(v, prefix + (i,))
    return out


def _json(path: Path, rng: random.Random) -> str:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return _bytes(path, rng)
    paths = _leaves(data)
    if not paths or rng.random() < 0.1:
        value = rng.choice(ODD_VALUES)
        _write_json(path, value)
        return f"{path.name}: the whole file is {value!r}"
    where = rng.choice(paths)
    parent = data
    for key in where[:-1]:
        parent = parent[key]
    if rng.random() < 0.35:
        del parent[where[-1]]
        what = "deleted"
    else:
        value = rng.choice(ODD_VALUES)
        parent[where[-1]] = value
        what = f"= {value!r}"
    _write_json(path, data)
    return f"{path.name}: {'.'.join(map(str, where))} {what}"


def _bytes(path: Path, rng: random.Random) -> str:
    data = path.read_bytes()
    how = rng.choice(("truncated", "garbage", "empty", "header only"))
    if how == "truncated":
        data = data[:rng.randrange(1, max(2, len(data)))]
    elif how == "garbage":
        data = rng.randbytes(max(1, len(data)))
    elif how == "empty":
        data = b""
    else:
        data = data[:16]
    _replace(path, data)
    return f"{path.name}: {how}"


def _image(path: Path, rng: random.Random) -> str:
    if rng.random() < 0.7:
        return _bytes(path, rng)
    small = np.full((3, 4, rng.choice((1, 3, 4))), 128, np.uint8)
    ok, buf = cv2.imencode(path.suffix, small)
    _replace(path, buf.tobytes())
    return f"{path.name}: a valid {small.shape[1]}x{small.shape[0]} image of {small.shape[2]} channel(s)"


def mesh_without_faces(path: Path) -> None:
    """Keep only the vertex lines of an OBJ file."""
    lines = path.read_text().splitlines()
    _replace(path, "\n".join(ln for ln in lines if not ln.startswith("f ")).encode() + b"\n")


def mesh_scaled(path: Path, factor: float) -> None:
    """Scale the vertex positions of an OBJ file (1000: a mesh in millimetres)."""
    out = []
    for ln in path.read_text().splitlines():
        if ln.startswith("v "):
            ln = "v " + " ".join(f"{float(x) * factor:.6g}" for x in ln.split()[1:4])
        out.append(ln)
    _replace(path, "\n".join(out).encode() + b"\n")


def _obj(path: Path, rng: random.Random) -> str:
    how = rng.choice(("no faces", "millimetres", "nan vertex", "bytes"))
    if how == "no faces":
        mesh_without_faces(path)
    elif how == "millimetres":
        mesh_scaled(path, 1000.0)
    elif how == "nan vertex":
        text = path.read_text().replace("\nv ", "\nv nan ", 1)
        _replace(path, text.encode())
    else:
        return _bytes(path, rng)
    return f"{path.name}: {how}"


_BY_SUFFIX = {".json": _json, ".png": _image, ".jpg": _image, ".jpeg": _image, ".obj": _obj}


def random_corruption(directory: Path, rng: random.Random) -> str:
    """Break one file of `directory` (chosen by `rng`) in a way its type can break, or delete it."""
    files = sorted(p for p in directory.rglob("*") if p.is_file())
    path = rng.choice(files)
    where = path.relative_to(directory)
    if rng.random() < 0.1:
        path.unlink()
        return f"{where}: deleted"
    prefix = "" if where.parent == Path(".") else f"{where.parent}/"
    return f"{prefix}{_BY_SUFFIX.get(path.suffix, _bytes)(path, rng)}"


def _manifest(edit: Callable[[dict], None], name: str) -> Corruption:
    def corrupt(directory: Path) -> str:
        edit_json(directory / "n2d.json", edit)
        return f"n2d.json: {name}"
    return corrupt


def _file(relative: str, edit: Callable[[Path], None], name: str) -> Corruption:
    def corrupt(directory: Path) -> str:
        edit(directory / relative)
        return f"{relative}: {name}"
    return corrupt


def _json_edit(relative: str, edit: Callable[[object], object | None], name: str) -> Corruption:
    return _file(relative, lambda p: edit_json(p, edit), name)


def _first(pattern: str, edit: Callable[[Path], None], name: str) -> Corruption:
    def corrupt(directory: Path) -> str:
        path = sorted(directory.glob(pattern))[0]
        edit(path)
        return f"{path.relative_to(directory)}: {name}"
    return corrupt


def _set(keys: tuple, value) -> Callable[[object], None]:
    def edit(data) -> None:
        for k in keys[:-1]:
            data = data[k]
        data[keys[-1]] = value
    return edit


def _drop(keys: tuple) -> Callable[[object], None]:
    def edit(data) -> None:
        for k in keys[:-1]:
            data = data[k]
        del data[keys[-1]]
    return edit


def _truncate(path: Path) -> None:
    _replace(path, path.read_bytes()[:max(1, path.stat().st_size // 2)])


def _garbage(path: Path) -> None:
    _replace(path, random.Random(path.name).randbytes(max(64, path.stat().st_size)))


def other_onnx(path: Path) -> None:
    """Replace an ONNX file with a valid model of another shape: one grey channel in, one map out, same names."""
    import onnx
    from onnx import TensorProto, helper

    weight = helper.make_tensor("w", TensorProto.FLOAT, [2, 1, 1, 1], [1.0, -1.0])
    graph = helper.make_graph(
        [helper.make_node("Conv", ["image", "w"], ["belief"]), helper.make_node("Identity", ["belief"], ["affinity"])],
        "other", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, 32, 32])],
        [helper.make_tensor_value_info("belief", TensorProto.FLOAT, [1, 2, 32, 32]),
         helper.make_tensor_value_info("affinity", TensorProto.FLOAT, [1, 2, 32, 32])], [weight])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    _replace(path, model.SerializeToString())
    onnx.checker.check_model(onnx.load(str(path)))


_COMMON = [
    _manifest(_set(("kind",), "model"), "kind of another stage"),  # replaced below for model dirs
    _manifest(_set(("version",), 99), "format version 99 (a newer n2d)"),
    _manifest(_set(("version",), "one"), "version is a string"),
    _manifest(_set(("complete",), False), "not complete"),
    _manifest(_set(("kind",), 7), "kind is a number"),
    _manifest(_drop(("extra",)), "no extra"),
    _manifest(_drop(("config",)), "no config"),
    _manifest(lambda m: ["kind", m["kind"]], "a list, not a mapping"),
    _file("n2d.json", _truncate, "truncated"),
]


def _common(kind: str) -> list[Corruption]:
    other = "dataset" if kind == "model" else "model"
    return [_manifest(_set(("kind",), other), f"kind {other}")] + _COMMON[1:]


def _pose(value) -> Callable[[dict], None]:
    def edit(t: dict) -> None:
        t["frames"][0]["transform_matrix"][0][3] = value
    return edit


CORRUPTIONS: dict[str, list[Corruption]] = {
    "capture_session": [
        _json_edit("transforms.json", _pose(math.nan), "NaN in a pose"),
        _json_edit("transforms.json", _pose(math.inf), "inf in a pose"),
        _json_edit("transforms.json", lambda t: t["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]),
                   "a 2x2 pose"),
        _json_edit("transforms.json", _set(("fl_x",), math.nan), "NaN focal length"),
        _json_edit("transforms.json", _set(("cy",), math.inf), "inf principal point"),
        _json_edit("transforms.json", _set(("fl_y",), -300.0), "negative focal length"),
        _json_edit("transforms.json", _set(("w",), "wide"), "width is a string"),
        _json_edit("transforms.json", _drop(("fl_x",)), "no fl_x"),
        _json_edit("transforms.json", _drop(("frames",)), "no frames"),
        _json_edit("transforms.json", _set(("frames",), []), "frames empty"),
        _json_edit("transforms.json", lambda t: t["frames"][0].pop("file_path"), "a frame without file_path"),
        _json_edit("transforms.json", lambda t: t["frames"][0].update(file_path=7), "file_path is a number"),
        _file("transforms.json", _truncate, "truncated"),
        _first("images/*.png", _truncate, "truncated PNG"),
        _first("images/*.png", _garbage, "garbage PNG"),
        _first("masks/*.png", lambda p: p.unlink(), "deleted"),
        _first("images/*.png", lambda p: _replace(p, cv2.imencode(".png", np.zeros((5, 7, 3), np.uint8))[1]
                                                  .tobytes()), "an image of another size"),
    ] + _common("capture_session"),
    "model": [
        _file("mesh.obj", mesh_without_faces, "no faces"),
        _file("mesh.obj", lambda p: mesh_scaled(p, 1000.0), "millimetres"),
        _file("mesh.obj", _truncate, "truncated"),
        _file("mesh.obj", _garbage, "garbage"),
        _file("mesh.obj", lambda p: p.unlink(), "deleted"),
        _json_edit("models_info.json", lambda m: next(iter(m.values())).update(diameter=math.nan), "NaN diameter"),
        _json_edit("models_info.json", lambda m: next(iter(m.values())).update(size_x="big"), "size_x a string"),
        _json_edit("models_info.json", lambda m: next(iter(m.values())).pop("min_y"), "no min_y"),
        _json_edit("models_info.json", lambda m: {}, "empty"),
        _json_edit("models_info.json", lambda m: [m], "a list"),
        _file("albedo.png", _truncate, "truncated PNG"),
    ] + _common("model"),
    "dataset": [
        _first("train_pbr/*/scene_camera.json", lambda p: edit_json(
            p, lambda c: next(iter(c.values())).update(cam_K=[math.nan] * 9)), "NaN intrinsics"),
        _first("train_pbr/*/scene_gt.json", lambda p: edit_json(
            p, lambda g: next(iter(g.values()))[0].update(cam_t_m2c=[0, math.inf, 500])), "inf in a pose"),
        _first("train_pbr/*/rgb/*.jpg", _truncate, "truncated JPEG"),
        _first("train_pbr/*/rgb/*.jpg", _garbage, "garbage JPEG"),
        _first("train_pbr/*/rgb/*.json", lambda p: edit_json(p, _drop(("objects",))), "no objects"),
        _first("train_pbr/*/rgb/*.json", lambda p: edit_json(
            p, lambda a: a["objects"][0].update(projected_cuboid=[[math.nan, 1]] * 9)), "NaN keypoints"),
        _first("train_pbr/*/rgb/*.json", lambda p: edit_json(
            p, lambda a: a["objects"][0].update(projected_cuboid="corners")), "keypoints a string"),
        _first("train_pbr/*/depth/*.png", _garbage, "garbage depth PNG"),
        _manifest(_drop(("extra", "cuboids_m")), "no cuboids"),
        _manifest(_set(("config", "camera", "focal_px"), math.nan), "NaN focal length"),
        _manifest(_set(("extra", "cuboid_signs"), [[1, 1]]), "cuboid signs of another shape"),
    ] + _common("dataset"),
    "dope_model": [
        _file("model.onnx", other_onnx, "a valid ONNX model of another shape"),
        _file("model.onnx", _truncate, "truncated"),
        _file("model.onnx", _garbage, "garbage"),
        _json_edit("config.json", _drop(("models",)), "no models"),
        _json_edit("config.json", _set(("cuboid_points_m",), [[0, 0, math.nan]] * 9), "NaN cuboid"),
        _json_edit("config.json", _set(("cuboid_points_m",), [[0, 0]] * 3), "cuboid of another shape"),
        _json_edit("config.json", _set(("trained_focal_px",), "far"), "focal a string"),
        _json_edit("config.json", _set(("models",), {"fp32": "missing.onnx"}), "model file missing"),
        _file("config.json", _truncate, "truncated"),
    ] + _common("dope_model"),
}
"""Corruptions aimed at each kind of directory (the manifest's, and those of the files its readers read)."""
