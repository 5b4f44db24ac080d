"""The Blender side of the simulated camera: builds the turntable scene once, then renders plate angles.

This is the only n2d_sim module that imports bpy, and it runs only as the worker process that
`n2d_sim.camera.SimCamera` starts, `python -m n2d_sim.render_worker FD` (bpy holds global state,
costs ~0.5 GB and is not thread-safe; a ROS node owns the caller's process). FD is one end of a
socket pair used as a `multiprocessing.connection.Connection`. Protocol: the caller sends the
SimWorldConfig as a dict; the worker answers ("ready", info) once the scene is built, then each
("render", (angle_rad, object_visible)) with ("frame", {rgb, mask, depth}); ("place", placement_deg)
lays the object on the plate another way (`SimWorldConfig.placement_deg`), answered ("placed", None);
("close", None) or a closed socket ends it; a failure is answered with ("error", traceback) and ends it too. With the
object hidden the frame is the empty plate (no object, no object shadows) and the mask is all False.

The scene: a lab table with a procedural wood top, a back wall with a poster, distractor boxes and
cylinders (seeded), a turntable (base + dark plate) with the ChArUco sheet lying on it and the object
standing on the board centre; a soft area key light, a fill light, a ceiling panel and a dim world.
Plate, board and object hang under one empty, so a new angle only turns that empty about Z.

One render gives RGB, depth and the object mask together: Cycles writes a multilayer EXR with the
Combined, Depth (planar, metres) and Object Index passes, one part each. The index pass is not
anti-aliased, so `index == 1` is the exact object mask. The linear RGB is turned into sRGB here
(view transform "Standard", as a camera's output), after the exposure correction.

Why it renders this way (measured on the 2-core Xeon CPU machine, 640x480, default scene, median
of 3 renders after a warm-up, other jobs running):
  - Only what moves is path-traced per frame. The surroundings are rendered once at start
    (`background_samples`), then made invisible to camera rays, though they still cast shadows
    and bounce light; each frame renders the turntable, board and object over a transparent film
    and lays them over the cached background by their alpha. Rendering everything per frame took
    4.4 s at 8 samples: table and wall cover most pixels. The price: where the object's shadow
    would reach past the plate onto the table it is missing (at the default light only the faint
    tip of the box's shadow would).
  - 4 samples + OpenImageDenoise (albedo+normal guided, prefilter and quality FAST): 1.0 s per new
    angle. Per-frame cost is ~0.19 s per sample plus ~0.2 s of denoising: 2 spp + OIDN 0.65 s,
    8 spp + OIDN 1.8 s, 16 spp + OIDN 3.2 s. Mean error against a 128-sample render: 2 spp 1.3 DN
    (jagged edges, crunchy text), 4 spp 1.0 DN, 8 spp 0.7 DN, 8 spp without denoiser 2.0 DN and
    visibly grainy. All are below the sensor noise added later (sigma 2.5-4.6 DN); 4 spp is the
    cheapest without visible aliasing. The guides keep the board's squares and the labels sharp.
  - Light bounces 1, 3 or 12 cost the same within noise here; 3 keeps the bounce light.
  - Threads = all cores in one process: 1 thread takes 3.5 s for what 2 threads do in 1.8 s; two
    render processes do not scale on 2 cores. Persistent data keeps the BVH, shaders and images
    between frames (2.0 s -> 1.8 s at 8 spp). EEVEE runs on Mesa's software GL here (~5 s/frame)
    and Workbench shades flat, so Cycles it is; a GPU (OptiX/CUDA/HIP/oneAPI/Metal) is used
    when present (`device: auto`).
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import time
import traceback
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path

import bpy
import cv2
import numpy as np
from mathutils import Matrix, Vector

from n2d_blender import materials, objects, renderer
from n2d_blender.camera import make_camera, set_pose
from n2d_common.config import from_dict
from n2d_common.formats.board import T_plate_board, board_image
from n2d_common.images import srgb_to_linear, to_srgb8
from n2d_sim.world import SimWorldConfig, T_plate_obj, T_turntable_cam, object_dir

OBJECT_INDEX = 1
BOARD_PX_PER_SQUARE = 128


# ---------------------------------------------------------------------------------------------
# Sim-specific materials and lights (the generic builders are n2d_blender's)


def _wood_material(name, base, dark, seed):
    """Procedural wood: bands along x distorted by noise into grain, with a slow colour variation."""
    mat, tree, bsdf = materials.principled(name, base, roughness=0.45, specular=0.4)
    nodes, links = tree.nodes, tree.links
    coord = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Location"].default_value = (seed * 1.7, seed * 0.3, 0.0)
    mapping.inputs["Scale"].default_value = (0.6, 4.0, 1.0)
    grain = nodes.new("ShaderNodeTexWave")
    grain.wave_type = "BANDS"
    grain.bands_direction = "Y"
    grain.inputs["Scale"].default_value = 3.0
    grain.inputs["Distortion"].default_value = 12.0
    grain.inputs["Detail"].default_value = 4.0
    grain.inputs["Detail Scale"].default_value = 1.5
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (*dark, 1.0)
    ramp.color_ramp.elements[1].color = (*base, 1.0)
    blotch = nodes.new("ShaderNodeTexNoise")
    blotch.inputs["Scale"].default_value = 3.0
    mix = nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.blend_type = "MULTIPLY"
    mix.inputs["Factor"].default_value = 0.35
    links.new(coord.outputs["Object"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], grain.inputs["Vector"])
    links.new(coord.outputs["Object"], blotch.inputs["Vector"])
    links.new(grain.outputs["Fac"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], mix.inputs["A"])
    links.new(blotch.outputs["Color"], mix.inputs["B"])
    links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    return mat


def _area_light(name, power_w, size_m, location, parent):
    """A square area light at `location` (in the parent's frame) shining at the plate centre."""
    light = bpy.data.lights.new(name, type="AREA")
    light.energy = power_w
    light.size = size_m
    obj = bpy.data.objects.new(name, light)
    bpy.context.scene.collection.objects.link(obj)
    obj.parent = parent
    obj.location = location
    obj.rotation_euler = (-Vector(location)).to_track_quat("-Z", "Y").to_euler()
    return obj


# ---------------------------------------------------------------------------------------------
# The scene


def _poster() -> np.ndarray:
    """A made-up lab poster: title, a bar chart and a few lines of text."""
    img = np.full((420, 300, 3), 245, np.uint8)
    img[:70] = (30, 80, 140)
    cv2.putText(img, "LAB SAFETY", (18, 48), cv2.FONT_HERSHEY_DUPLEX, 1.1, (255, 255, 255), 2, cv2.LINE_AA)
    for i, (h, c) in enumerate(zip((120, 80, 160, 60, 100), ((220, 80, 60), (240, 180, 40), (60, 160, 90),
                                                            (80, 120, 200), (150, 80, 160)))):
        cv2.rectangle(img, (30 + i * 50, 270 - h), (62 + i * 50, 270), c, -1)
    cv2.line(img, (20, 272), (280, 272), (40, 40, 40), 2)
    lines = ("1. Wear safety glasses", "2. Keep the bench tidy", "3. Label every sample",
             "4. Report incidents")
    for i, line in enumerate(lines):
        cv2.putText(img, line, (20, 310 + i * 26), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (40, 40, 40), 1,
                    cv2.LINE_AA)
    return img


class Scene:
    """The built Blender scene; `render(angle)` turns the plate and renders."""

    def __init__(self, cfg: SimWorldConfig, workdir: Path):
        self.cfg = cfg
        self.exr = workdir / "frame.exr"
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self.device = self._setup_render()
        self.rig = bpy.data.objects.new("turntable_rig", None)
        self.scene.collection.objects.link(self.rig)
        # The room (lights, table, wall, distractors) is laid out for a camera on its -Y side.
        self.room = bpy.data.objects.new("room", None)
        self.scene.collection.objects.link(self.room)
        self.room.rotation_euler[2] = math.radians(cfg.camera_azimuth_deg + 90.0)
        self._turntable()
        if cfg.board_visible:
            self._board()
        self.objects = self._object()
        self._camera()
        self._lights()
        self.static: list[bpy.types.Object] = self._clutter() if cfg.clutter else []
        self.background = self._render_background()

    def _setup_render(self) -> str:
        cfg, scene = self.cfg, self.scene
        device = renderer.setup(self.exr, cfg.samples, cfg.denoiser, cfg.max_bounces, cfg.device, cfg.threads)
        scene.render.resolution_x, scene.render.resolution_y = cfg.width, cfg.height
        scene.render.resolution_percentage = 100
        scene.render.film_transparent = False
        world = bpy.data.worlds.new("world")
        background = world.node_tree.nodes["Background"]
        background.inputs["Color"].default_value = (0.6, 0.62, 0.65, 1.0)
        background.inputs["Strength"].default_value = cfg.world_strength
        scene.world = world
        return device

    def _turntable(self):
        cfg = self.cfg
        r = cfg.board.plate_diameter_m / 2
        plate_mat, _, _ = materials.principled("plate", srgb_to_linear((0.12, 0.12, 0.13)), roughness=0.55,
                                    specular=0.4)
        plate = objects.cylinder("plate", r, -0.0063, -0.0003, parent=self.rig)
        materials.assign(plate, plate_mat)
        base_mat, _, _ = materials.principled("base", srgb_to_linear((0.2, 0.2, 0.22)), roughness=0.35,
                                              specular=0.5, metallic=0.6)
        base = objects.cylinder("base", 0.8 * r, -cfg.plate_height_m, -0.0063 - 0.001)
        materials.assign(base, base_mat)

    def _board(self):
        spec = self.cfg.board
        squares = board_image(spec, BOARD_PX_PER_SQUARE / spec.square_m)
        s = squares.shape[1] / spec.size_m[0]  # texture pixels per metre
        m = round(spec.margin_m * s)
        sheet = cv2.copyMakeBorder(squares, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
        # Paper is not a perfect black and white print.
        sheet = (np.float32(sheet) * (0.93 - 0.06) / 255 + 0.06) * 255
        w, h = sheet.shape[1] / s, sheet.shape[0] / s
        # Sheet corners in board coordinates (m), mapped onto the plate; UV v runs up the image.
        corners_b = np.array([[-m / s, h - m / s, 0], [w - m / s, h - m / s, 0],
                              [w - m / s, -m / s, 0], [-m / s, -m / s, 0]])
        T = T_plate_board(spec)
        verts = corners_b @ T[:3, :3].T + T[:3, 3]
        uvs = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]
        board = objects.mesh_object("board", verts, [(0, 1, 2, 3)], uvs=uvs, parent=self.rig)
        materials.assign(board, materials.textured("board", materials.image("board", np.uint8(np.round(sheet))),
                                          roughness=0.55, specular=0.35))

    def _object(self):
        directory = object_dir(self.cfg)
        before = set(bpy.data.objects)
        bpy.ops.wm.obj_import(filepath=str(directory / "mesh.obj"), forward_axis="Y", up_axis="Z")
        parts = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
        if not parts:
            raise RuntimeError(f"{directory / 'mesh.obj'} holds no mesh")
        self.imported = {obj.name: obj.matrix_basis.copy() for obj in parts}  # as the model frame stands
        for obj in parts:
            obj.parent = self.rig
            obj.pass_index = OBJECT_INDEX
        self.objects = parts
        self.place(self.cfg.placement_deg)
        return parts

    def place(self, placement_deg) -> None:
        """Lay the object on the plate as `placement_deg` says: turned, then lowered onto the board."""
        self.cfg = replace(self.cfg, placement_deg=tuple(placement_deg))
        placed = Matrix(T_plate_obj(self.cfg).tolist())
        for obj in self.objects:
            obj.matrix_basis = placed @ self.imported[obj.name]

    def _camera(self):
        cam = make_camera(self.cfg.width, self.cfg.height, self.cfg.focal_px)
        set_pose(cam, T_turntable_cam(self.cfg))

    def _lights(self):
        cfg = self.cfg
        _area_light("key", cfg.key_light_w, 0.5, (-0.9, -0.45, 1.0), self.room)
        _area_light("fill", cfg.fill_light_w, 0.8, (0.7, -0.5, 0.4), self.room)
        _area_light("ceiling", cfg.ceiling_light_w, 1.2, (0.0, 0.3, 1.3), self.room)

    def _clutter(self) -> list[bpy.types.Object]:
        cfg = self.cfg
        rng = np.random.default_rng(cfg.clutter_seed)
        z_table = -cfg.plate_height_m
        room = self.room
        table = objects.box("table", (2.4, 1.6, 0.04), (0.0, 0.35, z_table - 0.02), parent=room)
        materials.assign(table, _wood_material("wood", srgb_to_linear((0.72, 0.55, 0.38)),
                                      srgb_to_linear((0.5, 0.35, 0.22)), cfg.clutter_seed))
        wall_y = 0.55
        wall = objects.box("wall", (3.0, 0.05, 2.0), (0.0, wall_y + 0.025, z_table + 1.0), parent=room)
        materials.assign(wall, _pattern("wall", "noise", srgb_to_linear((0.78, 0.77, 0.72)),
                                        srgb_to_linear((0.72, 0.71, 0.66)), 40.0, 0.8))
        corners = [(-0.15, 0, -0.21), (0.15, 0, -0.21), (0.15, 0, 0.21), (-0.15, 0, 0.21)]
        poster = objects.mesh_object("poster", corners, [(0, 1, 2, 3)], uvs=[(0, 0), (1, 0), (1, 1), (0, 1)],
                              parent=room)
        poster.location = (-0.35 + 0.2 * rng.random(), wall_y - 0.002, z_table + 0.42)
        materials.assign(poster, materials.textured("poster", materials.image("poster", _poster()), roughness=0.4))
        kinds = ("noise", "checker", "brick", "magic")
        static = [table, wall, poster]
        placed: list[tuple[float, float, float]] = []
        # Distractors stand behind the plate or off to the sides, never between camera and plate.
        regions = [((-0.45, 0.45), (0.22, 0.42))] * 5
        regions += [((-0.45, -0.28), (-0.2, 0.05)), ((0.28, 0.45), (-0.2, 0.05))]
        for i, ((x0, x1), (y0, y1)) in enumerate(regions):
            for _ in range(50):
                radius = rng.uniform(0.03, 0.09)
                x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
                if all(math.hypot(x - px, y - py) > radius + pr + 0.02 for px, py, pr in placed):
                    break
            else:
                continue  # no free spot: one distractor fewer
            placed.append((x, y, radius))
            height = rng.uniform(0.05, 0.28)
            hue = rng.random()
            rgb = cv2.cvtColor(np.uint8([[[hue * 180, 150, 200]]]), cv2.COLOR_HSV2RGB)[0, 0] / 255
            color_a = srgb_to_linear(rgb)
            color_b = tuple(0.3 * c + 0.05 for c in color_a)
            mat = _pattern(f"distractor{i}", kinds[i % len(kinds)], color_a, color_b,
                                    rng.uniform(4, 30), rng.uniform(0.2, 0.8))
            if rng.random() < 0.5:
                obj = objects.cylinder(f"distractor{i}", radius, z_table, z_table + height, (x, y, 0.0), n=48,
                                parent=room)
            else:
                size = (1.4 * radius, rng.uniform(0.7, 1.3) * 1.4 * radius, height)
                obj = objects.box(f"distractor{i}", size, (x, y, z_table + height / 2), rng.uniform(0, np.pi), room)
            materials.assign(obj, mat)
            static.append(obj)
        return static

    def _render_background(self) -> dict | None:
        """Render the static surroundings once (object hidden, always denoised), then hide them from camera
        rays."""
        if not self.static:
            return None
        cycles = self.scene.cycles
        cycles.samples, cycles.use_denoising = self.cfg.background_samples, True
        self.scene.render.film_transparent = False
        for obj in self.objects:
            obj.hide_render = True
        bpy.ops.render.render(write_still=True)
        background = _read_exr(self.exr)
        for obj in self.objects:
            obj.hide_render = False
        for obj in self.static:
            obj.visible_camera = False
        self.scene.render.film_transparent = True
        cycles.samples, cycles.use_denoising = self.cfg.samples, self.cfg.denoiser == "oidn"
        return background

    def render(self, angle_rad: float, object_visible: bool = True) -> dict:
        """Linear RGB (float32), object mask (bool) and planar depth (float32, m) at plate angle `angle_rad`.

        Only the turntable, board and object are rendered (over a transparent film, the surroundings
        still casting shadows and bouncing light); they are laid over the cached background. With
        `object_visible` False the object is left out of the render altogether (the empty plate).
        """
        self.rig.rotation_euler = (0.0, 0.0, float(angle_rad))
        for obj in self.objects:
            obj.hide_render = not object_visible
        bpy.ops.render.render(write_still=True)
        frame = _read_exr(self.exr)
        if self.background is not None:
            alpha = frame.pop("alpha")[..., None]
            frame["linear"] = frame["linear"] + (1.0 - alpha) * self.background["linear"]
            far = frame["depth"] > 1e9
            frame["depth"][far] = self.background["depth"][far]
        return frame


def _pattern(name, kind, color_a, color_b, scale, roughness):
    return materials.pattern(name, kind, color_a, color_b, scale, roughness)[0]


def _read_exr(path: Path) -> dict:
    """The render's passes as the sim camera uses them: linear RGB, alpha, depth and the object mask."""
    frame = renderer.read_exr(path)
    frame["mask"] = frame.pop("index") == OBJECT_INDEX
    return frame


def serve(conn: Connection) -> None:
    """Worker process main loop: build the scene from the config sent first, then answer render requests."""
    try:
        cfg_dict = conn.recv()
        shm = "/dev/shm" if os.path.isdir("/dev/shm") else None  # the EXR never needs to touch a disk
        with tempfile.TemporaryDirectory(prefix="n2d_sim_", dir=shm) as workdir:
            t0 = time.perf_counter()
            scene = Scene(from_dict(SimWorldConfig, cfg_dict), Path(workdir))
            conn.send(("ready", {"device": scene.device, "build_s": time.perf_counter() - t0}))
            while True:
                command, arg = conn.recv()
                if command == "close":
                    return
                if command == "place":
                    scene.place(arg)
                    conn.send(("placed", None))
                    continue
                frame = scene.render(*arg)
                frame["rgb"] = to_srgb8(frame.pop("linear"), scene.cfg.exposure_ev)
                frame.pop("alpha", None)
                conn.send(("frame", frame))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        return
    except Exception:
        text = traceback.format_exc()
        print(text, file=sys.stderr, flush=True)
        conn.send(("error", text))


if __name__ == "__main__":
    serve(Connection(int(sys.argv[1])))
