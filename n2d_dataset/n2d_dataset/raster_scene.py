"""One random scene per frame for the fast renderer, in plain numpy (no bpy): floor and walls, the target models,
distractors, a printed fiducial sheet, lights and sky, resting as objects rest on a table or held by a gripper.

The same composition as the Cycles path's `scene.py`, drawn from the same config; what differs is that nothing is
dropped by a physics engine: a model either stands as it was captured, lies in one of its resting poses (the
stable faces of its hull, `placement.py`) or, drawn with a random rotation, floats above the floor as in DOPE's
"flying distractors" domain randomisation. World frame: Z up, floor at z = 0. Target instances get labels 1..n.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from n2d_common.errors import ContractError
from n2d_common.frames import make_T, rot_z
from n2d_common.images import kelvin_to_rgb, random_color
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import Model
from n2d_dataset.placement import RestingPose, rest_height, resting_poses, sample_orientation
from n2d_dataset.poses import random_rotation
from n2d_dataset.shading import Body, Light, Material, Plane, RasterScene, Sky, corner_normals
from n2d_dataset.textures import random_fiducial_sheet, random_image

FLOOR_HALF_M = 4.0
"""Half size of the floor square, metres (as the Cycles path)."""
DISTRACTOR_KINDS = ("box", "cylinder", "cone", "sphere", "icosphere", "capsule", "torus")
"""Shapes of the procedural distractors."""


def srgb8_to_linear(img: np.ndarray) -> np.ndarray:
    """Linear float32 RGB of an 8-bit sRGB image."""
    c = img.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


@dataclass
class Template:
    """A model loaded once: its mesh, texture, material and resting poses."""

    model: Model
    body: Body
    poses: list[RestingPose]


def load_template(model: Model) -> Template:
    """Read a model directory's textured mesh (metres, object frame) for the fast renderer."""
    path = model.directory / "mesh.obj"
    mesh = trimesh.load(path, force="mesh", process=False)
    uv = getattr(mesh.visual, "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        raise ContractError(f"{path} has no per-vertex texture coordinates", "export the model with its UV atlas")
    image = getattr(getattr(mesh.visual, "material", None), "image", None)
    if image is not None:
        texture = srgb8_to_linear(np.asarray(image.convert("RGB")))
    else:
        kd = np.asarray(getattr(mesh.visual.material, "diffuse", [200, 200, 200, 255]), float)[:3]
        texture = srgb8_to_linear(np.full((2, 2, 3), kd, np.uint8))
    faces = np.asarray(mesh.faces, np.int64)
    material = Material()
    manifest = model.directory / "n2d.json"
    if manifest.is_file():
        m = json.loads(manifest.read_text()).get("config", {}).get("material", {}) or {}
        material = Material(float(m.get("roughness", 0.5)), float(m.get("specular", 0.5)),
                            float(m.get("metallic", 0.0)))
    vertices = np.asarray(mesh.vertices, float)
    body = Body(vertices, faces, corner_normals(vertices, faces), np.asarray(uv, float)[faces], texture, np.eye(4),
                material)
    return Template(model, body, resting_poses(trimesh.Trimesh(vertices, faces, process=True)))


def _random_texture(rng: np.random.Generator) -> np.ndarray:
    """A random linear albedo: plain, a random picture, checks, stripes or coloured noise."""
    kind = rng.integers(5)
    a, b = np.array(random_color(rng), np.float32), np.array(random_color(rng), np.float32)
    if kind == 0:
        return np.broadcast_to(a, (4, 4, 3)).copy()
    if kind == 1:
        return srgb8_to_linear(random_image(rng, 128))
    n = 64
    y, x = np.mgrid[0:n, 0:n]
    if kind == 2:
        cells = int(rng.choice([2, 4, 8]))
        t = ((x // (n // cells) + y // (n // cells)) % 2).astype(np.float32)
    elif kind == 3:
        t = (np.sin(2 * np.pi * (x * rng.integers(1, 6) + y * rng.integers(0, 3)) / n) > 0).astype(np.float32)
    else:
        t = cv2.resize(rng.random((rng.integers(3, 12),) * 2).astype(np.float32), (n, n),
                       interpolation=cv2.INTER_CUBIC) + rng.normal(0, 0.1, (n, n)).astype(np.float32)
        t = np.clip(t, 0, 1)
    return (a * t[..., None] + b * (1 - t[..., None])).astype(np.float32)


def _random_material(rng: np.random.Generator) -> Material:
    return Material(float(rng.uniform(0.1, 1.0)), float(rng.uniform(0.1, 0.8)), float(rng.random() < 0.15))


def _box_uvs(vertices: np.ndarray, faces: np.ndarray, repeat: float) -> np.ndarray:
    """F x 3 x 2 UVs projected along each face's dominant axis (a box mapping), `repeat` tiles across the size."""
    v = vertices[faces]
    n = np.abs(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]))
    axis = n.argmax(1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    scale = repeat / max(float(np.ptp(vertices, axis=0).max()), 1e-6)
    return np.take_along_axis(v, keep[:, None, :].repeat(3, 1), 2) * scale


def primitive_body(kind: str, size: np.ndarray, texture: np.ndarray, material: Material, repeat: float) -> Body:
    """A distractor or gripper part: a primitive fitting a box of `size` (x, y, z metres), centred at its origin."""
    if kind == "box":
        m = trimesh.creation.box(extents=(1, 1, 1))
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=0.5, height=1.0, sections=24)
    elif kind == "cone":
        m = trimesh.creation.cone(radius=0.5, height=1.0, sections=24)
        m.apply_translation((0, 0, -0.5))
    elif kind == "sphere":
        m = trimesh.creation.uv_sphere(radius=0.5, count=(16, 24))
    elif kind == "icosphere":
        m = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    elif kind == "capsule":
        m = trimesh.creation.capsule(height=0.5, radius=0.25, count=(12, 12))
        m.apply_translation(-m.bounds.mean(0))
        m.apply_scale(1.0 / np.ptp(m.vertices, axis=0))
    elif kind == "torus":
        m = trimesh.creation.torus(major_radius=0.35, minor_radius=0.15, major_sections=24, minor_sections=12)
        m.apply_scale(1.0 / np.ptp(m.vertices, axis=0))
    else:
        raise ValueError(f"unknown primitive {kind!r}; known: {', '.join(DISTRACTOR_KINDS)}")
    vertices = np.asarray(m.vertices, float) * np.asarray(size, float)
    faces = np.asarray(m.faces, np.int64)
    return Body(vertices, faces, corner_normals(vertices, faces), _box_uvs(vertices, faces, repeat), texture,
                np.eye(4), material)


def _quad(size_x: float, size_y: float, texture: np.ndarray, material: Material) -> Body:
    """A flat rectangle in the z = 0 plane, centred, UVs spanning the texture once."""
    v = np.array([(-size_x / 2, -size_y / 2, 0), (size_x / 2, -size_y / 2, 0), (size_x / 2, size_y / 2, 0),
                  (-size_x / 2, size_y / 2, 0)], float)
    f = np.array([(0, 1, 2), (0, 2, 3)])
    uv = np.array([(0, 0), (1, 0), (1, 1), (0, 1)], float)
    # A sheet's UVs stay inside [0, 1] (0.001 in from the border): it must not repeat.
    uv = 0.001 + 0.998 * uv
    return Body(v, f, np.tile([0.0, 0.0, 1.0], (2, 3, 1)), uv[f], texture, np.eye(4), material)


@dataclass
class Placed:
    """A target instance of a composed scene."""

    template: Template
    label: int
    body: Body

    @property
    def model(self) -> Model:
        return self.template.model

    def T_world_obj(self) -> np.ndarray:
        return self.body.T_world


class RasterSceneBuilder:
    """Loads the models once, then composes a new random scene per frame."""

    def __init__(self, models: list[Model], cfg: DatasetConfig):
        self.cfg = cfg
        self.templates = [load_template(m) for m in models]

    def build(self, rng: np.random.Generator) -> tuple[RasterScene, list[Placed], Placed, bool]:
        """A new scene: (the scene, its target instances, the one the camera looks at, whether in hand)."""
        sc = self.cfg.scene
        planes = self._room(rng)
        placed: list[Placed] = []
        for t in self.templates:
            for _ in range(rng.integers(sc.instances_per_model[0], sc.instances_per_model[1] + 1)):
                placed.append(self._instance(t, len(placed) + 1, rng))
        if not placed:
            placed.append(self._instance(self.templates[0], 1, rng))
        in_hand = bool(rng.random() < sc.in_hand)
        held = placed[rng.integers(len(placed))] if in_hand else None
        bodies = [p.body for p in placed]
        distractors = [self._distractor(rng) for _ in range(rng.integers(sc.distractors[0], sc.distractors[1] + 1))]
        footprints: list[tuple[np.ndarray, float]] = []
        for item in [p for p in placed if p is not held] + distractors:
            body, poses = (item.body, item.template.poses) if isinstance(item, Placed) else (item, [])
            self._place(rng, body, poses, footprints)
        bodies += distractors
        if held is not None:
            bodies += self._hold(rng, held)
        focus = held if held is not None else placed[rng.integers(len(placed))]
        if sc.boards and rng.random() < sc.boards:
            bodies.append(self._sheet(rng, placed[rng.integers(len(placed))]))
        lights = self._lights(rng, int(rng.integers(sc.lights[0], sc.lights[1] + 1)), focus.T_world_obj()[:3, 3])
        sky = Sky(np.array(random_color(rng), np.float32), np.array(random_color(rng), np.float32),
                  float(rng.uniform(*sc.world_strength)))
        return RasterScene(bodies, planes, lights, sky), placed, focus, in_hand

    def _instance(self, t: Template, label: int, rng: np.random.Generator) -> Placed:
        b = t.body
        m = b.material
        jitter = Material(float(np.clip(m.roughness + rng.uniform(-0.15, 0.15), 0.05, 1.0)), m.specular, m.metallic)
        return Placed(t, label, Body(b.vertices, b.faces, b.corner_normals, b.face_uvs, b.texture, np.eye(4), jitter,
                                     label))

    def _room(self, rng: np.random.Generator) -> list[Plane]:
        h = FLOOR_HALF_M
        ex, ey, ez = np.eye(3)
        planes = [Plane(np.array([-h, -h, 0.0]), ex, ey, (2 * h, 2 * h), _random_texture(rng),
                        float(rng.uniform(0.05, 1.0)), _random_material(rng))]
        if rng.random() < self.cfg.scene.walls:
            d = rng.uniform(0.5, 1.5)
            planes.append(Plane(np.array([-d, -h, 0.0]), ey, ez, (2 * h, 3.0), _random_texture(rng),
                                float(rng.uniform(0.05, 1.0)), _random_material(rng)))
            planes.append(Plane(np.array([-h, -d, 0.0]), ez, ex, (3.0, 2 * h), _random_texture(rng),
                                float(rng.uniform(0.05, 1.0)), _random_material(rng)))
        return planes

    def _distractor(self, rng: np.random.Generator) -> Body:
        lo, hi = self.cfg.scene.distractor_size_m
        size = rng.uniform(lo, hi) * rng.uniform(0.3, 1.0, 3)
        size[rng.integers(3)] = max(size.max(), lo)
        kind = str(rng.choice(DISTRACTOR_KINDS))
        return primitive_body(kind, size, _random_texture(rng), _random_material(rng), float(rng.uniform(1, 6)))

    def _place(self, rng: np.random.Generator, body: Body, poses: list[RestingPose],
               footprints: list[tuple[np.ndarray, float]]) -> None:
        """Orient `body` as a model rests (or at random, floating), then put it where it overlaps nothing placed
        so far (within the spread square; after 20 tries it floats above the others)."""
        sc = self.cfg.scene
        if poses:
            R, how = sample_orientation(rng, poses, sc.upright, sc.resting)
        else:  # a distractor: on the floor about a random yaw, or turned at random
            R, how = (rot_z(rng.uniform(0, 2 * np.pi))[:3, :3], "upright") if rng.random() < 0.6 else (
                random_rotation(rng), "random")
        rotated = body.vertices @ R.T
        radius = float(np.linalg.norm(rotated[:, :2], axis=1).max())
        z = rest_height(body.vertices, R)
        if how == "random":
            z += rng.uniform(0.0, 0.25)
        for _ in range(20):
            xy = rng.uniform(-sc.spread_m, sc.spread_m, 2)
            if all(np.linalg.norm(xy - c) > radius + r for c, r in footprints):
                break
        else:
            z += 0.3
        footprints.append((xy, radius))
        body.T_world = make_T(R, (*xy, z))

    def _hold(self, rng: np.random.Generator, held: Placed) -> list[Body]:
        """Put `held` in the air at a random orientation, pinched across its x extent by a two-finger gripper
        (palm, fingers, forearm) of one random plastic or metal finish; returns the gripper's parts."""
        T = make_T(random_rotation(rng), (*rng.uniform(-0.1, 0.1, 2), rng.uniform(0.2, 0.45)))
        held.body.T_world = T
        hx, hy, hz = (d / 2 for d in held.model.size_m)
        t, w = 0.012, min(0.03, 2 * hy)
        reach = hz + 0.03
        parts = [((t, w, reach), (-(hx + t / 2), 0.0, reach / 2)), ((t, w, reach), (hx + t / 2, 0.0, reach / 2)),
                 ((2 * hx + 2 * t + 0.02, 0.05, 0.025), (0.0, 0.0, reach + 0.0125))]
        colour = np.array(random_color(rng) if rng.random() < 0.5 else (0.02,) * 3, np.float32)
        finish = Material(float(rng.uniform(0.2, 0.7)), 0.5, float(rng.random() < 0.4))
        texture = np.broadcast_to(colour, (2, 2, 3)).copy()
        bodies = []
        for size, centre in parts:
            part = primitive_body("box", np.array(size), texture, finish, 1.0)
            part.T_world = T @ make_T(np.eye(3), centre)
            bodies.append(part)
        arm = primitive_body("cylinder", np.array([0.06, 0.06, 0.5]), texture, finish, 1.0)
        arm.T_world = T @ make_T(np.eye(3), (0.0, 0.0, reach + 0.025 + 0.25))
        return bodies + [arm]

    def _sheet(self, rng: np.random.Generator, under: Placed) -> Body:
        """A fiducial sheet flat on the floor, 0.15-0.45 m across, roughly centred under `under`."""
        img = random_fiducial_sheet(rng)
        h, w = img.shape
        sx = rng.uniform(0.15, 0.45)
        sy = sx * h / w
        paper = srgb8_to_linear(np.repeat(img[..., None], 3, 2))
        sheet = _quad(sx, sy, paper, Material(float(rng.uniform(0.3, 0.9)), 0.5, 0.0))
        centre = under.T_world_obj()[:2, 3] + rng.uniform(-0.3, 0.3, 2) * (sx, sy)
        T = rot_z(rng.uniform(0, 2 * np.pi))
        T[:3, 3] = (*centre, 0.0003)
        sheet.T_world = T
        return sheet

    def _lights(self, rng: np.random.Generator, count: int, target: np.ndarray) -> list[Light]:
        """`count` lights of random colour temperature (2700-7500 K) and power above `target`, as the Cycles
        path draws them (area and spot lights become point lights here); the first two cast shadows."""
        lights = []
        for i in range(count):
            kind = str(rng.choice(["POINT", "SPOT", "AREA", "SUN"], p=[0.35, 0.2, 0.35, 0.1]))
            azimuth, elevation = rng.uniform(0, 2 * np.pi), rng.uniform(np.radians(25), np.radians(85))
            distance = rng.uniform(0.8, 2.5)
            direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                  np.sin(elevation)])
            color = np.array(kelvin_to_rgb(rng.uniform(2700, 7500)))
            if kind == "SUN":
                lights.append(Light(color * rng.uniform(1.0, 5.0), direction=direction, shadow=i < 2))
            else:
                power = rng.uniform(*self.cfg.scene.light_power_w) * distance ** 2
                lights.append(Light(color * power, position=np.asarray(target) + distance * direction, shadow=i < 2))
        return lights

