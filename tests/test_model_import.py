"""n2d model import: mesh files (a textured OBJ in mm, a vertex-coloured PLY in cm, a GLB in m) become model
directories whose renders match the source's (silhouettes to 1 px, colours within a tolerance) once
T_source_object is applied; bad files and absurd sizes are refused with a hint, and nothing is written then."""

import json

import numpy as np
import pytest
import trimesh
from helpers import look_at
from PIL import Image
from scipy.ndimage import binary_erosion, distance_transform_edt
from scipy.spatial import cKDTree

from n2d.cli import main
from n2d_common.contracts import open_stage
from n2d_common.errors import ConfigError, ContractError
from n2d_common.formats.model import read_textured_model
from n2d_common.frames import inv_T, transform_points
from n2d_common.raster import rasterize, render_textured
from n2d_dataset.models import load_models
from n2d_reconstruct.model_import import ImportConfig, detect_units, import_model
from n2d_reconstruct.texture import TextureConfig

SIZE = 160
K = np.array([[220.0, 0, (SIZE - 1) / 2], [0, 220.0, (SIZE - 1) / 2], [0, 0, 1]])
COLOURS = [(220, 30, 30), (30, 200, 40), (30, 40, 220), (230, 220, 30), (200, 30, 200), (30, 210, 210)]
"""The texture's six regions, one per face of the box."""


def _cfg(**kw) -> ImportConfig:
    return ImportConfig(texture=TextureConfig(size_px=256), **kw)


def _textured_box(folder, size_mm=(60.0, 40.0, 30.0), at_mm=(100.0, -20.0, 15.0)):
    """box.obj + box.mtl + tex.png: a box in millimetres off the origin, each face a colour region of the texture.
    Returns (V x 3 vertices in mm, F x 3 faces, F x 3 x 2 UVs, texture)."""
    box = trimesh.creation.box(size_mm)
    box.apply_translation(at_mm)
    vertices, uvs = [], []
    lo, span = box.vertices.min(0), np.ptp(box.vertices, 0)
    for f, normal in zip(box.faces, box.face_normals):
        axis = int(np.argmax(np.abs(normal)))
        region = 2 * axis + int(normal[axis] > 0)
        col, row = region % 3, region // 3
        others = [a for a in range(3) if a != axis]
        for v in box.vertices[f]:
            t = (v[others] - lo[others]) / span[others]
            vertices.append(v)
            uvs.append(((col + 0.1 + 0.8 * t[0]) / 3, (row + 0.1 + 0.8 * t[1]) / 2))
    texture = np.zeros((200, 300, 3), np.uint8)
    for region, colour in enumerate(COLOURS):
        col, row = region % 3, region // 3
        texture[200 - 100 * (row + 1):200 - 100 * row, 100 * col:100 * (col + 1)] = colour
    Image.fromarray(texture).save(folder / "tex.png")
    faces = np.arange(len(vertices)).reshape(-1, 3)
    lines = ["mtllib box.mtl", *(f"v {x} {y} {z}" for x, y, z in vertices), *(f"vt {u} {v}" for u, v in uvs),
             "usemtl painted", *(f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in faces + 1)]
    (folder / "box.obj").write_text("\n".join(lines) + "\n")
    (folder / "box.mtl").write_text("newmtl painted\nKd 0.8 0.8 0.8\nmap_Kd tex.png\n")
    return np.array(vertices), faces, np.array(uvs)[faces], texture


def _coloured_ball(folder):
    """ball.ply: a sphere of 5 cm radius in centimetres, Y up, coloured by position. Returns (vertices in cm,
    faces, V x 3 uint8 colours)."""
    ball = trimesh.creation.icosphere(3, radius=5.0)
    ball.vertices[:, 1] *= 1.4  # an ellipsoid, taller along Y
    ball.apply_translation([3.0, 8.0, -2.0])
    colours = np.clip((ball.vertices - ball.vertices.min(0)) / np.ptp(ball.vertices, 0) * 255, 0, 255).astype(np.uint8)
    ball.visual.vertex_colors = np.c_[colours, np.full(len(colours), 255, np.uint8)]
    ball.export(folder / "ball.ply")
    return np.asarray(ball.vertices), np.asarray(ball.faces), colours


def _views(centre_m, distance_m):
    """T_cam_source of cameras around `centre_m` (source frame, metres)."""
    eyes = [(1.0, 0.3, 0.5), (-0.4, 1.0, 0.2), (0.2, -0.6, 1.0), (-0.7, -0.5, -0.6)]
    return [inv_T(look_at(centre_m + distance_m * np.array(e) / np.linalg.norm(e), centre_m)) for e in eyes]


def _render_model(model_dir, T_cam_obj):
    vertices, faces, face_uvs, texture = read_textured_model(model_dir)
    return render_textured(vertices, faces, face_uvs, texture, K, T_cam_obj, SIZE, SIZE)


def _vertex_coloured(vertices_m, faces, colours, T_cam):
    r = rasterize(transform_points(T_cam, vertices_m), faces, K, SIZE, SIZE)
    rgb = np.zeros((SIZE, SIZE, 3))
    rgb[r.mask] = np.einsum("nk,nkc->nc", r.bary[r.mask], colours[faces[r.face[r.mask]]].astype(float))
    return np.rint(rgb).astype(np.uint8), r.mask


def _assert_same(source, imported, colour_tol=6.0):
    """Silhouettes agree to 1 px (every differing pixel within 1 px of the source's outline) and the mean colours
    over the object agree within `colour_tol` grey levels per channel."""
    (rgb_s, mask_s), (rgb_i, mask_i) = source, imported
    assert mask_s.sum() > 500
    outline = mask_s & ~binary_erosion(mask_s)
    differ = mask_s ^ mask_i
    if differ.any():
        assert distance_transform_edt(~outline)[differ].max() <= 1.0
    both = mask_s & mask_i
    mean_s, mean_i = rgb_s[both].mean(0), rgb_i[both].mean(0)
    assert np.abs(mean_s - mean_i).max() < colour_tol, (mean_s, mean_i)
    assert np.median(np.abs(rgb_s[both].astype(float) - rgb_i[both]).max(1)) < colour_tol


def _manifest_source(model_dir):
    source = open_stage(model_dir, "model")["extra"]["source"]
    return source, np.array(source["T_source_object"])


def test_textured_obj_in_mm_renders_as_its_source(tmp_path):
    V_mm, faces, face_uvs, texture = _textured_box(tmp_path)
    summary = import_model(tmp_path / "box.obj", tmp_path / "model", _cfg(object_name="box"))
    source, T_source_obj = _manifest_source(tmp_path / "model")
    assert (source["units"], source["scale_to_m"], source["appearance"]) == ("mm", 0.001, "texture")
    assert "millimetres" in source["units_reason"]
    assert summary["model"]["size_mm"] == [60.0, 40.0, 30.0]
    np.testing.assert_allclose(T_source_obj[:3, 3], [0.1, -0.02, 0.015], atol=1e-9)  # the box centre, metres
    info = json.loads((tmp_path / "model" / "models_info.json").read_text())["1"]
    assert "symmetries_discrete" not in info  # six colours: no turn maps the box onto itself
    V_m = 0.001 * V_mm
    for T_cam_source in _views(V_m.mean(0), 0.35):
        _assert_same(render_textured(V_m, faces, face_uvs, texture, K, T_cam_source, SIZE, SIZE),
                     _render_model(tmp_path / "model", T_cam_source @ T_source_obj))
    # a point of the file is T_source_object @ p_object / scale_to_m
    obj_vertices = read_textured_model(tmp_path / "model")[0]
    file_points = transform_points(T_source_obj, obj_vertices) / source["scale_to_m"]
    assert cKDTree(V_mm).query(file_points)[0].max() < 1e-3  # the model's vertices are the file's


def test_vertex_coloured_ply_in_cm_renders_as_its_source(tmp_path):
    V_cm, faces, colours = _coloured_ball(tmp_path)
    import_model(tmp_path / "ball.ply", tmp_path / "model", _cfg(up="y"))
    source, T_source_obj = _manifest_source(tmp_path / "model")
    assert (source["units"], source["up"], source["appearance"]) == ("cm", "y", "vertex colours")
    info = json.loads((tmp_path / "model" / "models_info.json").read_text())["1"]
    assert info["size_z"] == pytest.approx(140.0, abs=0.5)  # the tall Y axis is the object's Z
    V_m = 0.01 * V_cm
    for T_cam_source in _views(V_m.mean(0), 0.5):
        _assert_same(_vertex_coloured(V_m, faces, colours, T_cam_source),
                     _render_model(tmp_path / "model", T_cam_source @ T_source_obj))


def test_a_dense_mesh_is_decimated_and_keeps_its_colours(tmp_path):
    V_cm, faces, colours = _coloured_ball(tmp_path)
    summary = import_model(tmp_path / "ball.ply", tmp_path / "model", _cfg(up="y", max_faces=400))
    source, T_source_obj = _manifest_source(tmp_path / "model")
    assert source["decimated"] and source["faces"] == len(faces) and summary["model"]["faces"] <= 420
    V_m = 0.01 * V_cm
    for T_cam_source in _views(V_m.mean(0), 0.5):
        (rgb_s, mask_s), (rgb_i, mask_i) = (_vertex_coloured(V_m, faces, colours, T_cam_source),
                                            _render_model(tmp_path / "model", T_cam_source @ T_source_obj))
        assert (mask_s ^ mask_i).sum() < 0.03 * mask_s.sum()  # the decimated outline is close to the source's
        both = mask_s & mask_i
        assert np.abs(rgb_s[both].mean(0) - rgb_i[both].mean(0)).max() < 4.0
        assert np.median(np.abs(rgb_s[both].astype(float) - rgb_i[both]).max(1)) < 8.0


def test_glb_in_metres_is_read_y_up(tmp_path):
    """A model's own mesh.glb (glTF: Y up, metres) imports to the same object frame as its mesh.obj."""
    _textured_box(tmp_path)
    import_model(tmp_path / "box.obj", tmp_path / "a", _cfg(symmetry="none"))
    import_model(tmp_path / "a" / "mesh.glb", tmp_path / "b", _cfg(symmetry="none"))
    source, T_source_obj = _manifest_source(tmp_path / "b")
    assert (source["units"], source["up"], source["format"]) == ("m", "y", "glb")
    for T_cam_obj in _views(np.zeros(3), 0.35):
        _assert_same(_render_model(tmp_path / "a", T_cam_obj), _render_model(tmp_path / "b", T_cam_obj))


@pytest.mark.parametrize(("diameter", "unit"), [(0.08, "m"), (1.5, "m"), (8.0, "cm"), (20.0, "cm"), (25.0, "mm"),
                                                (1500.0, "mm")])
def test_units_from_the_size(diameter, unit):
    found, scale, why = detect_units(diameter, "auto", ImportConfig())
    assert found == unit and 0.01 <= diameter * scale <= 1.5
    assert "within" in why


def test_given_units_override_and_absurd_sizes_are_refused(tmp_path):
    assert detect_units(80.0, "cm", ImportConfig())[:2] == ("cm", 0.01)
    assert detect_units(4.0, "in", ImportConfig())[:2] == ("in", 0.0254)
    with pytest.raises(ConfigError, match="cannot tell the units") as err:
        detect_units(0.001, "auto", ImportConfig())
    assert "--units" in err.value.hint

    long = trimesh.creation.box((2000.0, 10.0, 10.0))  # 2 km in metres
    long.export(tmp_path / "long.stl")
    with pytest.raises(ConfigError, match="2 km across in metres") as err:
        import_model(tmp_path / "long.stl", tmp_path / "model", _cfg(units="m"))
    assert "--units" in err.value.hint
    with pytest.raises(ConfigError, match="cannot tell the units"):
        import_model(tmp_path / "long.stl", tmp_path / "model", _cfg())
    assert not (tmp_path / "model").exists() and not (tmp_path / "model.partial").exists()


def test_bad_files_are_refused_with_a_hint(tmp_path):
    (tmp_path / "empty.obj").write_bytes(b"")
    trimesh.PointCloud(np.random.default_rng(0).random((50, 3))).export(tmp_path / "cloud.ply")
    (tmp_path / "junk.glb").write_bytes(b"not a glb file at all")
    (tmp_path / "mesh.fbx").write_bytes(b"x")
    square = trimesh.Trimesh([[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0]], [[0, 1, 2], [0, 2, 3]])
    square.export(tmp_path / "flat.stl")
    cases = [("empty.obj", "is empty"), ("cloud.ply", "has no faces"), ("junk.glb", "not a readable GLB"),
             ("mesh.fbx", "not a mesh format"), ("missing.stl", "does not exist"), ("flat.stl", "is flat")]
    for name, message in cases:
        with pytest.raises(ConfigError, match=message) as err:
            import_model(tmp_path / name, tmp_path / "model", _cfg())
        assert err.value.hint
    _textured_box(tmp_path)
    (tmp_path / "tex.png").unlink()
    with pytest.raises(ConfigError, match="names the texture tex.png") as err:
        import_model(tmp_path / "box.obj", tmp_path / "model", _cfg())
    assert "copy the texture" in err.value.hint
    (tmp_path / "box.mtl").unlink()
    with pytest.raises(ConfigError, match="uses the material file box.mtl"):
        import_model(tmp_path / "box.obj", tmp_path / "model", _cfg())
    assert not (tmp_path / "model").exists() and not (tmp_path / "model.partial").exists()


def test_plain_stl_gets_the_given_colour_and_its_symmetries(tmp_path):
    trimesh.creation.cylinder(radius=30.0, height=80.0, sections=48).export(tmp_path / "can.stl")
    summary = import_model(tmp_path / "can.stl", tmp_path / "model", _cfg(colour_rgb=(200, 40, 40)))
    assert summary["source"]["appearance"] == "plain" and summary["source"]["units"] == "mm"
    albedo = np.asarray(Image.open(tmp_path / "model" / "albedo.png"))
    np.testing.assert_array_equal(np.unique(albedo.reshape(-1, 3), axis=0), [[200, 40, 40]])
    info = json.loads((tmp_path / "model" / "models_info.json").read_text())["1"]
    assert info["symmetries_continuous"] and info["diameter"] == pytest.approx(np.hypot(60.0, 80.0), rel=1e-3)
    with pytest.raises(ContractError, match="already exists"):
        import_model(tmp_path / "can.stl", tmp_path / "model", _cfg())
    import_model(tmp_path / "can.stl", tmp_path / "model", _cfg(), overwrite=True)


def test_cli_imports_a_model_the_dataset_stage_reads(tmp_path, capsys):
    _textured_box(tmp_path)
    out = tmp_path / "model"
    assert main(["model", "import", str(tmp_path / "box.obj"), str(out), "--set", "texture.size_px=256"]) == 0
    printed = capsys.readouterr().out
    assert "units mm" in printed and "millimetres" in printed and "texture" in printed
    for name in ("mesh.obj", "mesh.mtl", "albedo.png", "mesh.glb", "models_info.json", "n2d.json"):
        assert (out / name).is_file(), name
    (model,) = load_models([out])
    assert model.name == "box" and model.diameter_m == pytest.approx(0.0781, abs=1e-4)
    assert main(["model", "import", str(tmp_path / "box.obj"), str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["model", "import", str(tmp_path / "box.obj"), str(tmp_path / "m2"), "--units", "m"]) == 2
    err = capsys.readouterr().err
    assert "78.1 m across in metres" in err and "hint: " in err


def test_an_imported_model_renders_into_a_dataset(tmp_path):
    """The dataset stage takes an imported model as it takes a reconstruction (the fast renderer, two frames)."""
    from n2d_common.config import load_config
    from n2d_dataset.check import check_dataset
    from n2d_dataset.config import DatasetConfig
    from n2d_dataset.generate import generate_dataset

    _coloured_ball(tmp_path)
    import_model(tmp_path / "ball.ply", tmp_path / "ball", _cfg(up="y", object_name="ball"))
    cfg = load_config(DatasetConfig, overrides=["frames=2", "camera.width=160", "camera.height=120",
                                                "camera.focal_px=150", "render.engine=raster", "workers=1"])
    summary = generate_dataset([tmp_path / "ball"], tmp_path / "ds", cfg)
    assert summary["frames"] == 2 and summary["instances"] >= 1
    report = check_dataset(tmp_path / "ds")  # the labels agree with the renders, as for a reconstruction
    assert report["mask_boundary_offset_px"]["mean"] <= 0.5 and report["depth_error_mm"]["mean"] < 1.0, report
