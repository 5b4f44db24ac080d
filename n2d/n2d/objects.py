"""Many objects at once: the pipeline of each object of a list, on this machine or on a Ray cluster (`n2d pipeline`).

Each object has its own run directory, `RUN_DIR/NAME` (the layout of n2d/pipeline.py), so each resumes from its own
run.json and stage outputs. An object enters as a run directory already there (its captures made by the Pipeline
action or `n2d pipeline` before) or as `NAME=SOURCE`: a capture session (n2d capture, n2d capture import) or a model
directory (n2d reconstruct, n2d model import), copied in as the run's capture/ or model/ before its first stage.
The stages run through `LibraryStages` (no ROS), so the capture stages are not among them.

Without a cluster the objects run one after another in this process. With one, each object's pipeline is one Ray
task that takes a whole node's worth of CPUs (the smallest node's; and a GPU where every node has one): its
dataset renders with local worker processes and its training takes the node's cores, as on one machine. The dataset
does not go through the cluster's frame actors from inside the task: on a small cluster the object tasks would hold
every CPU while waiting for frame actors that then find none. A node that dies takes its task with it; Ray runs the
task again elsewhere and it resumes from the run directory. The tasks read and write the run directories in place,
so RUN_DIR must be on a filesystem every node mounts at the same path (checked: a node that does not see RUN_DIR
fails its object with that message). A failing object (its error, or a lost task) is reported with its error and
the others finish; progress comes back per object.
"""

from __future__ import annotations

import secrets
import shutil
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from n2d.pipeline import (
    CAPTURE_STAGES,
    PipelineConfig,
    RunLayout,
    check_object_name,
    check_run_dir,
    check_stages,
    read_status,
    run_config,
    run_pipeline,
    stage_order,
)
from n2d_common import __version__
from n2d_common.contracts import atomic_write_text, read_manifest, write_manifest
from n2d_common.errors import Cancelled, ConfigError, ContractError, N2DError
from n2d_common.progress import Progress, ProgressFn

SOURCE_STAGES = {"capture_session": "capture", "model": "reconstruct"}
"""The stage whose output a source of each kind stands in for."""
MARKER = ".n2d_cluster_check"
"""A file the driver writes into RUN_DIR for the length of a cluster run: a node that cannot read it does not see
RUN_DIR."""
REPORT_EVERY_S = 0.5
"""A task sends its object's progress at most this often (and at each new stage)."""


@dataclass(frozen=True)
class ObjectRun:
    """One object of the list: its name and, optionally, the capture session or model its run starts from."""

    name: str
    source: Path | None = None
    given: str | None = None
    """The stage whose output `source` is (capture or reconstruct)."""


def parse_objects(text: str) -> list[ObjectRun]:
    """The objects of `NAME[=SOURCE],...`; ConfigError for an unusable or repeated name or a source that is not a
    finished capture session or model directory."""
    objects: list[ObjectRun] = []
    for item in text.split(","):
        name, sep, source = (part.strip() for part in item.partition("="))
        if not name:
            raise ConfigError(f"the object list {text!r} has an empty entry", "list objects as NAME[=SOURCE],...")
        check_object_name(name)
        if name in (o.name for o in objects):
            raise ConfigError(f"object {name} is listed twice", "list each object once (each has one run directory)")
        if not sep:
            objects.append(ObjectRun(name))
            continue
        path = Path(source).absolute()
        manifest = read_manifest(path) if path.is_dir() else None
        kind = manifest["kind"] if manifest else None
        if kind not in SOURCE_STAGES or not manifest.get("complete"):
            what = f"an unfinished {kind.replace('_', ' ')}" if kind in SOURCE_STAGES else "no capture session or model"
            raise ConfigError(f"the source {path} of object {name} is {what}",
                              "give a finished capture session (n2d capture) or model directory (n2d reconstruct, "
                              "n2d model import)")
        objects.append(ObjectRun(name, path, SOURCE_STAGES[kind]))
    return objects


def check_objects(root: Path, objects: list[ObjectRun], cfg: PipelineConfig, stages: list[str] | None) -> list[str]:
    """Check every object's run before anything is written; returns the stages to run (default: all but the
    captures). ConfigError or ContractError, the object named."""
    order = stage_order(stages, cfg) if stages else [s for s in cfg.stages() if s not in CAPTURE_STAGES]
    turntable = [s for s in order if s in CAPTURE_STAGES]
    if turntable:
        raise ConfigError(f"stage(s) {', '.join(turntable)} drive the turntable, which n2d pipeline does not",
                          "capture each object with the Pipeline action or n2d capture, then give the rest here")
    if root.exists() and not root.is_dir():
        raise ContractError(f"{root} is not a directory", "give the folder that holds one run directory per object")
    if read_manifest(root) is not None:
        raise ContractError(f"{root} is itself an n2d directory ({read_manifest(root)['kind']})",
                            "give the folder that holds one run directory per object (RUN_DIR/NAME)")
    for obj in objects:
        layout = RunLayout(root / obj.name)
        try:
            check_run_dir(layout.root, obj.name, cfg)
            if obj.source is None and not layout.root.is_dir():
                raise ConfigError(f"no run directory {layout.root} and no source",
                                  f"give it as {obj.name}=CAPTURE_SESSION_OR_MODEL_DIR, or check the name")
            status = read_status(layout, obj.name, fresh=False)
            check_stages(layout, cfg, order, status, given=(obj.given,) if obj.given else ())
        except N2DError as exc:
            raise type(exc)(f"object {obj.name}: {exc.message}", exc.hint) from None
    return order


def run_object(root: Path, obj: ObjectRun, cfg: PipelineConfig, order: list[str], progress: ProgressFn,
               cancel: threading.Event) -> dict:
    """One object's pipeline: its source copied in (once), then `order` through LibraryStages; returns run.json."""
    from n2d.local_stages import LibraryStages

    layout = RunLayout(root / obj.name)
    if obj.source is not None and not layout.done(obj.given, read_status(layout, obj.name, fresh=False)):
        check_run_dir(layout.root, obj.name, cfg)
        if read_manifest(layout.root) is None:
            write_manifest(layout.root, "run", config=run_config(obj.name, cfg), complete=False)
        target = layout.output(obj.given)
        copying = target.with_name(target.name + ".copying")
        shutil.rmtree(copying, ignore_errors=True)  # a copy stopped half way
        shutil.copytree(obj.source, copying)
        copying.rename(target)
    return run_pipeline(layout.root, obj.name, cfg, LibraryStages(), stages=order, progress=progress, cancel=cancel)


def run_isolated(root: Path, obj: ObjectRun, cfg: PipelineConfig, order: list[str], progress: ProgressFn,
                 cancel: threading.Event) -> dict:
    """`run_object`, its failure returned instead of raised: {name, ok, done: stages finished, run_dir} or
    {name, ok: False, error, hint}. A cancel still raises Cancelled."""
    base = {"name": obj.name, "run_dir": str(root / obj.name), "host": socket.gethostname()}
    try:
        status = run_object(root, obj, cfg, order, progress, cancel)
    except Cancelled:
        raise
    except N2DError as exc:
        copied = RunLayout(root / obj.name).output(obj.given) if obj.given else None
        again = (f"; {copied} is the copy of {obj.source}: fix the source, then delete the copy to take it in again"
                 if copied is not None and copied.is_dir() else "")
        return base | {"ok": False, "error": exc.message, "hint": exc.hint + again}
    except Exception as exc:  # an object's failure of any kind must not stop the others
        return base | {"ok": False, "error": f"{type(exc).__name__}: {exc}", "hint": "this is a bug in n2d; please "
                       "report it with the object's run directory"}
    return base | {"ok": True, "done": [s for s in order if s in status["stages"]]}


def _object_task(root: str, obj: ObjectRun, cfg: PipelineConfig, order: list[str], version: str, token: str,
                 board) -> dict:
    """An object's pipeline as a Ray task on a cluster node: checks the node (n2d version, RUN_DIR seen), then
    `run_isolated`, its progress sent to the driver through `board` (a Ray queue)."""
    import ray

    where = f"node {ray.util.get_node_ip_address()} ({socket.gethostname()})"
    run_root = Path(root)
    failure = {"name": obj.name, "run_dir": str(run_root / obj.name), "host": socket.gethostname(), "ok": False}
    if version != __version__:
        return failure | {"error": f"{where} runs n2d {__version__}, the driver n2d {version}",
                          "hint": "install the same n2d on every node (install.sh), then re-run to resume"}
    marker = run_root / MARKER
    if not marker.is_file() or marker.read_text() != token:
        return failure | {"error": f"{where} does not see the run directory {run_root}",
                          "hint": "put RUN_DIR on a filesystem every node mounts at the same path (NFS), or run "
                          "without --cluster"}
    last = [0.0, ""]

    def report(p: Progress) -> None:
        now = time.monotonic()
        if p.stage != last[1] or p.fraction >= 1.0 or now - last[0] >= REPORT_EVERY_S:
            last[:] = [now, p.stage]
            board.put((obj.name, p))

    return run_isolated(run_root, obj, cfg, order, report, threading.Event()) | {"host": where}


def _task_resources(cluster_nodes) -> dict:
    """A node's worth of CPUs for one object (the smallest node's), and a GPU where every node has one."""
    alive = [n for n in cluster_nodes if n.cpus >= 1]
    if not alive:
        raise N2DError("the Ray cluster has no node with a free CPU", "check `ray status` on the head")
    gpus = {"num_gpus": 1} if all(n.gpus >= 1 for n in alive) else {}
    return {"num_cpus": int(min(n.cpus for n in alive))} | gpus


def _run_on_cluster(ray, root: Path, objects: list[ObjectRun], cfg: PipelineConfig, order: list[str],
                    progress_for: Callable[[str], ProgressFn], cancel: threading.Event) -> list[dict]:
    from ray.util.queue import Empty, Queue

    from n2d_common.cluster import nodes

    resources = _task_resources(nodes(ray))
    token = secrets.token_hex(16)
    marker = root / MARKER
    atomic_write_text(marker, token)
    board = Queue(actor_options={"num_cpus": 0})
    task = ray.remote(_object_task).options(**resources, max_retries=2)
    refs = {task.remote(str(root), obj, cfg, order, __version__, token, board): obj for obj in objects}
    results: dict[str, dict] = {}

    def drain() -> None:
        while True:
            try:
                name, p = board.get_nowait()
            except Empty:
                return
            progress_for(name)(p)

    pending = list(refs)
    try:
        while pending:
            if cancel.is_set():
                raise Cancelled("the objects' pipelines were cancelled", "run the same command again to continue")
            done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            drain()
            for ref in done:
                obj = refs[ref]
                try:
                    results[obj.name] = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    results[obj.name] = {"name": obj.name, "run_dir": str(root / obj.name), "ok": False,
                                         "error": f"its task was lost on the cluster ({type(exc).__name__}: "
                                         f"{str(exc).splitlines()[0] if str(exc) else ''})",
                                         "hint": "check `ray status` on the head, then re-run the same command "
                                         "to resume"}
    finally:
        for ref in pending:  # Ctrl-C or a cancel: the run directories keep what is finished
            ray.cancel(ref, force=True)
        marker.unlink(missing_ok=True)
    return [results[o.name] for o in objects]


def run_objects(root: str | Path, objects: list[ObjectRun], cfg: PipelineConfig, *, stages: list[str] | None = None,
                cluster: str | None = None, progress_for: Callable[[str], ProgressFn] = lambda name: (lambda p: None),
                cancel: threading.Event | None = None) -> list[dict]:
    """Run the pipeline (or `stages`) of every object into `root/NAME`, one after another here or as tasks on the
    Ray cluster `cluster` (an address of n2d_common.cluster); returns one result per object (see `run_isolated`).
    Everything is checked, and the cluster reached, before anything is written; then an object's failure is its
    result, not an exception. `progress_for(name)` gives the ProgressFn of an object."""
    root = Path(root).absolute()
    cancel = cancel or threading.Event()
    order = check_objects(root, objects, cfg, stages)
    if not cluster:
        root.mkdir(parents=True, exist_ok=True)
        return [run_isolated(root, obj, cfg, order, progress_for(obj.name), cancel) for obj in objects]
    from n2d_common.cluster import connect

    with connect(cluster) as ray:
        root.mkdir(parents=True, exist_ok=True)
        return _run_on_cluster(ray, root, objects, cfg, order, progress_for, cancel)
