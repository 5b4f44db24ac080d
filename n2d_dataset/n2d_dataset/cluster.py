"""Rendering a dataset's frames on a Ray cluster: one render actor per worker slot, the frames back to the driver.

The alternative to the local worker processes of `generate.py`, with the same frames and records. Each worker
slot is a Ray actor (`FrameRenderer`, one process; for Cycles one bpy per slot, a GPU per slot where the cluster
has GPUs). It checks its node (the n2d version, bpy for Cycles), receives the models as bytes (nodes need no
shared filesystem), sets up the same renderer as a local worker, then renders one frame per call into a scratch
directory of its own and returns that frame's files, its record last. The driver writes them into the dataset's
partial directory with the same atomic writes, so a frame counts as done only once its record is on the
driver's disk: a run stopped by a lost worker, node or head resumes from the records like a local run, and a
frame depends only on (seed, frame), so the dataset is byte for byte the one a single machine writes. Frames of
a worker that dies are handed to the others (and to a replacement actor once the cluster has room for it).
"""

from __future__ import annotations

import errno
import importlib.util
import shutil
import socket
import tempfile
import threading
import time
from collections import Counter, deque
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from contextlib import ExitStack
from pathlib import Path
from types import ModuleType

from n2d_common import __version__
from n2d_common.cluster import nodes
from n2d_common.contracts import atomic_write_bytes
from n2d_common.errors import Cancelled, N2DError
from n2d_common.progress import Progress
from n2d_dataset import writer
from n2d_dataset.config import DatasetConfig

WRITE_THREADS = 4
"""Frames the driver writes at once (each frame's files in turn, its record last): one writer, at tens of ms a frame
with fsync, would cap a large cluster (docs/experiments.md#dataset-on-ray)."""
FRAME_TRIES = 3
"""How often a frame is handed out again after the worker rendering it was lost, before the run stops."""
STALL_S = 120.0
"""The run stops when no worker slot comes up and no frame finishes for this long (no room on the cluster)."""
_SKIP = {"preview.png", "report.json"}


def _scratch_parent() -> str | None:
    return "/dev/shm" if Path("/dev/shm").is_dir() else None


class FrameRenderer:
    """A worker slot on a cluster node (run as a Ray actor): renders frames into a scratch directory of its own
    and returns their files."""

    def __init__(self):
        self.scratch = Path(tempfile.mkdtemp(prefix="n2d_frames_", dir=_scratch_parent()))
        self.stack = ExitStack()
        self.render_one = None

    def info(self) -> dict:
        """The node as n2d sees it: address, host name, n2d version, whether bpy is installed."""
        import ray

        return {"node": ray.util.get_node_ip_address(), "host": socket.gethostname(), "version": __version__,
                "bpy": importlib.util.find_spec("bpy") is not None}

    def open(self, models: list[tuple[str, dict[str, bytes]]], config: dict, engine: str, threads: int) -> str:
        """Write the models (name, {relative path: bytes}) into the scratch directory and set up the renderer of
        `engine` on them; returns the device it renders on."""
        dirs = []
        for i, (name, files) in enumerate(models):
            d = self.scratch / "models" / str(i) / name
            for rel, data in files.items():
                atomic_write_bytes(d / rel, data)
            dirs.append(str(d))
        if engine == "raster":
            from n2d_dataset.raster_worker import frame_renderer
        else:
            from n2d_dataset.render_worker import frame_renderer
        self.render_one, device = self.stack.enter_context(frame_renderer(dirs, config, threads))
        return device

    def render(self, frame: int) -> list[tuple[str, bytes]]:
        """Render one frame; returns its files as (path relative to the dataset root, bytes), the record last."""
        out = self.scratch / "out"
        self.render_one(out, frame)
        record = out / writer.RECORDS / f"{frame:06d}.json"
        files = [p for p in sorted(out.rglob("*")) if p.is_file() and p != record] + [record]
        result = [(str(p.relative_to(out)), p.read_bytes()) for p in files]
        shutil.rmtree(out)
        return result

    def close(self) -> None:
        self.stack.close()
        shutil.rmtree(self.scratch, ignore_errors=True)


def model_files(directory: Path) -> dict[str, bytes]:
    """A model directory's files as {relative path: bytes}, for workers without the driver's filesystem."""
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*"))
            if p.is_file() and p.name not in _SKIP and not any(part.endswith(".partial") for part in p.parts)}


def slots(cluster_nodes, cfg: DatasetConfig, engine: str) -> tuple[int, dict, int]:
    """(worker slots, Ray resources of one slot, render threads of one slot) for `engine` on these nodes:
    `cfg.workers` slots or one per core (raster), one per GPU (Cycles on GPUs) or one per node using its cores
    (Cycles on CPUs)."""
    alive = [n for n in cluster_nodes if n.cpus >= 1]
    if not alive:
        raise N2DError("the Ray cluster has no node with a free CPU", "check `ray status` on the head")
    gpus = sum(n.gpus for n in alive)
    if engine == "raster":
        return cfg.workers or int(sum(n.cpus for n in alive)), {"num_cpus": 1}, cfg.render.threads or 1
    if gpus >= 1 and cfg.render.device != "cpu":
        return cfg.workers or int(gpus), {"num_cpus": 1, "num_gpus": 1}, cfg.render.threads or 1
    cpus = int(min(n.cpus for n in alive))
    return cfg.workers or len(alive), {"num_cpus": cpus}, cfg.render.threads or cpus


def check_node(info: dict, engine: str) -> None:
    """Refuse a node that would write other frames: another n2d version, or no bpy for Cycles frames."""
    where = f"node {info['node']} ({info['host']})"
    if info["version"] != __version__:
        raise N2DError(f"{where} runs n2d {info['version']}, this machine n2d {__version__}",
                       "install the same n2d on every node of the cluster, then re-run the same command to resume")
    if engine == "cycles" and not info["bpy"]:
        raise N2DError(f"{where} has no bpy (Blender as a Python module) to render the Cycles frames",
                       "run install.sh on that node (or stop its `ray start`), then re-run the same command")


def write_frame_files(root: Path, files: list[tuple[str, bytes]]) -> None:
    """Write a frame's files from a worker into the dataset directory, the record last (atomic writes)."""
    try:
        for rel, data in files:
            atomic_write_bytes(root / rel, data)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise N2DError(f"the disk of {root} on {socket.gethostname()} (the driver) is full",
                           "free space there, then re-run the same command: the finished frames are kept") from None
        raise N2DError(f"could not write {root / rel} on {socket.gethostname()}: {exc}",
                       "check the output directory, then re-run the same command to resume") from None


def render_on_cluster(ray: ModuleType, job: dict, engine: str, frames: list[int], cfg: DatasetConfig, report,
                      cancel: threading.Event) -> None:
    """Render `frames` with `engine` on the connected Ray cluster into `job['root']` (the partial directory);
    `report(Progress)` after each frame written. Raises N2DError naming the node, or Cancelled."""
    from ray.exceptions import ObjectLostError, RayActorError, RayTaskError, WorkerCrashedError

    lost_errors = (RayActorError, WorkerCrashedError, ObjectLostError)
    root = Path(job["root"])
    count, options, threads = slots(nodes(ray), cfg, engine)
    models = ray.put([(Path(d).name, model_files(Path(d))) for d in job["model_dirs"]])
    Actor = ray.remote(FrameRenderer)
    todo, tries = deque(frames), Counter()
    pending: dict = {}  # ObjectRef -> (step: info | open | frame, actor, node info, frame)
    ready_actors, actors, spawned = [], [], 0
    last_event = time.monotonic()
    pool, writing = ThreadPoolExecutor(WRITE_THREADS, thread_name_prefix="n2d-write"), {}  # Future -> (frame, node)

    def written(block: bool) -> None:
        """Report the frames whose files are on disk (waiting for one when `block`); raise a write's error."""
        finished, _ = wait(list(writing), timeout=None if block else 0, return_when=FIRST_COMPLETED)
        for future in finished:
            frame, node = writing.pop(future)
            future.result()
            report(Progress(0.0, "rendering", message=f"frame {frame}", info={"frame": frame, "node": node}))

    def spawn() -> None:
        nonlocal spawned
        actor = Actor.options(**options).remote()
        actors.append(actor)
        spawned += 1
        pending[actor.info.remote()] = ("info", actor, None, None)

    def stop_all(graceful: bool) -> None:
        if graceful:
            try:
                ray.get([a.close.remote() for a, _ in ready_actors], timeout=30)
            except Exception:  # a worker that cannot clean up its scratch is killed all the same
                pass
        for a in actors:
            ray.kill(a)

    try:
        for _ in range(min(count, len(frames))):
            spawn()
        while todo or any(step == "frame" for step, *_ in pending.values()):
            written(block=len(writing) >= 4 * WRITE_THREADS)
            if cancel.is_set():
                raise Cancelled(f"cancelled with {len(writer.done_frames(root))} of {cfg.frames} frames done",
                                "re-run the same command to resume")
            while ready_actors and todo:
                actor, node = ready_actors.pop()
                frame = todo.popleft()
                pending[actor.render.remote(frame)] = ("frame", actor, node, frame)
            done, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            if not done:
                if time.monotonic() - last_event > STALL_S:
                    raise N2DError(f"no Ray worker slot ({options}) came up and no frame finished for {STALL_S:.0f} s",
                                   "check `ray status` on the head: the nodes must offer these resources")
                continue
            last_event = time.monotonic()
            ref = done[0]
            step, actor, node, frame = pending.pop(ref)
            try:
                value = ray.get(ref)
            except lost_errors as exc:
                actors.remove(actor)
                if frame is not None:
                    tries[frame] += 1
                    if tries[frame] >= FRAME_TRIES:
                        raise N2DError(f"frame {frame} was lost {tries[frame]} times, last on node "
                                       f"{node['node'] if node else '?'} ({type(exc).__name__})",
                                       "check the nodes' logs (`ray logs` on the head); re-run to resume") from None
                    todo.appendleft(frame)
                if spawned < 3 * count:
                    spawn()  # a replacement, which starts when the cluster has room for it
                continue
            except RayTaskError as exc:
                where = f"node {node['node']} ({node['host']})" if node else "a Ray worker"
                cause = exc.cause if isinstance(exc.cause, N2DError) else None
                if cause is not None:
                    raise type(cause)(f"{where}: {cause.message}", cause.hint) from None
                raise N2DError(f"{where} failed to {'render frame ' + str(frame) if frame is not None else step}: "
                               f"{exc.cause!r}", "check that node's n2d install (install.sh); re-run to resume"
                               ) from None
            if step == "info":
                check_node(value, engine)
                pending[actor.open.remote(models, job["config"], engine, threads)] = ("open", actor, value, None)
            elif step == "open":
                ready_actors.append((actor, node))
            else:
                ready_actors.append((actor, node))
                writing[pool.submit(write_frame_files, root, value)] = (frame, node["node"])
        while writing:
            written(block=True)
    except BaseException:
        stop_all(graceful=False)
        raise
    finally:
        pool.shutdown(wait=True)  # a frame being written is finished before the run stops
    stop_all(graceful=True)
