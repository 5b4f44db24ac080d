"""Bring your own mesh: an OBJ (+ MTL + texture), PLY (vertex colours), GLB / glTF or STL file to a model directory.

The result is the model directory `n2d reconstruct` writes (`write_model`: mesh.obj + mesh.mtl + albedo.png,
mesh.glb, models_info.json with the detected symmetries, n2d.json), so `n2d dataset` and `n2d train` take it as
they take a reconstruction.

- **Units**: the file's numbers are scaled to metres. `auto` reads them from the mesh's diameter d (in the file's
  numbers): objects a robot grasps are 1 cm to 1.5 m across, so 0.01 < d <= 1.5 is metres, 1.5 < d <= 20
  centimetres and 20 < d <= 1500 millimetres; anything else is refused with a hint to give the unit.
- **Frame**: the source's up axis (`up`; auto: +Y for glTF, as its spec says, +Z otherwise) is turned to +Z, and
  the object frame is put at the bounding-box centre (`export.object_frame`), as a reconstruction's is.
  `T_source_object` (4 x 4, metres) maps object-frame points into the source's frame: a point of the file is
  `T_source_object @ p_object / scale_to_m`.
- **Appearance**: whatever colour the source has is baked into the reconstruct stage's UV atlas (xatlas,
  `texture.unwrap`): a texture sampled at the source's UVs (glTF's base colour factor applied), vertex or face
  colours interpolated barycentrically, or one plain colour (`colour_rgb`, else the material's, else grey).
  A mesh of more than `max_faces` faces is decimated first, and each texel takes the colour of the nearest
  point of the source surface.
- **Writing**: everything is checked and computed before the output is opened; it is then written into
  `<out>.partial` and renamed into place (`contracts.stage_output`), refusing an existing output without
  `overwrite`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import fast_simplification
import numpy as np
import trimesh
from scipy.spatial import QhullError, cKDTree

from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, stage_output
from n2d_common.errors import ConfigError, ContractError
from n2d_common.formats.model import diameter
from n2d_common.frames import inv_T, make_T, transform_points
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_common.raster import sample_bilinear
from n2d_common.symmetry import AmbiguousSymmetry, Symmetries, find_symmetries, to_models_info
from n2d_reconstruct.export import object_frame, write_model
from n2d_reconstruct.texture import TextureConfig, TexturedMesh, bake_from_function, bake_from_surface, unwrap

FORMATS = {".obj": "obj", ".ply": "ply", ".stl": "stl", ".glb": "glb", ".gltf": "gltf", ".off": "off"}
"""File suffixes read, and the trimesh file type of each."""
SCALE_TO_M = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
"""Metres per unit of the file's numbers."""
AUTO_UNITS = (("m", 0.01, 1.5), ("cm", 1.5, 20.0), ("mm", 20.0, 1500.0))
"""(unit, lo, hi): `units: auto` reads a diameter lo < d <= hi in the file's numbers as that unit: 1 cm to 1.5 m
in metres, 1.5 to 20 cm in centimetres, 2 cm to 1.5 m in millimetres."""
UP_TO_Z = {"z": np.eye(3), "-z": np.diag([1.0, -1.0, -1.0]),
           "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
           "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]), "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])}
"""Rotation turning each source up axis to +Z (+Y: the inverse of the GLB writer's Z-up to Y-up turn)."""
NEUTRAL_RGB = (180, 180, 180)
"""Colour of a mesh with no texture, colours or material colour, and no `colour_rgb`."""
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")


@dataclass
class ImportConfig:
    """A mesh file to a model directory."""

    object_name: str = "object"
    """Name of the object (written into the model files and the manifest)."""
    units: Literal["auto", "m", "cm", "mm", "in"] = "auto"
    """Unit of the file's numbers; auto: read from the mesh's size (see the module doc)."""
    up: Literal["auto", "x", "y", "z", "-x", "-y", "-z"] = "auto"
    """The source's up axis, turned to the object frame's +Z; auto: y for glTF / GLB, z for the others."""
    colour_rgb: tuple[int, int, int] | None = None
    """sRGB 0..255 colour of a mesh without a texture or vertex colours (None: its material's, else grey)."""
    symmetry: Literal["auto", "none"] = "auto"
    """auto: detect the symmetries as n2d reconstruct does (an undecidable one stops the import before anything is
    written); none: the model is treated as asymmetric."""
    min_diameter_m: float = 0.002
    """Smaller models are refused, whatever the units, metres."""
    max_diameter_m: float = 2.0
    """Larger models are refused, whatever the units (the dataset stage takes nothing larger), metres."""
    max_faces: int = 50_000
    """Meshes with more faces are decimated to this many (quadric, fast-simplification) and their colours
    carried over from the nearest point of the source surface: xatlas takes about a minute per 40k faces on a
    CPU, and a reconstruction has 40k (0: never decimate)."""
    texture: TextureConfig = field(default_factory=TextureConfig)
    """UV atlas and albedo size."""

    def __post_init__(self):
        if not _NAME.match(self.object_name or ""):
            raise ConfigError(f"object name {self.object_name!r} is not usable",
                              "use letters, digits, '_' and '-' (up to 64), starting with a letter or digit")
        if self.colour_rgb is not None and not all(0 <= c <= 255 for c in self.colour_rgb):
            raise ConfigError(f"colour {tuple(self.colour_rgb)} is out of range", "give R,G,B in 0..255")
        if not 0 < self.min_diameter_m < self.max_diameter_m:
            raise ConfigError("need 0 < min_diameter_m < max_diameter_m")
        if self.max_faces != 0 and self.max_faces < 100:
            raise ConfigError(f"max_faces {self.max_faces} is too few", "use 0 (never decimate) or >= 100")


ColourFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""colour(faces, bary): N face indices and N x 3 barycentrics -> N x 3 sRGB in [0, 1]."""


@dataclass
class SourceMesh:
    """The geometry of a mesh file (its numbers, its frame) and the colour on its surface."""

    vertices: np.ndarray
    """V x 3 float64 in the file's units and frame, vertices at one position merged."""
    faces: np.ndarray
    """F x 3 int64."""
    colour: ColourFn
    """Colour at points of the faces."""
    appearance: str
    """texture, vertex colours, face colours, material colour or plain."""


def read_source(path: Path, colour_rgb: tuple[int, int, int] | None = None) -> SourceMesh:
    """Read a mesh file; ConfigError for a missing, empty, unreadable or faceless file."""
    path = Path(path)
    suffix = path.suffix.lower()
    hint = f"give a mesh file: {', '.join(FORMATS)}"
    if not path.is_file():
        raise ConfigError(f"{path} does not exist", hint)
    if suffix not in FORMATS:
        raise ConfigError(f"{path}: {suffix or 'no suffix'} is not a mesh format n2d reads", hint)
    if path.stat().st_size == 0:
        raise ConfigError(f"{path} is empty (0 bytes)", "export the mesh again; the file holds nothing")
    if suffix == ".obj":
        _check_obj_materials(path)
    try:
        scene = trimesh.load(path, file_type=FORMATS[suffix], force="scene", process=False)
    except Exception as exc:  # trimesh's loaders raise anything from ValueError to struct.error on bad input
        raise ConfigError(f"{path} is not a readable {suffix[1:].upper()} file ({type(exc).__name__}: {exc})",
                          "open it in a mesh viewer (e.g. Blender) and export it again") from None
    parts = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not parts:
        raise ConfigError(f"{path} has no faces (a point cloud or lines only?)",
                          "give a surface mesh with triangles or polygons")
    return _merge(parts, colour_rgb)


def _check_obj_materials(path: Path) -> None:
    """Refuse an OBJ whose MTL files or textures are missing: trimesh would load it grey without a word."""
    for line in re.findall(r"^mtllib[ \t]+(.+?)[ \t]*$", path.read_text(errors="replace"), re.M):
        names = [line] if (path.parent / line).is_file() else line.split()  # one name with spaces, or several
        for mtl in (path.parent / name for name in names):
            if not mtl.is_file():
                raise ConfigError(f"{path} uses the material file {mtl.name}, which is not in {path.parent}",
                                  "copy the .mtl file (and its textures) next to the .obj")
            _check_textures(mtl)


def _check_textures(mtl: Path) -> None:
    """Refuse an MTL file whose diffuse textures are missing."""
    for texture in re.findall(r"^[ \t]*map_Kd[ \t]+(?:.*[ \t])?(\S+)[ \t]*$", mtl.read_text(errors="replace"), re.M):
        if not (mtl.parent / texture).is_file():
            raise ConfigError(f"{mtl} names the texture {texture}, which is not in {mtl.parent}",
                              "copy the texture next to the .mtl file, or delete its map_Kd line for a plain model")


def _merge(parts: list[trimesh.Trimesh], colour_rgb) -> SourceMesh:
    """One mesh of the parts (vertices at the same position merged, faces in order, degenerate ones dropped) with
    the colour function of each part."""
    vertices = np.concatenate([np.asarray(p.vertices, np.float64) for p in parts])
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])[:-1]
    faces = np.concatenate([np.asarray(p.faces, np.int64) + o for p, o in zip(parts, offsets)])
    part_of = np.repeat(np.arange(len(parts)), [len(p.faces) for p in parts])
    local = np.concatenate([np.arange(len(p.faces)) for p in parts])
    if not np.isfinite(vertices).all():
        raise ConfigError("the mesh has vertices at NaN or infinity", "repair the mesh and export it again")
    unique, inverse = np.unique(vertices, axis=0, return_inverse=True)
    merged = inverse.reshape(-1)[faces]
    keep = (merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2]) & (merged[:, 0] != merged[:, 2])
    if not keep.any():
        raise ConfigError("every face of the mesh is degenerate", "give a surface mesh with triangles")
    colours = [_part_colour(p, colour_rgb) for p in parts]
    part_of, local = part_of[keep], local[keep]

    def colour(f: np.ndarray, bary: np.ndarray) -> np.ndarray:
        out = np.zeros((len(f), 3))
        for i, (fn, _) in enumerate(colours):
            sel = part_of[f] == i
            if sel.any():
                out[sel] = fn(local[f[sel]], bary[sel])
        return out

    kinds = sorted({kind for _, kind in colours})
    return SourceMesh(unique, merged[keep], colour, " + ".join(kinds))


def _part_colour(mesh: trimesh.Trimesh, colour_rgb) -> tuple[ColourFn, str]:
    """The colour function of one loaded mesh over its own faces, and what it comes from."""
    visual, faces = mesh.visual, np.asarray(mesh.faces, np.int64)
    if isinstance(visual, trimesh.visual.TextureVisuals):
        material = visual.material
        image = getattr(material, "baseColorTexture", None)
        image = getattr(material, "image", None) if image is None else image
        factor = _rgba(getattr(material, "baseColorFactor", None))
        if image is not None and visual.uv is not None and len(visual.uv) == len(mesh.vertices):
            texture = np.asarray(image.convert("RGB"))
            uv = np.asarray(visual.uv, np.float64)
            scale = np.ones(3) if factor is None else factor

            def textured(f, bary):
                p = np.einsum("nk,nkc->nc", bary, uv[faces[f]])
                p = np.where((p < 0) | (p > 1), p % 1.0, p)  # OBJ and glTF textures repeat
                return sample_bilinear(texture, p) / 255.0 * scale

            return textured, "texture"
        plain = factor if factor is not None else _rgba(getattr(material, "diffuse", None))
        if colour_rgb is None and plain is not None:
            return _constant(plain), "material colour"
    elif isinstance(visual, trimesh.visual.ColorVisuals) and visual.kind in ("vertex", "face"):
        if visual.kind == "vertex":
            vc = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255.0
            return (lambda f, bary: np.einsum("nk,nkc->nc", bary, vc[faces[f]])), "vertex colours"
        fc = np.asarray(visual.face_colors, np.float64)[:, :3] / 255.0
        return (lambda f, bary: fc[f]), "face colours"
    return _constant(np.asarray(colour_rgb or NEUTRAL_RGB, float) / 255.0), "plain"


def _rgba(value) -> np.ndarray | None:
    """RGB in [0, 1] of a trimesh material colour (uint8 or float RGBA), None when unset."""
    if value is None:
        return None
    c = np.asarray(value, np.float64).reshape(-1)[:3]
    return c / 255.0 if np.asarray(value).dtype.kind in "ui" or c.max() > 1.0 else c


def _constant(rgb: np.ndarray) -> ColourFn:
    return lambda f, bary: np.broadcast_to(rgb, (len(f), 3))


def detect_units(size: float, units: str, cfg: ImportConfig) -> tuple[str, float, str]:
    """(unit, metres per unit, why) of a mesh `size` (its diameter in the file's numbers) and the configured
    `units`; ConfigError when no unit makes it an object n2d models."""
    if units == "auto":
        for unit, lo, hi in AUTO_UNITS:
            if lo < size <= hi:
                metres = size * SCALE_TO_M[unit]
                return unit, SCALE_TO_M[unit], (f"its diameter, {size:.4g} in the file's numbers, is within "
                                                f"{lo:g}..{hi:g}: {_unit_name(unit)}, {_length(metres)} across")
        readings = ", ".join(f"{_length(size * SCALE_TO_M[u])} in {u}" for u, _, _ in AUTO_UNITS)
        raise ConfigError(f"cannot tell the units of the mesh: its diameter is {size:.4g} in the file's numbers "
                          f"({readings}), and objects n2d models are 1 cm to 1.5 m across",
                          "give the unit (--units m|cm|mm|in), or scale the mesh to one of them")
    metres = size * SCALE_TO_M[units]
    if not cfg.min_diameter_m <= metres <= cfg.max_diameter_m:
        raise ConfigError(f"the mesh is {_length(metres)} across in {_unit_name(units)} (diameter {size:.4g} in the "
                          f"file's numbers): n2d models objects of {_length(cfg.min_diameter_m)} to "
                          f"{_length(cfg.max_diameter_m)}", "check the unit (--units, or --units auto), or scale the "
                          "mesh")
    return units, SCALE_TO_M[units], f"given: {_unit_name(units)}, {_length(metres)} across"


def _unit_name(unit: str) -> str:
    return {"m": "metres", "cm": "centimetres", "mm": "millimetres", "in": "inches"}[unit]


def _length(metres: float) -> str:
    """A length in the unit that reads best: 2 km, 20 m, 35 cm, 4.2 mm."""
    for unit, scale in (("km", 1000.0), ("m", 1.0), ("cm", 0.01)):
        if metres >= scale:
            return f"{metres / scale:.3g} {unit}"
    return f"{metres / 0.001:.3g} mm"


def _diameter(vertices: np.ndarray) -> float:
    """The mesh's diameter in its own numbers; ConfigError for a flat mesh (no convex hull)."""
    try:
        return diameter(vertices)
    except (QhullError, ValueError):
        raise ConfigError("the mesh is flat (its vertices lie in a plane or on a line): not a solid object",
                          "give a closed surface mesh of the object") from None


def _decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """The mesh decimated to about `faces` faces (quadric error, as the reconstruction's clean-up)."""
    v, f = fast_simplification.simplify(mesh.vertices.astype(np.float32), mesh.faces.astype(np.int64),
                                        target_reduction=1.0 - faces / len(mesh.faces))
    return trimesh.Trimesh(v.astype(np.float64), f, process=True)


def _nearest_colour(vertices: np.ndarray, src: SourceMesh, points: np.ndarray, k: int = 8,
                    block: int = 1 << 15) -> np.ndarray:
    """N x 3 colours of the source surface (`vertices`: its vertices where `points` are) nearest each point: exact
    over the triangles of the k nearest face centroids, `block` points at a time (memory stays under 1 GB)."""
    triangles = vertices[src.faces]
    tree = cKDTree(triangles.mean(1))
    out = np.zeros((len(points), 3))
    for i in range(0, len(points), block):
        p = points[i:i + block]
        _, near = tree.query(p, k=k)
        closest = trimesh.triangles.closest_point(triangles[near.ravel()], np.repeat(p, k, 0)).reshape(-1, k, 3)
        best = np.linalg.norm(closest - p[:, None], axis=2).argmin(1)
        rows = np.arange(len(p))
        face = near[rows, best]
        bary = np.clip(trimesh.triangles.points_to_barycentric(triangles[face], closest[rows, best]), 0.0, 1.0)
        out[i:i + block] = src.colour(face, bary / np.maximum(bary.sum(1, keepdims=True), 1e-12))
    return out


def _symmetries(model: TexturedMesh, cfg: ImportConfig) -> Symmetries | None:
    """The model's symmetries as n2d reconstruct finds them (None with `symmetry: none`)."""
    if cfg.symmetry == "none":
        return None
    try:
        return find_symmetries(model.vertices, model.faces, face_uvs=model.face_uvs, texture=model.albedo)
    except AmbiguousSymmetry as exc:
        raise AmbiguousSymmetry(exc.message, "import with --symmetry none, then write the symmetries into "
                                "models_info.json by hand (BOP's symmetries_discrete / symmetries_continuous)",
                                exc.residual) from None


def import_model(mesh_path: str | Path, out: str | Path, cfg: ImportConfig, *, overwrite: bool = False,
                 progress: ProgressFn = no_progress) -> dict:
    """Import the mesh file `mesh_path` as the model directory `out`; returns the summary also in the manifest.

    Raises ConfigError for a file that is not a usable mesh (see `read_source`, `detect_units`) and for an
    undecidable symmetry, ContractError for an output that exists (without `overwrite`); nothing is written then.
    """
    mesh_path, out = Path(mesh_path), Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:  # before any work
        raise ContractError(f"{out} already exists", "choose another output path, or pass --overwrite")
    src = read_source(mesh_path, cfg.colour_rgb)
    unit, scale, why = detect_units(_diameter(src.vertices), cfg.units, cfg)
    progress(Progress(0.1, "load", message=f"{mesh_path.name}: {len(src.faces)} faces, {src.appearance}"))
    up = cfg.up if cfg.up != "auto" else ("y" if FORMATS[mesh_path.suffix.lower()] in ("glb", "gltf") else "z")
    T_upright_source = make_T(UP_TO_Z[up], np.zeros(3))  # metres, the source's axes turned Z up
    upright = trimesh.Trimesh(transform_points(T_upright_source, scale * src.vertices), src.faces, process=False)
    decimated = bool(cfg.max_faces) and len(src.faces) > cfg.max_faces
    if decimated:
        progress(Progress(0.15, "decimate", message=f"{len(src.faces)} to {cfg.max_faces} faces"))
        upright = _decimate(upright, cfg.max_faces)
    T_upright_object = object_frame(upright.vertices)
    T_source_object = inv_T(T_upright_source) @ T_upright_object
    mesh = trimesh.Trimesh(transform_points(inv_T(T_upright_object), upright.vertices), upright.faces, process=False)
    progress(Progress(0.2, "texture", message=f"baking the {src.appearance} (xatlas)"))
    model = unwrap(mesh, cfg.texture)  # the same faces in the same order: without decimation, source face f is f
    if decimated:  # the colour of the nearest source point, the source placed in the object frame
        at = transform_points(inv_T(T_source_object), scale * src.vertices)
        model.albedo = bake_from_function(model, lambda p, n: _nearest_colour(at, src, p), cfg.texture.size_px)
    else:
        model.albedo = bake_from_surface(model, src.colour, cfg.texture.size_px)
    progress(Progress(0.5, "symmetry"))
    symmetries = _symmetries(model, cfg)
    source = {"file": str(mesh_path.absolute()), "format": FORMATS[mesh_path.suffix.lower()], "units": unit,
              "units_reason": why, "scale_to_m": scale, "up": up, "appearance": src.appearance,
              "faces": len(src.faces), "decimated": decimated,
              "T_source_object": np.round(T_source_object, 12).tolist()}
    progress(Progress(0.8, "export"))
    with stage_output(out, "model", overwrite=overwrite, config=to_dict(cfg)) as writer:
        info = write_model(writer.path, model, cfg.object_name, to_models_info(symmetries) if symmetries else None)
        summary = {"source": source, "model": {
            "faces": len(model.faces), "vertices": len(model.vertices), "watertight": mesh.is_watertight,
            "diameter_mm": info["diameter"], "size_mm": [info["size_x"], info["size_y"], info["size_z"]]},
            "symmetry": {"mode": cfg.symmetry,
                         "group_order": None if symmetries is None or symmetries.continuous else symmetries.group_order,
                         "discrete": len(symmetries.discrete) if symmetries else 0,
                         "continuous": len(symmetries.continuous) if symmetries else 0}}
        atomic_write_json(writer.path / "report.json", summary)
        writer.finish(config=to_dict(cfg), inputs={"mesh": str(mesh_path.absolute())},
                      extra={"object": cfg.object_name, "method": "import", "source": source,
                             "frame": "object frame at the bounding-box centre of the mesh with the source's up axis "
                                      "turned to +Z; T_source_object maps it into the source's frame in metres, "
                                      "divide by scale_to_m for the file's units"})
    progress(Progress(1.0, "done"))
    return summary
