"""The simulated turntable camera: rendered frames with exact ground truth, plus sensor noise.

`SimCamera` runs Blender in a worker process (`python -m n2d_sim.render_worker`; bpy is never
imported in the caller's process, which may be a ROS node) and keeps the scene built between
frames, so a new plate angle costs one render. The worker is a plain subprocess talking over a
socket pair, not a multiprocessing child, so callers need no `if __name__ == "__main__"` guard.
Frames are noise-free and cached by angle; `noisy()` adds fresh sensor noise, so a node can
republish the last frame at its camera rate while the plate stands still. `render(angle,
object_visible=False)` gives the empty plate at that angle, the reference for background subtraction;
`place(placement_deg)` turns the object over on the plate (`SimWorldConfig.placement_deg`) in the built scene.

    with SimCamera(SimWorldConfig(object="bottle")) as cam:
        frame = cam.render(math.radians(30))
        empty = cam.render(math.radians(30), object_visible=False)
        image = cam.noisy(frame.rgb, rng)
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection

import numpy as np

from n2d_common.config import to_dict
from n2d_common.errors import DeviceError
from n2d_common.process import die_with_parent
from n2d_sim import world
from n2d_sim.world import SimWorldConfig

START_TIMEOUT_S = 600.0
"""Longest wait for the worker to import bpy, build the scene and render the background."""
RENDER_TIMEOUT_S = 300.0
"""Longest wait for one frame."""


@dataclass
class SimFrame:
    """One noise-free rendered view with its ground truth (OpenCV camera frame, metres)."""

    rgb: np.ndarray
    """HxWx3 uint8 sRGB image."""
    mask: np.ndarray
    """HxW bool: pixels whose centre sees the object (exact, not anti-aliased); all False when it is hidden."""
    depth: np.ndarray
    """HxW float32 planar depth (distance along the optical axis), metres."""
    K: np.ndarray
    """3x3 intrinsics."""
    T_cam_turntable: np.ndarray
    """4x4 transform from the turntable frame into the camera frame."""
    T_cam_obj: np.ndarray
    """4x4 transform from the object (model) frame into the camera frame (where it stands, even when hidden)."""
    angle_rad: float
    """Plate angle of this view, radians."""
    render_s: float
    """Seconds the render took (0 when it came from the cache)."""
    object_visible: bool = True
    """False for a render of the empty plate (the object left out)."""


class SimCamera:
    """A fixed camera looking at the simulated turntable; renders in a worker process.

    Use as a context manager, or call `start()` and `close()`. Thread-safe: renders are serialised.
    """

    def __init__(self, cfg: SimWorldConfig | None = None):
        self.cfg = cfg or SimWorldConfig()
        self.K = world.K(self.cfg)
        self.T_cam_turntable = world.T_cam_turntable(self.cfg)
        self.info: dict = {}
        """What the worker reported at start: device (CPU/GPU) and build_s."""
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()
        self._cache: OrderedDict[tuple[float, bool], SimFrame] = OrderedDict()

    @property
    def width(self) -> int:
        return self.cfg.width

    @property
    def height(self) -> int:
        return self.cfg.height

    def start(self) -> SimCamera:
        """Start the render process and wait until its scene is built (a few seconds)."""
        with self._lock:
            if self._proc is not None:
                return self
            ours, theirs = socket.socketpair()
            with theirs:
                # Blender prints render progress on stdout: keep it out of the caller's output.
                self._proc = subprocess.Popen(
                    [sys.executable, "-m", "n2d_sim.render_worker", str(theirs.fileno())],
                    pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                    preexec_fn=die_with_parent)
            self._conn = Connection(ours.detach())
            try:
                self._conn.send(to_dict(self.cfg))
                self.info = self._receive("ready", START_TIMEOUT_S)
            except BaseException:
                self._stop()
                raise
        return self

    def close(self) -> None:
        """Stop the render process."""
        with self._lock:
            self._stop()

    def _stop(self) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if proc is None:
            return
        try:
            conn.send(("close", None))
        except OSError:
            pass
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        conn.close()

    def __enter__(self) -> SimCamera:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def render(self, angle_rad: float, object_visible: bool = True) -> SimFrame:
        """The noise-free frame at plate angle `angle_rad` (from the cache when it was rendered lately).

        The frame's `angle_rad` is the angle asked for (multi-turn angles stay as they are); the cache
        and the render work with the angle modulo one turn. With `object_visible` False the object is
        left out (the empty plate: no object, none of its shadows; the mask all False).
        """
        angle = float(angle_rad)
        object_visible = bool(object_visible)
        key = (round(math.remainder(angle, 2 * math.pi), 6), object_visible)
        if self._proc is None:
            self.start()
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return replace(self._cache[key], angle_rad=angle, T_cam_obj=world.T_cam_obj(self.cfg, angle),
                               render_s=0.0)
            t0 = time.perf_counter()
            out = self._ask("render", (math.remainder(angle, 2 * math.pi), object_visible), "frame")
            frame = SimFrame(rgb=out["rgb"], mask=out["mask"], depth=out["depth"], K=self.K.copy(),
                             T_cam_turntable=self.T_cam_turntable.copy(),
                             T_cam_obj=world.T_cam_obj(self.cfg, angle), angle_rad=angle,
                             render_s=time.perf_counter() - t0, object_visible=object_visible)
            self._cache[key] = frame
            while len(self._cache) > self.cfg.cache_size:
                self._cache.popitem(last=False)
        return frame

    def place(self, placement_deg) -> None:
        """Lay the object on the plate another way (`SimWorldConfig.placement_deg`: what a person turning it over
        does); later frames and their ground truth show it so."""
        cfg = replace(self.cfg, placement_deg=tuple(placement_deg))  # validated before the worker sees it
        if self._proc is None:
            self.start()
        with self._lock:
            self._ask("place", cfg.placement_deg, "placed")
            self.cfg = cfg
            self._cache.clear()

    def noisy(self, rgb: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """`rgb` with fresh sensor noise: Gaussian read noise plus signal-dependent shot noise (8-bit DN)."""
        rng = rng or np.random.default_rng()
        x = rgb.astype(np.float32)
        sigma = np.sqrt(np.float32(self.cfg.read_noise_dn) ** 2 + np.float32(self.cfg.shot_noise) * x)
        x += rng.standard_normal(x.shape, dtype=np.float32) * sigma
        return np.clip(np.rint(x), 0, 255).astype(np.uint8)

    def _ask(self, command: str, arg, expected: str):
        """Send the worker `(command, arg)` and return its answer of kind `expected` (the lock held)."""
        if self._conn is None:
            raise DeviceError("the simulated camera is closed", "start() it again")
        try:
            self._conn.send((command, arg))
        except (BrokenPipeError, OSError):
            raise DeviceError("the simulated camera's render process is gone", "restart the camera") from None
        return self._receive(expected, RENDER_TIMEOUT_S)

    def _receive(self, expected: str, timeout_s: float):
        """The next message of kind `expected` from the worker, or a DeviceError saying why not."""
        if not self._conn.poll(timeout_s):
            raise DeviceError(f"the simulated camera did not answer within {timeout_s:.0f} s",
                              "is the machine overloaded? lower width/height or samples")
        try:
            kind, payload = self._conn.recv()
        except (EOFError, OSError):
            raise DeviceError("the simulated camera's render process died",
                              "run `python -c 'import bpy'` to check the Blender install") from None
        if kind == "error":
            last = payload.strip().splitlines()[-1]
            raise DeviceError(f"the simulated camera failed: {last}", "see the traceback above in stderr")
        if kind != expected:
            raise DeviceError(f"the simulated camera answered {kind!r} instead of {expected!r}")
        return payload
