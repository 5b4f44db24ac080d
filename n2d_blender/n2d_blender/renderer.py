"""Renderer: Cycles set up for speed on a CPU (a GPU when present), renders to multilayer EXR read back as arrays.

Two kinds of render share one scene:
  - the image: `samples` per pixel, the pixel filter's anti-aliasing and OpenImageDenoise;
  - the labels: one sample through each pixel's centre (pixel filter width 0.01 px), no bounces, no
    denoiser, giving the Depth (planar, metres) and Object Index passes exactly at the pixel centres,
    where a pinhole projection with K puts them. Index and depth passes are written by a pixel's
    first sample only, so in the image render they would sit at a random sub-pixel offset.
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np
import OpenEXR

LABEL_FILTER_PX = 0.01
"""Pixel filter width of the label render (Blender's minimum): its one sample hits the pixel centre."""


def setup(exr_path: Path, samples: int, denoiser: str = "oidn", max_bounces: int = 3, device: str = "auto",
          threads: int = 0) -> str:
    """Configure Cycles for the current scene; returns the device used, "CPU" or "GPU"."""
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    used = "CPU"
    if device != "cpu":
        prefs = bpy.context.preferences.addons["cycles"].preferences
        for backend in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
            try:
                prefs.compute_device_type = backend
            except TypeError:
                continue
            prefs.get_devices()
            if any(d.type == backend for d in prefs.devices):
                for d in prefs.devices:
                    d.use = d.type == backend
                used = "GPU"
                break
        if used == "CPU" and device == "gpu":
            raise RuntimeError("device: gpu was asked for, but Cycles finds no GPU")
    cycles = scene.cycles
    cycles.device = used
    cycles.samples = samples
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = denoiser == "oidn"
    cycles.denoiser = "OPENIMAGEDENOISE"
    cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    cycles.denoising_prefilter = "FAST"
    cycles.denoising_quality = "FAST"
    cycles.max_bounces = max_bounces
    cycles.diffuse_bounces = cycles.glossy_bounces = max_bounces
    cycles.transmission_bounces = cycles.volume_bounces = 0
    cycles.transparent_max_bounces = 2
    cycles.caustics_reflective = cycles.caustics_refractive = False
    cycles.use_auto_tile = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = threads or len(os.sched_getaffinity(0))
    scene.render.use_persistent_data = True
    scene.view_settings.view_transform = "Standard"
    settings = scene.render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = "NONE"
    scene.render.filepath = str(exr_path)
    layer = scene.view_layers[0]
    layer.use_pass_z = True
    layer.use_pass_object_index = True
    return used


class LabelRender:
    """Within `with LabelRender():` renders give exact labels at pixel centres (one sample, no bounces)."""

    def __enter__(self):
        scene = bpy.context.scene
        c = scene.cycles
        self._saved = (c.samples, c.use_denoising, c.max_bounces, c.filter_width, scene.render.film_transparent)
        c.samples, c.use_denoising, c.max_bounces, c.filter_width = 1, False, 0, LABEL_FILTER_PX
        scene.render.film_transparent = True
        return self

    def __exit__(self, *_):
        scene = bpy.context.scene
        c = scene.cycles
        c.samples, c.use_denoising, c.max_bounces, c.filter_width, scene.render.film_transparent = self._saved


def render() -> dict:
    """Render the scene; returns linear RGB and alpha (float32), planar depth (metres, inf where nothing
    is hit) and the object index (int32) per pixel."""
    bpy.ops.render.render(write_still=True)
    return read_exr(Path(bpy.context.scene.render.filepath))


def read_exr(path: Path) -> dict:
    """Combined (linear RGB, alpha), Depth and Object Index passes of a Cycles multilayer EXR."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        # Blender 5 writes each pass as its own part of a multi-part file.
        ch = {name: c.pixels for part in f.parts for name, c in part.channels.items()}
    depth = ch["ViewLayer.Depth.Z"].astype(np.float32)
    depth[depth > 1e9] = np.inf
    return {"linear": np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1),
            "alpha": ch["ViewLayer.Combined.A"],
            "depth": depth,
            "index": np.round(ch["ViewLayer.Object Index.X"]).astype(np.int32)}
