"""One random scene per frame, composed from the bpy layer: floor and walls, the target models, distractors,
a printed fiducial sheet, lights and sky, dropped by physics or held in a gripper proxy.

World frame: Z up, floor at z = 0. Target instances get Object Index 1..n (their label in the index
pass); everything else keeps 0. Runs inside a render worker process only (imports bpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np
from mathutils import Matrix

from n2d_blender import lighting, materials, objects, physics
from n2d_blender.camera import make_camera, world_pose
from n2d_common.frames import make_T, rot_z
from n2d_common.images import random_color
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import Model
from n2d_dataset.placement import resting_poses, sample_orientation
from n2d_dataset.poses import random_rotation
from n2d_dataset.textures import random_fiducial_sheet, random_image

FLOOR_HALF_M = 4.0
"""Half size of the floor square, metres."""


@dataclass
class Instance:
    """A target model placed in the scene."""

    model: Model
    """Which model it shows."""
    index: int
    """Its Object Index pass value (1..n)."""
    obj: bpy.types.Object
    """The Blender object (its matrix_world is T_world_obj once the scene is built)."""

    def T_world_obj(self) -> np.ndarray:
        return world_pose(self.obj)


def random_material(rng: np.random.Generator, name: str) -> bpy.types.Material:
    """A random surface: plain, one of the procedural patterns, or a random image repeated over it."""
    roughness, specular = rng.uniform(0.1, 1.0), rng.uniform(0.1, 0.8)
    choice = rng.integers(0, len(materials.PATTERNS) + 2)
    if choice == len(materials.PATTERNS):
        return materials.principled(name, random_color(rng), roughness, specular,
                                    metallic=float(rng.random() < 0.15))[0]
    if choice == len(materials.PATTERNS) + 1:
        return materials.textured(name, materials.image(name, random_image(rng)), roughness, specular, coords="Object",
                        scale=rng.uniform(1.0, 12.0))
    kind = list(materials.PATTERNS)[choice]
    return materials.pattern(name, kind, random_color(rng), random_color(rng), rng.uniform(2.0, 40.0), roughness,
                             specular)[0]


class SceneBuilder:
    """Loads the models once, then builds a new random scene per frame on demand."""

    def __init__(self, models: list[Model], cfg: DatasetConfig):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.cfg = cfg
        self.models = models
        self.meshes = {m.name: objects.load_model(m.directory, m.name) for m in models}
        self.poses = {m.name: resting_poses(m.mesh) for m in models}
        self.camera = make_camera(cfg.camera.width, cfg.camera.height, cfg.camera.focal_px)

    def build(self, rng: np.random.Generator) -> tuple[list[Instance], Instance, bool]:
        """Clear the last scene and compose a new one; returns the target instances, the one the camera
        looks at, and whether the frame is in-hand."""
        objects.clear_scene(keep=(self.camera,))
        sc = self.cfg.scene
        floor = self._room(rng)
        instances = []
        for model in self.models:
            for _ in range(rng.integers(sc.instances_per_model[0], sc.instances_per_model[1] + 1)):
                obj = objects.instance(self.meshes[model.name], f"{model.name}_{len(instances)}")
                obj.pass_index = len(instances) + 1
                instances.append(Instance(model, len(instances) + 1, obj))
        if not instances:  # every range allowed zero copies: show one of the first model
            obj = objects.instance(self.meshes[self.models[0].name], f"{self.models[0].name}_0")
            obj.pass_index = 1
            instances.append(Instance(self.models[0], 1, obj))
        distractors = [self._distractor(rng, i) for i in range(rng.integers(sc.distractors[0], sc.distractors[1] + 1))]
        in_hand = bool(rng.random() < sc.in_hand)
        held = instances[rng.integers(len(instances))] if in_hand else None
        resting = [i.obj for i in instances if i is not held] + distractors
        poses = {i.obj.name: self.poses[i.model.name] for i in instances}
        self._scatter(rng, resting, poses)
        if sc.physics and resting:
            physics.drop(resting, [floor])
        if held is not None:
            self._hold(rng, held)
        focus = instances[rng.integers(len(instances))] if held is None else held
        # No draw at all when boards is 0, so configs without sheets render the frames they always did.
        if sc.boards and rng.random() < sc.boards:
            self._sheet(rng, instances[rng.integers(len(instances))])
        lighting.random_lights(rng, int(rng.integers(sc.lights[0], sc.lights[1] + 1)), sc.light_power_w,
                               focus.T_world_obj()[:3, 3])
        lighting.gradient_world(rng, float(rng.uniform(*sc.world_strength)))
        bpy.context.view_layer.update()
        return instances, focus, in_hand

    def _room(self, rng: np.random.Generator) -> bpy.types.Object:
        h = FLOOR_HALF_M
        floor = objects.mesh_object("floor", [(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [(0, 1, 2, 3)])
        materials.assign(floor, random_material(rng, "floor"))
        if rng.random() < self.cfg.scene.walls:
            d = rng.uniform(0.5, 1.5)
            for i, (a, b) in enumerate((((-d, -h), (-d, h)), ((-h, -d), (h, -d)))):
                (x0, y0), (x1, y1) = a, b
                wall = objects.mesh_object(f"wall{i}", [(x0, y0, 0), (x1, y1, 0), (x1, y1, 3), (x0, y0, 3)],
                                           [(0, 1, 2, 3)])
                materials.assign(wall, random_material(rng, f"wall{i}"))
        return floor

    def _distractor(self, rng: np.random.Generator, i: int) -> bpy.types.Object:
        lo, hi = self.cfg.scene.distractor_size_m
        size = rng.uniform(lo, hi) * rng.uniform(0.3, 1.0, 3)
        size[rng.integers(3)] = max(size.max(), lo)
        obj = objects.primitive(f"distractor{i}", str(rng.choice(objects.PRIMITIVES)), size)
        materials.assign(obj, random_material(rng, f"distractor{i}"))
        return obj

    def _sheet(self, rng: np.random.Generator, under: Instance) -> None:
        """A fiducial sheet flat on the floor, 0.15-0.45 m across, roughly centred under `under` (held
        targets too: the sheet is on the table below them), turned at random about Z."""
        img = random_fiducial_sheet(rng)
        h, w = img.shape
        sx = rng.uniform(0.15, 0.45)
        sy = sx * h / w
        verts = [(-sx / 2, -sy / 2, 0), (sx / 2, -sy / 2, 0), (sx / 2, sy / 2, 0), (-sx / 2, sy / 2, 0)]
        sheet = objects.mesh_object("fiducial_sheet", verts, [(0, 1, 2, 3)], uvs=[(0, 0), (1, 0), (1, 1), (0, 1)])
        centre = under.T_world_obj()[:2, 3] + rng.uniform(-0.3, 0.3, 2) * (sx, sy)
        # 0.3 mm above the floor: above it for the depth test, below anything resting on it by less than a pixel.
        T = rot_z(rng.uniform(0, 2 * np.pi))
        T[:3, 3] = (*centre, 0.0003)
        sheet.matrix_world = Matrix(T.tolist())
        paper = materials.image("fiducial_sheet", img)
        materials.assign(sheet, materials.textured("fiducial_sheet", paper, roughness=rng.uniform(0.3, 0.9),
                                                   interpolation="Closest"))

    def _scatter(self, rng: np.random.Generator, objs: list[bpy.types.Object], poses: dict) -> None:
        """Orientations over the spread square, stacked in height so nothing starts interpenetrating: models stand
        as captured, lie in a resting pose or turn at random (`placement.sample_orientation`), distractors turn
        at random; physics then settles them."""
        sc = self.cfg.scene
        spread = sc.spread_m
        z = 0.0
        for obj in objs:
            radius = max(obj.dimensions) / 2
            z += radius + 0.005
            R = (sample_orientation(rng, poses[obj.name], sc.upright, sc.resting)[0] if obj.name in poses
                 else random_rotation(rng))
            T = make_T(R, (*rng.uniform(-spread, spread, 2), z))
            obj.matrix_world = Matrix(T.tolist())
            z += radius

    def _hold(self, rng: np.random.Generator, held: Instance) -> None:
        """Put `held` in the air at a random orientation, pinched across its x extent by a two-finger gripper
        (palm, fingers and a forearm: occluders with a random plastic or metal finish)."""
        T = make_T(random_rotation(rng), (*rng.uniform(-0.1, 0.1, 2), rng.uniform(0.2, 0.45)))
        held.obj.matrix_world = Matrix(T.tolist())
        hx, hy, hz = (d / 2 for d in held.model.size_m)
        t, w = 0.012, min(0.03, 2 * hy)
        reach = hz + 0.03
        parts = [((t, w, reach), (-(hx + t / 2), 0.0, reach / 2)),              # fingers, from the palm down
                 ((t, w, reach), (hx + t / 2, 0.0, reach / 2)),
                 ((2 * hx + 2 * t + 0.02, 0.05, 0.025), (0.0, 0.0, reach + 0.0125))]  # palm
        finish = materials.principled("gripper", random_color(rng) if rng.random() < 0.5 else (0.02,) * 3,
                                      roughness=rng.uniform(0.2, 0.7), metallic=float(rng.random() < 0.4))[0]
        for i, (size, centre) in enumerate(parts):
            part = objects.box(f"gripper{i}", size)
            part.matrix_world = Matrix((T @ make_T(np.eye(3), centre)).tolist())
            materials.assign(part, finish)
        arm = objects.cylinder("forearm", 0.03, reach + 0.025, reach + 0.5, n=24)
        arm.matrix_world = Matrix(T.tolist())
        materials.assign(arm, finish)
