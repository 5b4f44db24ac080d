"""Fault campaign: kill, interrupt, corrupt, unplug and fill the disk under the real stages, then count.

    python benchmarks/faults.py [--trials 2] [--seed 0] [--only CLASS[,CLASS]] [--stages STAGE[,STAGE]] [--work DIR]
    python benchmarks/faults.py --soak [--soak-frames 1000] [--soak-node-seconds 3600] --work DIR

Small configs of the real stages, each run as a user runs it (`python -m n2d.cli dataset|train|reconstruct|
evaluate`; the capture sweep through `run_sweep`, the real driver and the emulated servo in another process, with
the rendered camera; the pipeline through `run_pipeline` in another process; dope_node as `n2d launch dope`
starts it), in fault classes of `--trials` seeded trials each:
- kill -9 / SIGINT: the stage's process group (the stage and its render or NeuS workers, as a power cut, the OOM
  killer or Ctrl-C in a terminal) at a random time within an uninterrupted run's duration, then the same command
  again. Recovered: it finishes with the uninterrupted run's result (dataset: every frame's files byte for
  byte; sweep: the same views at the same angles; DOPE training: the planned steps, from the checkpoint; fast
  reconstruction: the same models_info.json; NeuS: every planned step, the held-out radiance-field PSNR within
  0.5 dB and the diameter within 1 % (the notes count reruns bit for bit the uninterrupted network); pipeline: the
  run complete with the same model, dataset frames and training steps). Work lost: frames, views, checkpointed
  steps or finished pipeline stages that were finished at the kill and redone or missing after the rerun; steps
  done after the last checkpoint and done again are shown beside it. dope_node: killed mid-stream and started
  again, it must publish detections again with its model directory unchanged and no files left behind.
- corrupt input: an aimed corruption of the stage's input (`n2d_sim.corrupt`: truncated or garbage images, a
  JSON value of another type or a missing key, NaN/inf in poses and intrinsics, a mesh in millimetres or without
  faces, an ONNX model of another shape, another kind or a newer format in n2d.json). Clean: exit code 2 with one
  `n2d: error:` line and a hint, no traceback, nothing written.
- servo fault (no_reply, bad_crc, overload, disconnect, injected through the emulator's control socket at a
  random view) and a camera that stops publishing during a sweep: the sweep stops with a clean error, the fault
  is cleared (an overload by rebooting the servo, as its error says) and the same sweep resumes.
- full disk: the stage writes into a small tmpfs (a random fraction of the size of its uninterrupted output):
  clean error, no output that looks complete; the tmpfs is then enlarged and the same command resumes. Without
  the privilege to mount, RLIMIT_FSIZE on the writer stands in (a file may not grow past the limit: EFBIG),
  which the table says. (The dataset, DOPE training, fast reconstruction and sweep.)
One table: fault class, stage, trials, recovered, clean errors, work lost.

`--soak`: 1000 raster dataset frames in one render worker (its resident memory and open file descriptors sampled
every second: first / last / max, growth over the run) and `dope_node` on a 30 Hz stream for `--soak-node-seconds`
(default an hour): median latency and the node's CPU time per frame (user + system from /proc, which other jobs on
the cores do not change) of the first and the last minute, its memory and descriptors first / last / max.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from table import print_table

PY = sys.executable
CLI = [PY, "-m", "n2d.cli"]
HERE = Path(__file__).resolve()
SIZE = ["camera.width=160", "camera.height=120", "camera.focal_px=150"]
DATASET_SET = ["render.engine=raster", "scene.boards=0", *SIZE]
DATASET_FRAMES = 12
RECONSTRUCT_SET = [a for s in ("mesh.voxel_m=0.004", "mesh.target_faces=2000", "texture.size_px=128", "symmetry=none")
                   for a in ("--set", s)]
NEUS_SET = ["--neus-preset", "tiny"] + [a for s in (
    "neus.steps=40", "neus.checkpoint_every=10", "neus.progress_every=1", "neus.pretrain.steps=20",
    "neus.sampler.rays=128", "neus.optim.warmup_steps=10", "neus.optim.cos_anneal_steps=30", "mesh.voxel_m=0.006",
    "mesh.target_faces=1000", "texture.size_px=64", "symmetry=none") for a in ("--set", s)]
NEUS_PSNR_DB, NEUS_DIAMETER = 0.5, 0.01
"""Equivalence of a resumed NeuS run: held-out radiance-field PSNR within 0.5 dB, diameter within 1 %."""
PIPELINE_CONFIG = {
    "views": 12, "test_views": 0, "test_frames": 0, "require_empty_plate": False, "frames": 12, "preset": "tiny",
    "train_minutes": 0.0, "precisions": ["fp32"],
    "reconstruct": {"mesh": {"voxel_m": 0.004, "target_faces": 2000}, "texture": {"size_px": 128}, "symmetry": "none"},
    "dataset": {"render": {"engine": "raster"}, "scene": {"boards": 0}, "workers": 1,
                "camera": {"width": 160, "height": 120, "focal_px": 150.0}},
    "train": {"epochs": 3, "int8": False, "checkpoint_every_s": 0.5}}
"""The pipeline of the kill trials: the campaign's small stages in one run directory (the capture given)."""
SWEEP_VIEWS = 8
SESSION_VIEWS = 12
SERVO_FAULTS = ("no_reply", "bad_crc", "overload", "disconnect")
CLASSES = ("kill9", "sigint", "corrupt", "servo", "disk")
STAGES = ("dataset", "train", "reconstruct", "sweep", "neus", "pipeline", "node")
"""Stages of the kill trials (`--stages`); the full-disk class writes with the first four."""
DISK_STAGES = ("dataset", "train", "reconstruct", "sweep")


@dataclass
class Tally:
    """One row of the table."""

    fault: str
    stage: str
    trials: int = 0
    recovered: int = 0
    clean: int = 0
    lost: int = 0
    unit: str = ""
    redone: int = 0
    """Work done after the last checkpoint and done again (within the checkpoint interval: not lost)."""
    notes: list[str] = field(default_factory=list)


@dataclass
class Run:
    rc: int
    stdout: str
    stderr: str
    seconds: float


def _run(cmd: list[str], timeout_s: float = 600, env: dict | None = None, **kw) -> Run:
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env, **kw)
    return Run(proc.returncode, proc.stdout, proc.stderr, time.monotonic() - t0)


def clean_error(run: Run) -> bool:
    """Exit code 2, one `n2d: error:` line with a hint, no traceback."""
    lines = [ln for ln in run.stderr.splitlines() if ln.startswith("n2d: error:")]
    return (run.rc == 2 and len(lines) == 1 and "  hint: " in run.stderr and "Traceback" not in run.stderr)


def _interrupted(run: Run) -> bool:
    """A kill -9 ends without a word; Ctrl-C with the CLI's one line (exit 130) or a clean error."""
    return run.rc in (-signal.SIGKILL, 130) or clean_error(run) or "interrupted" in run.stderr


def tree_hashes(root: Path, under: str = "") -> dict[str, str]:
    """SHA-1 of every file below `root / under`, by relative path."""
    base = root / under
    return {str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(base.rglob("*")) if p.is_file()}


def _mtimes(root: Path, files: list[Path]) -> dict[str, int]:
    """Modification time of each of `files` that exists, by its path relative to `root`."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in files if p.is_file()}


def _partial(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


class Stage:
    """One stage under test: its command, what an interrupted run had finished, and how its result is judged."""

    name = ""
    unit = ""
    kill_by_progress = False
    """Kill at a random percentage of the stage's progress bar (5-95 %) instead of a random time within the
    uninterrupted run's duration (which varies with the other jobs on the cores)."""

    def __init__(self, work: Path):
        self.work = work

    def command(self, out: Path) -> list[str]:
        raise NotImplementedError

    def finished(self, out: Path) -> dict:
        """Work finished in the unfinished output of `out` (name -> mtime or step)."""
        return {}

    def lost(self, before: dict, out: Path, rerun: Run) -> int:
        """Of the work `finished` found, how much the rerun redid or lost."""
        return 0

    def redone(self, first: Run, before: dict) -> int:
        """Of the work the interrupted run `first` had done, how much came after its last checkpoint."""
        return 0

    def summary(self) -> list[str]:
        """Notes on the trials since the last call."""
        return []

    def same(self, out: Path, reference: Path) -> bool:
        raise NotImplementedError

    def looks_complete(self, out: Path) -> bool:
        """Whether `out` holds what a finished run leaves (a complete manifest)."""
        from n2d_common.contracts import read_manifest
        from n2d_common.errors import N2DError

        try:
            manifest = read_manifest(out) if out.is_dir() else None
        except N2DError:
            return False
        return bool(manifest and manifest.get("complete"))


class DatasetStage(Stage):
    name, unit = "dataset (raster)", "frames"

    def __init__(self, work: Path, model: Path):
        super().__init__(work)
        self.model = model

    def command(self, out: Path) -> list[str]:
        sets = [a for s in DATASET_SET for a in ("--set", s)]
        return CLI + ["dataset", str(self.model), str(out), "--frames", str(DATASET_FRAMES), "--workers", "1", *sets]

    def finished(self, out: Path) -> dict:
        root = _partial(out)
        done = [int(p.stem) for p in (root / "records").glob("*.json")]  # a frame's record is written last
        return _mtimes(root, [root / "train_pbr" / f"{i // 1000:06d}" / "rgb" / f"{i % 1000:06d}.jpg" for i in done])

    def lost(self, before: dict, out: Path, rerun: Run) -> int:
        after = _mtimes(out, sorted(out.glob("train_pbr/*/rgb/*.jpg")))
        return sum(after.get(name) != t for name, t in before.items())

    def same(self, out: Path, reference: Path) -> bool:
        return tree_hashes(out, "train_pbr") == tree_hashes(reference, "train_pbr")


class TrainStage(Stage):
    name, unit = "train (DOPE tiny)", "steps"

    def __init__(self, work: Path, dataset: Path):
        super().__init__(work)
        self.dataset = dataset

    def command(self, out: Path) -> list[str]:
        return CLI + ["train", str(self.dataset), str(out), "--backbone", "tiny", "--epochs", "3", "--set",
                      "int8=false", "--set", "checkpoint_every_s=0.5"]

    def finished(self, out: Path) -> dict:
        ckpt = _partial(out) / "checkpoint.pt"
        if not ckpt.is_file():
            return {"step": 0}
        from n2d_common.torch_utils import load_checkpoint

        return {"step": int(load_checkpoint(ckpt)["position"]["step"])}

    def lost(self, before: dict, out: Path, rerun: Run) -> int:
        trained = {int(s) for s in re.findall(r"step (\d+)/\d+", rerun.stderr)}  # the steps the rerun trained
        return sum(s <= before.get("step", 0) for s in trained)

    def same(self, out: Path, reference: Path) -> bool:
        run, ref = (json.loads((d / "training.json").read_text()) for d in (out, reference))
        return run["steps"] == ref["steps"] == run["planned_steps"] and (out / "model.onnx").is_file()


class ReconstructStage(Stage):
    name, unit = "reconstruct (fast)", "checkpoints"

    def __init__(self, work: Path, session: Path):
        super().__init__(work)
        self.session = session

    def command(self, out: Path, session: Path | None = None) -> list[str]:
        return CLI + ["reconstruct", str(session or self.session), str(out), "--method", "fast", *RECONSTRUCT_SET]

    def same(self, out: Path, reference: Path) -> bool:
        return (out / "models_info.json").read_text() == (reference / "models_info.json").read_text()


class SweepStage(Stage):
    """The object sweep of a capture: the real driver on the emulated servo, the rendered camera."""

    name, unit = "capture sweep", "views"

    def __init__(self, work: Path, link: str):
        super().__init__(work)
        self.link = link

    def command(self, out: Path, *more: str) -> list[str]:
        return [PY, str(HERE), "--child-sweep", str(out), "--port", self.link, *more]

    def finished(self, out: Path) -> dict:
        from n2d_capture.sweep import read_sweep

        return _mtimes(out, [out / v["file"] for v in read_sweep(out, "images")]) if out.is_dir() else {}

    def looks_complete(self, out: Path) -> bool:
        from n2d_capture.sweep import read_sweep

        return out.is_dir() and len(read_sweep(out, "images")) == SWEEP_VIEWS

    def lost(self, before: dict, out: Path, rerun: Run) -> int:
        after = _mtimes(out, sorted((out / "images").glob("*.png")))
        return sum(after.get(name) != t for name, t in before.items())

    def same(self, out: Path, reference: Path) -> bool:
        from n2d_capture.sweep import read_sweep

        views, ref = read_sweep(out, "images"), read_sweep(reference, "images")
        return ([v["angle_cmd_rad"] for v in views] == [v["angle_cmd_rad"] for v in ref]
                and all(abs(v["angle_rad"] - v["angle_cmd_rad"]) < 0.005 for v in views)
                and all((out / v["file"]).is_file() for v in views))


class NeusStage(ReconstructStage):
    """`n2d reconstruct --method neus` on the tiny preset, shortened to 40 steps with a checkpoint every 10."""

    name, unit = "reconstruct (NeuS tiny)", "steps"
    compared = identical = 0
    kill_by_progress = True

    def command(self, out: Path, session: Path | None = None) -> list[str]:
        return CLI + ["reconstruct", str(session or self.session), str(out), "--method", "neus", *NEUS_SET]

    def finished(self, out: Path) -> dict:
        from n2d_common.torch_utils import load_checkpoint
        from n2d_reconstruct.neus.trainer import CHECKPOINT

        ckpt = _partial(out) / CHECKPOINT
        if not _partial(out).is_dir():
            return {}  # nothing unfinished: the run had finished
        return {"step": int(load_checkpoint(ckpt)["step"])} if ckpt.is_file() else {"step": 0}

    def lost(self, before: dict, out: Path, rerun: Run) -> int:
        """Checkpointed steps the rerun trained again: it must start at the checkpoint's step."""
        start = re.findall(r"starting at step (\d+)/\d+", rerun.stderr)
        return max(0, before.get("step", 0) - int(start[0])) if start else 0

    def redone(self, first: Run, before: dict) -> int:
        reached = max((int(s) for s in re.findall(r"step (\d+)/\d+ loss", first.stderr)), default=0)
        return max(0, reached - before["step"]) if before else 0

    def same(self, out: Path, reference: Path) -> bool:
        """Equivalent: every planned step trained, the held-out radiance-field PSNR within NEUS_PSNR_DB and the
        diameter within NEUS_DIAMETER of the uninterrupted run's (identical when the resume is bit-exact)."""
        from n2d_common.torch_utils import load_checkpoint
        from n2d_reconstruct.neus.trainer import CHECKPOINT

        run, ref = (json.loads((d / "report.json").read_text()) for d in (out, reference))
        psnr = abs(run["heldout"]["field_psnr_db"] - ref["heldout"]["field_psnr_db"])
        diameter = abs(run["model"]["diameter_mm"] / ref["model"]["diameter_mm"] - 1)
        a, b = (load_checkpoint(d / CHECKPOINT) for d in (out, reference))
        self.compared += 1
        self.identical += all(bool((a["network"][k] == v).all()) for k, v in b["network"].items())
        return a["step"] == b["step"] and psnr <= NEUS_PSNR_DB and diameter <= NEUS_DIAMETER

    def summary(self) -> list[str]:
        compared, identical, self.compared, self.identical = self.compared, self.identical, 0, 0
        return [f"{identical} of {compared} reruns bit for bit the uninterrupted network"] if compared else []


class PipelineStage(Stage):
    """`run_pipeline` over one run directory: the given capture, then reconstruct, dataset, train and evaluate, each
    stage the library call its node makes for a goal (`n2d.local_stages.LibraryStages`, as `n2d pipeline` runs it), in
    a child process."""

    name, unit = "pipeline (run_pipeline)", "stages"
    outputs = ("capture", "model", "dataset", "dope")
    kept = 0
    kill_by_progress = True

    def __init__(self, work: Path, session: Path):
        super().__init__(work)
        self.session = session

    def command(self, out: Path) -> list[str]:
        return [PY, str(HERE), "--child-pipeline", str(out), "--session", str(self.session)]

    def finished(self, out: Path) -> dict:
        """The finished stages' outputs: the modification time of each complete manifest."""
        return _mtimes(out, [out / d / "n2d.json" for d in self.outputs if self.looks_complete(out / d)])

    def lost(self, before: dict, out: Path, rerun: Run) -> int:
        after = _mtimes(out, [out / d / "n2d.json" for d in self.outputs])
        self.kept += sum(after.get(name) == t for name, t in before.items()) - ("capture/n2d.json" in before)
        return sum(after.get(name) != t for name, t in before.items())

    def summary(self) -> list[str]:
        kept, self.kept = self.kept, 0
        return [f"{kept} stages finished at the kills (the given capture aside) and kept as they were"]

    def same(self, out: Path, reference: Path) -> bool:
        status = json.loads((out / "run.json").read_text())
        training = json.loads((out / "dope" / "training.json").read_text())
        return (self.looks_complete(out) and set(status["stages"]) == {"reconstruct", "dataset", "train",
                                                                              "evaluate"}
                and (out / "model" / "models_info.json").read_text()
                == (reference / "model" / "models_info.json").read_text()
                and tree_hashes(out / "dataset", "train_pbr") == tree_hashes(reference / "dataset", "train_pbr")
                and training["steps"] == training["planned_steps"])


def _default_sigint() -> None:
    """preexec_fn of a stage under test: Ctrl-C as in a terminal, even when the campaign runs in the background
    (where a shell starts it with SIGINT ignored, which its children inherit: a SIGINT trial would do nothing)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=_default_sigint)


class _Stderr:
    """The stderr of a running stage, read as it comes (its progress bar redraws without newlines)."""

    def __init__(self, proc: subprocess.Popen):
        import threading

        self.chunks: list[bytes] = []
        self.thread = threading.Thread(target=self._read, args=(proc.stderr.fileno(),), daemon=True)
        self.thread.start()

    def _read(self, fd: int) -> None:
        while chunk := os.read(fd, 4096):
            self.chunks.append(chunk)

    def text(self) -> str:
        return b"".join(self.chunks).decode(errors="replace")

    def percent(self) -> int:
        """The progress bar's last percentage."""
        found = re.findall(r"(\d+)%\|", b"".join(self.chunks[-8:]).decode(errors="replace"))
        return int(found[-1]) if found else 0


def _stop(proc: subprocess.Popen, sig: int, stderr: _Stderr | None = None) -> Run:
    """Send `sig` to the process group of `proc` (a terminal's Ctrl-C reaches the whole group) and wait."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
    try:
        _, err = proc.communicate(timeout=120) if stderr is None else (proc.wait(timeout=120), "")
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate() if stderr is None else (proc.wait(), "")
    if stderr is not None:
        stderr.thread.join(timeout=10)
        err = stderr.text()
    return Run(proc.returncode, "", err, 0.0)


def _again(stage: Stage, out: Path, first: Run) -> Run:
    """The same command again, unless the first run had finished before the fault reached it."""
    if first.rc == 0 or stage.looks_complete(out):
        return Run(0, "", "", 0.0)
    return _run(stage.command(out))


def kill_trials(stage: Stage, reference: Path, ref_s: float, sig: int, trials: int, rng: random.Random,
                tally: Tally) -> None:
    points = []
    for i in range(trials):
        out = stage.work / f"{re.sub(r'[^a-z0-9]+', '-', stage.name.lower()).strip('-')}-{sig}-{i}"
        proc = _start(stage.command(out))
        stderr = _Stderr(proc) if stage.kill_by_progress else None
        deadline, target = time.monotonic() + rng.uniform(0.25, 0.9) * ref_s, rng.uniform(5, 95)
        while proc.poll() is None and (stderr.percent() < target if stderr else time.monotonic() < deadline):
            time.sleep(0.05)
        first = _stop(proc, sig, stderr)
        if stderr is not None:
            points.append(f"{stderr.percent()} %" if first.rc != 0 else "finished")
        before = stage.finished(out)
        rerun = _again(stage, out, first)
        tally.trials += 1
        ok = rerun.rc == 0 and stage.same(out, reference)
        tally.recovered += ok
        tally.clean += _interrupted(first) or first.rc == 0
        tally.lost += stage.lost(before, out, rerun) if ok else len(before)
        tally.redone += stage.redone(first, before)
        if not ok:
            tally.notes.append(f"trial {i}: rerun exit {rerun.rc}: {rerun.stderr.strip().splitlines()[-1:]}")
    tally.notes += ([f"killed at {', '.join(points)} of the progress bar"] if points else []) + stage.summary()


def corrupt_trials(kind: str, valid: Path, command, work: Path, trials: int, rng: random.Random,
                   tally: Tally) -> None:
    """Run the stage that reads `kind` on corrupted copies of `valid`: a clean refusal or a finished run."""
    from n2d_sim import corrupt

    for i, aimed in enumerate(rng.sample(corrupt.CORRUPTIONS[kind], min(trials, len(corrupt.CORRUPTIONS[kind])))):
        d = work / f"corrupt-{kind}-{i}" / valid.name
        shutil.rmtree(d.parent, ignore_errors=True)
        corrupt.copy_tree(valid, d)
        what = aimed(d)
        out = d.parent / "out"
        run = _run(command(d, out))
        tally.trials += 1
        written = [p for p in (out, _partial(out)) if p.exists()]
        if clean_error(run) and not written:
            tally.clean += 1
        elif run.rc == 0:
            tally.recovered += 1  # a corruption the stage does not care about: it finishes
        else:
            tally.notes.append(f"{what}: exit {run.rc}, wrote {[p.name for p in written]}: "
                               f"{run.stderr.strip().splitlines()[-1:]}")


def sweep_fault_trials(stage: SweepStage, control, reference: Path, trials: int, rng: random.Random,
                       rows: dict) -> None:
    for fault in (*SERVO_FAULTS, "camera_silent"):
        tally = rows.setdefault(fault, Tally(f"servo {fault}" if fault != "camera_silent" else "camera silent",
                                             stage.name, unit="views"))
        for i in range(trials):
            out = stage.work / f"sweep-{fault}-{i}"
            at = rng.randrange(1, SWEEP_VIEWS - 1)
            if fault == "camera_silent":
                first = _run(stage.command(out, "--silent-after", str(at)))
            else:
                proc = _start(stage.command(out))
                while proc.poll() is None and len(stage.finished(out)) < at:
                    time.sleep(0.02)
                control.fault(fault)
                first = Run(*_wait(proc))
                control.fault("none")
            before = stage.finished(out)
            rerun = _run(stage.command(out, *(["--reboot"] if fault == "overload" else [])))
            if fault == "disconnect" and rerun.rc != 0:  # a port that came back under another name: plug in again
                rerun = _run(stage.command(out))
            tally.trials += 1
            ok = rerun.rc == 0 and stage.same(out, reference)
            tally.recovered += ok
            tally.clean += clean_error(first) or first.rc == 0  # a fault the driver retried through finishes
            tally.lost += stage.lost(before, out, rerun) if ok else len(before)
            if not ok or not (clean_error(first) or first.rc == 0):
                tally.notes.append(f"trial {i}: first exit {first.rc} {first.stderr.strip().splitlines()[-1:]}; "
                                   f"rerun exit {rerun.rc} {rerun.stderr.strip().splitlines()[-1:]}")


def _wait(proc: subprocess.Popen) -> tuple[int, str, str, float]:
    try:
        _, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        err += "\n(hung: killed after 180 s)"
    return proc.returncode, "", err, 0.0


class Disk:
    """A small filesystem for one writer: a tmpfs when this process may mount, else RLIMIT_FSIZE on the writer."""

    def __init__(self, path: Path, size_bytes: int):
        self.path, self.size = path, max(64 * 1024, size_bytes)
        path.mkdir(parents=True, exist_ok=True)
        self.tmpfs = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={self.size}", "tmpfs", str(path)],
                                    capture_output=True).returncode == 0
        self.mechanism = "tmpfs" if self.tmpfs else "RLIMIT_FSIZE"

    def limit(self):
        """preexec_fn of the writer (the RLIMIT_FSIZE stand-in)."""
        if self.tmpfs:
            return None
        size = self.size

        def apply():
            import resource

            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of being killed
            resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
        return apply

    def grow(self, size_bytes: int) -> None:
        if self.tmpfs:
            subprocess.run(["mount", "-o", f"remount,size={size_bytes}", str(self.path)], check=True)
        else:
            self.size = None

    def close(self) -> None:
        if self.tmpfs:
            subprocess.run(["umount", "-l", str(self.path)], capture_output=True)


def _du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def disk_trials(stage: Stage, reference: Path, trials: int, rng: random.Random, tally: Tally) -> None:
    need = _du(reference)
    for i in range(trials):
        disk = Disk(stage.work / f"disk-{stage.name.split()[0]}-{i}", int(rng.uniform(0.15, 0.85) * need))
        tally.notes = [n for n in tally.notes if not n.startswith("mechanism")] + [f"mechanism: {disk.mechanism}"]
        try:
            out = disk.path / "out"
            first = _run(stage.command(out), preexec_fn=disk.limit())
            looks_complete = stage.looks_complete(out)
            before = stage.finished(out)
            disk.grow(4 * need + (1 << 20))
            rerun = _again(stage, out, first)
            tally.trials += 1
            tally.clean += (clean_error(first) or first.rc == 0) and not (looks_complete and first.rc != 0)
            ok = rerun.rc == 0 and stage.same(out, reference)
            tally.recovered += ok
            tally.lost += stage.lost(before, out, rerun) if ok else len(before)
            if not ok or not clean_error(first):
                tally.notes.append(f"trial {i}: first exit {first.rc} {first.stderr.strip().splitlines()[-1:]}; "
                                   f"rerun exit {rerun.rc} {rerun.stderr.strip().splitlines()[-1:]}")
        finally:
            disk.close()


def child_sweep(args) -> int:
    """One object sweep into `args.child_sweep` (what the campaign kills and faults), errors as the CLI prints."""
    from n2d_capture.sweep import SweepConfig, run_sweep
    from n2d_capture.turntable import Turntable, TurntableConfig
    from n2d_common.errors import DeviceError
    from n2d_sim.camera import SimCamera
    from n2d_sim.frame_source import SimFrameSource
    from n2d_sim.world import SimWorldConfig

    class Silent:
        """A camera driver that stops publishing after `n` frames: grabs wait out their timeout, as
        RosFrameSource does when no fresh image arrives, and fail the same way."""

        def __init__(self, source, n):
            self.source, self.n, self.grabs = source, n, 0

        def grab(self, after_s, timeout_s):
            self.grabs += 1
            if self.grabs > self.n + 1:  # +1: the sweep's first grab only waits for the camera to be up
                time.sleep(timeout_s)
                raise DeviceError(f"no fresh image on /n2d/camera/image_raw within {timeout_s:.0f} s",
                                  "check the camera driver; the views taken are kept")
            return self.source.grab(after_s, timeout_s)

    world = SimWorldConfig(width=160, height=120, focal_px=150.0, samples=2, background_samples=2, clutter=False)
    cfg = SweepConfig(views=SWEEP_VIEWS, frame_timeout_s=2.0)
    table_cfg = TurntableConfig(port=args.port, velocity_limit_rad_s=6.0, acceleration_rad_s2=30.0,
                                settle_time_s=0.02, retries=2)
    out = Path(args.child_sweep)
    out.mkdir(parents=True, exist_ok=True)

    def sweep() -> None:
        from n2d_sim.servo import ServoControl

        control = ServoControl(args.control)
        table = Turntable(table_cfg)
        try:
            table.open()
        except DeviceError:
            if not args.reboot:
                raise
            table.reboot()  # what the overload's hint says; reboot works on a turntable whose open() failed
        with SimCamera(world) as camera, table:
            source = SimFrameSource(camera, lambda: control.state()["plate_rad"])
            run_sweep(out, "images", cfg, table, Silent(source, args.silent_after) if args.silent_after else source)

    return _as_cli(sweep)


def _as_cli(job) -> int:
    """Run `job()` and end as the `n2d` command ends: errors as one line and a hint (exit 2), Ctrl-C exit 130."""
    from n2d_common.errors import N2DError

    try:
        job()
    except N2DError as exc:
        print(f"n2d: error: {exc.message}", file=sys.stderr)
        print(f"  hint: {exc.hint}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"n2d: error: {exc.strerror or exc}", file=sys.stderr)
        print("  hint: check free disk space and permissions; finished work is kept", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("n2d: interrupted; finished work is kept and the same command resumes it", file=sys.stderr)
        return 130
    return 0


def child_pipeline(args) -> int:
    """The pipeline into the run directory `args.child_pipeline` (what the campaign kills): the run's manifest and
    its capture stage as an earlier call leaves them (the session copied in), then `run_pipeline` as the node runs
    it, its progress on stderr."""
    import threading

    from n2d.cli import _progress_bar
    from n2d.local_stages import LibraryStages
    from n2d.pipeline import PipelineConfig, run_pipeline
    from n2d_common.config import from_dict, to_dict
    from n2d_common.contracts import read_manifest, write_manifest

    run = Path(args.child_pipeline)
    cfg = from_dict(PipelineConfig, PIPELINE_CONFIG, "pipeline")
    cancel = threading.Event()

    def pipeline() -> None:
        if not run.is_dir() or read_manifest(run) is None:
            write_manifest(run, "run", config={"object_name": "box", **to_dict(cfg)}, complete=False)
        if not (run / "capture").is_dir():
            copy = run / "capture.copying"
            shutil.rmtree(copy, ignore_errors=True)
            shutil.copytree(args.session, copy)
            copy.rename(run / "capture")
        try:
            run_pipeline(run, "box", cfg, LibraryStages(), progress=_progress_bar("pipeline"), cancel=cancel)
        except KeyboardInterrupt:
            cancel.set()
            raise

    return _as_cli(pipeline)


def _replay(dataset: Path, frames: int = 30) -> list:
    """(rgb, K) of the first `frames` frames of `dataset`, for a replay to dope_node."""
    from n2d_dope.data import open_dataset, read_rgb

    replay = []
    for frame in open_dataset(dataset).frames[:frames]:
        camera = json.loads((frame.chunk / "scene_camera.json").read_text())[str(frame.frame_id)]
        replay.append((read_rgb(frame.image), np.array(camera["cam_K"], dtype=float).reshape(3, 3)))
    return replay


class Replay:
    """A camera driver replaying frames at 30 Hz with fresh stamps, and the arrival times of dope_node's
    detection messages (one per frame it processed)."""

    def __init__(self, node, frames: list):
        import threading

        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image
        from vision_msgs.msg import Detection3DArray

        from n2d_common.ros import PUBLISH_QOS

        self.frames, self.arrivals, self.latencies, self.stop = frames, [], [], threading.Event()
        node.create_subscription(Detection3DArray, "/n2d/dope/detections", self._received,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.image_pub = node.create_publisher(Image, "/n2d/camera/image_raw", PUBLISH_QOS)
        self.info_pub = node.create_publisher(CameraInfo, "/n2d/camera/camera_info", PUBLISH_QOS)
        self.thread = threading.Thread(target=self._publish, daemon=True)
        self.thread.start()

    def _received(self, msg) -> None:
        from n2d_common.ros import stamp_seconds

        self.latencies.append(time.time() - stamp_seconds(msg.header.stamp))
        self.arrivals.append(time.monotonic())

    def _publish(self) -> None:
        from n2d_common.ros import camera_info_msg, image_msg, stamp_msg

        i, t0 = 0, time.monotonic()
        while not self.stop.is_set():
            rgb, K = self.frames[i % len(self.frames)]
            stamp = stamp_msg(time.time())
            self.info_pub.publish(camera_info_msg(K, rgb.shape[1], rgb.shape[0], stamp, "camera"))
            self.image_pub.publish(image_msg(rgb, "rgb8", stamp, "camera"))
            i += 1
            time.sleep(max(0.0, t0 + i / 30.0 - time.monotonic()))

    def wait(self, since: float, count: int, timeout_s: float) -> float | None:
        """Seconds from `since` (monotonic) to the `count`-th detection message after it, None at the timeout."""
        while time.monotonic() < since + timeout_s:
            after = [t for t in self.arrivals if t > since]
            if len(after) >= count:
                return after[count - 1] - since
            time.sleep(0.05)
        return None


ORT_SESSION_FILE = ".ses"
"""ONNX Runtime's session-id file in TMPDIR: written by every run, killed or stopped cleanly, and reused."""


def _shm_files(pid: int) -> set[Path]:
    """The shared-memory files (/dev/shm) process `pid` has mapped: Fast DDS's segments and ports."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text().splitlines()
    except OSError:
        return set()
    return {Path(ln.split()[-1]) for ln in maps if ln.split()[-1].startswith("/dev/shm/")}


def node_trials(model: Path, frames: list, sig: int, trials: int, rng: random.Random, work: Path,
                tally: Tally) -> None:
    """dope_node (started as `n2d launch dope` starts it) on a 30 Hz replay, killed with `sig` a random 0.5-3 s
    after its first detections, then started again. Recovered: it publishes detections again, the model directory
    is byte for byte as before and the node's temporary directory holds nothing but ONNX Runtime's session-id file;
    the stopped process's own Fast DDS segment files (those it mapped that were new at its start; not the shared
    port files) still in /dev/shm after the restarted node stopped are counted in the notes."""
    from n2d.launch_description import load
    from n2d.launcher import Launch
    from n2d_common.ros import background_node

    domain = 89 + os.getpid() % 4  # outside the tests' 1..88 (tests/conftest.py)
    model_before, logs, stale, tracked, recover_s = tree_hashes(model), [], 0, 0, []
    with background_node("faults_camera", domain) as node:
        replay = Replay(node, frames)
        try:
            for i in range(trials):
                tmp = work / f"node-{sig}-{i}-tmp"
                shutil.rmtree(tmp, ignore_errors=True)
                tmp.mkdir(parents=True)
                env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "TMPDIR": str(tmp)}
                existing = set(Path("/dev/shm").iterdir())
                with Launch(load("dope"), {"models": str(model)}, env=env, log=logs.append) as launch:
                    up = replay.wait(time.monotonic(), 5, 180)
                    time.sleep(rng.uniform(0.5, 3.0))
                    proc = launch.procs["dope"]
                    segments = {f for f in _shm_files(proc.pid) - existing  # its own segments and their locks
                                if not f.name.startswith("fastrtps_port")}  # the port files are shared, reused
                    segments |= {f.with_name(f.name + "_el") for f in segments if Path(f"{f}_el").exists()}
                    os.killpg(proc.pid, sig)
                    try:
                        rc = proc.wait(30)
                    except subprocess.TimeoutExpired:
                        rc = None
                restart = time.monotonic()
                with Launch(load("dope"), {"models": str(model)}, env=env, log=logs.append):
                    back = replay.wait(restart, 5, 180)
                time.sleep(1.0)
                left = [p.name for p in tmp.iterdir() if p.name != ORT_SESSION_FILE]
                stale, tracked = stale + sum(p.exists() for p in segments), tracked + len(segments)
                tally.trials += 1
                ok = up is not None and back is not None and tree_hashes(model) == model_before and not left
                tally.recovered += ok
                tally.clean += rc == (-signal.SIGKILL if sig == signal.SIGKILL else 0)
                if back is not None:
                    recover_s.append(back)
                if not ok or rc != (-signal.SIGKILL if sig == signal.SIGKILL else 0):
                    tally.notes.append(f"trial {i}: exit {rc}, up {up}, back {back}, left {left[:3]}; {logs[-1:]}")
                shutil.rmtree(tmp, ignore_errors=True)
        finally:
            replay.stop.set()
            replay.thread.join(timeout=5)
    again = f"detections again {min(recover_s):.1f}-{max(recover_s):.1f} s after the restart, " if recover_s else ""
    tally.notes.append(f"{again}{stale} of its {tracked} shared-memory segment files left in /dev/shm")


def _emulator(tmp: Path):
    from n2d_sim.servo import ServoControl

    link, control = tmp / "ttyDXL", tmp / "ctl"
    log = open(tmp / "servo.log", "w")
    proc = subprocess.Popen([PY, "-m", "n2d_sim.servo", "--link", str(link), "--control", str(control)],
                            stdout=log, stderr=subprocess.STDOUT)
    ctl = ServoControl(control)
    ctl.wait_ready(timeout_s=20)
    return proc, str(link), ctl, str(control)


def campaign(args) -> list[Tally]:
    from n2d_sim.objects import sample_object_dir
    from n2d_sim.session import render_session, small_world

    rng = random.Random(args.seed)
    only = set(args.only.split(",")) if args.only else set(CLASSES)
    chosen = set(args.stages.split(",")) if args.stages else set(STAGES)
    work = Path(args.work or tempfile.mkdtemp(prefix="n2d-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    rows: list[Tally] = []
    model = sample_object_dir("box")
    session = work / "session"
    if not session.exists():
        render_session(session, small_world("box", 160, 120), views=SESSION_VIEWS)
    ds = work / "ref-dataset"
    stages: dict[str, Stage] = {"dataset": DatasetStage(work, model), "train": TrainStage(work, ds),
                                "reconstruct": ReconstructStage(work, session), "neus": NeusStage(work, session),
                                "pipeline": PipelineStage(work, session)}
    needed = chosen | ({"dataset", "train", "reconstruct"} if "corrupt" in only else set())
    needed |= {"dataset", "train"} if needed & {"train", "node"} else set()  # the node runs the trained model
    refs = {name: (work / f"ref-{name}", _reference(stage, work / f"ref-{name}"))
            for name, stage in stages.items() if name in needed}
    stages = {name: stage for name, stage in stages.items() if name in chosen}
    servo = "sweep" in chosen and only & {"kill9", "sigint", "servo", "disk"}
    if servo:
        servo_tmp = Path(tempfile.mkdtemp(prefix="n2d-servo-", dir="/tmp"))  # short: AF_UNIX names are limited
        emulator, link, control, control_path = _emulator(servo_tmp)
    try:
        if servo:
            sweep = SweepStage(work, link)
            sweep.command = (lambda f: lambda out, *more: f(out, "--control", control_path, *more))(sweep.command)
            stages["sweep"] = sweep
            refs["sweep"] = (work / "ref-sweep", _reference(sweep, work / "ref-sweep"))
        for cls, sig in (("kill9", signal.SIGKILL), ("sigint", signal.SIGINT)):
            if cls in only:
                label = "kill -9" if cls == "kill9" else "SIGINT"
                for name, stage in stages.items():
                    tally = Tally(label, stage.name, unit=stage.unit)
                    kill_trials(stage, refs[name][0], refs[name][1], sig, args.trials, rng, tally)
                    rows.append(tally)
                if "node" in chosen:
                    tally = Tally(label, "dope_node (live stream)")
                    node_trials(refs["train"][0], _replay(ds), sig, args.trials, rng, work, tally)
                    rows.append(tally)
        if "corrupt" in only:
            eval_dope = refs["train"][0]
            reconstruct = ReconstructStage(work, session)
            for kind, stage_name, command in (
                    ("capture_session", "reconstruct", lambda d, out: reconstruct.command(out, d)),
                    ("model", "dataset", lambda d, out: CLI + ["dataset", str(d), str(out), "--frames", "2",
                                                               "--workers", "1",
                                                               *[a for s in DATASET_SET for a in ("--set", s)]]),
                    ("dataset", "train", lambda d, out: CLI + ["train", str(d), str(out), "--backbone", "tiny",
                                                               "--epochs", "1", "--set", "int8=false"]),
                    ("dope_model", "evaluate", lambda d, out: CLI + ["evaluate", str(d), str(ds), "--frames", "2"])):
                valid = {"capture_session": session, "model": model, "dataset": ds, "dope_model": eval_dope}[kind]
                tally = Tally("corrupt input", f"{stage_name} (reads a {kind.replace('_', ' ')})")
                corrupt_trials(kind, valid, command, work, args.trials * 2, rng, tally)
                rows.append(tally)
        if "servo" in only and servo:
            faults: dict[str, Tally] = {}
            sweep_fault_trials(stages["sweep"], control, refs["sweep"][0], args.trials, rng, faults)
            rows += list(faults.values())
        if "disk" in only:
            for name, stage in stages.items():
                if name in DISK_STAGES:
                    tally = Tally("full disk", stage.name, unit=stage.unit)
                    disk_trials(stage, refs[name][0], args.trials, rng, tally)
                    rows.append(tally)
    finally:
        if servo:
            emulator.terminate()
            emulator.wait(timeout=10)
            shutil.rmtree(servo_tmp, ignore_errors=True)
    return rows


def _reference(stage: Stage, out: Path) -> float:
    """Run the stage uninterrupted into `out` (kept from an earlier campaign in --work); its wall time."""
    stamp = out.with_name(out.name + ".seconds")
    if out.exists() and stamp.is_file():
        return float(stamp.read_text())
    shutil.rmtree(out, ignore_errors=True)
    run = _run(stage.command(out))
    if run.rc != 0:
        raise SystemExit(f"the uninterrupted {stage.name} failed (exit {run.rc}):\n{run.stderr[-3000:]}")
    stamp.write_text(f"{run.seconds:.2f}")
    return run.seconds


def print_campaign(rows: list[Tally], seconds: float) -> None:
    table = []
    notes = any(r.notes for r in rows)
    for r in rows:
        lost = f"{r.lost} {r.unit}".strip() if r.unit else "-"
        if r.redone:
            lost += f" ({r.redone} done after the last checkpoint, done again)"
        table.append((r.fault, r.stage, str(r.trials), str(r.recovered), str(r.clean), lost)
                     + (("; ".join(r.notes[:3]),) if notes else ()))
    print_table(f"Fault campaign ({seconds:.0f} s): recovered = the same command afterwards gives the uninterrupted "
                "result; clean errors = exit 2 with one error line and a hint (or the CLI's interrupted line)",
                table, ("fault class", "stage", "trials", "recovered", "clean errors", "work lost")
                + (("notes",) if notes else ()))
    trials = sum(r.trials for r in rows)
    ok = sum(r.recovered + r.clean if r.fault == "corrupt input" else r.recovered for r in rows)
    lost = sum(r.lost for r in rows)
    print_table("Fault campaign, in all", [
        ("trials", str(trials), "", ""),
        ("recovered or cleanly refused", f"{ok}/{trials}", "100 %", "met" if ok == trials else "not met"),
        ("work lost (frames, views, steps)", str(lost), "0", "met" if lost == 0 else "not met")],
        ("metric", "value", "goal", "met"))


def _proc_stats(pid: int) -> tuple[float, int] | None:
    """(resident memory in MB, open file descriptors) of process `pid`, None once it is gone."""
    try:
        rss_kb = next(int(ln.split()[1]) for ln in Path(f"/proc/{pid}/status").read_text().splitlines()
                      if ln.startswith("VmRSS:"))
        return rss_kb / 1024, len(os.listdir(f"/proc/{pid}/fd"))
    except (OSError, StopIteration):
        return None


def _descendants(pid: int) -> list[int]:
    """The processes below `pid` (from /proc's parent links), children first."""
    parents = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parents[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    out, todo = [], [pid]
    while todo:
        parent = todo.pop(0)
        kids = [c for c, p in parents.items() if p == parent]
        out += kids
        todo += kids
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _flat_rows(label: str, samples: list[tuple[float, int]], warm: int) -> list[tuple]:
    rss, fds = [s[0] for s in samples[warm:]], [s[1] for s in samples[warm:]]
    growth = 100 * (rss[-1] - rss[0]) / rss[0]
    return [(f"{label}: resident memory first / last / max", f"{rss[0]:.0f} / {rss[-1]:.0f} / {max(rss):.0f} MB",
             f"growth {growth:+.1f} %", "<= 5 %", "met" if growth <= 5 else "not met"),
            (f"{label}: open file descriptors first / last / max", f"{fds[0]} / {fds[-1]} / {max(fds)}", "",
             "flat", "met" if fds[-1] <= fds[0] else "not met")]


def soak_dataset(frames: int, work: Path) -> list[tuple]:
    """`frames` raster frames in one render worker, its memory and descriptors sampled every second."""
    from n2d_sim.objects import sample_object_dir

    out = work / "soak-dataset"
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(_partial(out), ignore_errors=True)
    cmd = DatasetStage(work, sample_object_dir("box")).command(out)
    cmd[cmd.index("--frames") + 1] = str(frames)
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    samples, done_at = [], []
    while proc.poll() is None:
        workers = [p for p in _descendants(proc.pid) if "multiprocessing" in _cmdline(p)
                   and "resource_tracker" not in _cmdline(p)]
        stats = _proc_stats(workers[0]) if workers else None
        if stats is not None:
            samples.append(stats)
            done_at.append(len(list((_partial(out) / "records").glob("*.json"))))
        time.sleep(1.0)
    if proc.returncode != 0 or not samples:
        return [("dataset soak", f"failed (exit {proc.returncode})", "", "", "not met")]
    warm = next((i for i, d in enumerate(done_at) if d >= 10), 0)  # imports, the model and the first frames
    rows = _flat_rows(f"render worker, {frames} raster frames (from frame {done_at[warm]})", samples, warm)
    rows.append(("dataset soak: wall time", f"{time.monotonic() - t0:.0f} s", f"{len(samples)} samples", "", ""))
    return rows


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of process `pid` so far (from /proc/PID/stat), None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _window(samples: list[tuple], arrivals: np.ndarray, latency: np.ndarray, lo: float, hi: float) -> tuple:
    """Median latency (ms) and CPU time per frame (ms) of the node between monotonic times `lo` and `hi`."""
    inside = (arrivals >= lo) & (arrivals <= hi)
    times = np.array([t for t, *_ in samples])
    cpu = [samples[int(np.argmin(np.abs(times - t)))][1] for t in (lo, hi)]
    return float(np.median(latency[inside])), 1000 * (cpu[1] - cpu[0]) / max(int(inside.sum()), 1)


def soak_node(seconds: float, work: Path) -> list[tuple]:
    """dope_node for `seconds` on a 30 Hz replay of dataset frames: median latency and CPU time per frame (the
    node process's user + system time over the frames it processed: what other jobs on the cores do not change)
    of the first and the last minute, and the node's memory and descriptors sampled every second."""
    from n2d.launch_description import load
    from n2d.launcher import Launch
    from n2d_common.ros import background_node

    domain, logs, samples = 93 + os.getpid() % 4, [], []  # outside the tests' 1..88
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain)}
    with background_node("soak_camera", domain) as node:
        replay = Replay(node, _replay(work / "ref-dataset"))
        try:
            with Launch(load("dope"), {"models": str(work / "ref-train")}, env=env, log=logs.append) as launch:
                proc = launch.procs["dope"]
                if replay.wait(time.monotonic(), 5, 180) is None:
                    return [("dope_node soak", "no detections within 180 s", "; ".join(logs[-3:]), "", "not met")]
                time.sleep(3.0)  # the first frames
                t0 = time.monotonic()
                while time.monotonic() - t0 < seconds and proc.poll() is None:
                    cpu, stats = _cpu_seconds(proc.pid), _proc_stats(proc.pid)
                    if cpu is not None and stats is not None:
                        samples.append((time.monotonic(), cpu, *stats))
                    time.sleep(1.0)
        finally:
            replay.stop.set()
            replay.thread.join(timeout=5)
    if proc.returncode not in (None, 0) or len(samples) < 10:
        return [("dope_node soak", f"the node ended (exit {proc.returncode})", "; ".join(logs[-3:]), "", "not met")]
    arrivals, latency = np.array(replay.arrivals), 1000 * np.array(replay.latencies)
    start, end = samples[0][0], samples[-1][0]
    minute = min(60.0, (end - start) / 3)
    (lat0, cpu0), (lat1, cpu1) = (_window(samples, arrivals, latency, lo, lo + minute) for lo in (start, end - minute))
    inside = (arrivals >= start) & (arrivals <= end)
    fps = inside.sum() / (end - start)
    drift, cpu_drift = 100 * (lat1 - lat0) / lat0, 100 * (cpu1 - cpu0) / cpu0
    rows = [(f"dope_node {seconds / 60:.0f} min on a 30 Hz replay: median latency first / last {minute:.0f} s",
             f"{lat0:.1f} / {lat1:.1f} ms", f"drift {drift:+.1f} %, {fps:.1f} FPS out", "within 10 %",
             "met" if abs(drift) <= 10 else "not met"),
            (f"dope_node: CPU time per frame (user + system) first / last {minute:.0f} s",
             f"{cpu0:.1f} / {cpu1:.1f} ms", f"drift {cpu_drift:+.1f} %", "within 10 %",
             "met" if abs(cpu_drift) <= 10 else "not met")]
    return rows + _flat_rows("dope_node", [(rss, fds) for _, _, rss, fds in samples], 0)


def soak(args) -> None:
    work = Path(args.work or tempfile.mkdtemp(prefix="n2d-faults-"))
    rows = soak_dataset(args.soak_frames, work) if args.soak_frames > 0 else []
    if args.soak_node_seconds > 0:
        from n2d_sim.objects import sample_object_dir

        ds = work / "ref-dataset"  # the campaign's dataset and tiny DOPE model (kept in --work, else made here)
        _reference(DatasetStage(work, sample_object_dir("box")), ds)
        _reference(TrainStage(work, ds), work / "ref-train")
        rows += soak_node(args.soak_node_seconds, work)
    print_table("Soak", rows, ("metric", "value", "note", "goal", "met"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=2, help="seeded trials per fault class and stage")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", help=f"fault classes, comma-separated: {', '.join(CLASSES)}")
    parser.add_argument("--stages", help=f"stages, comma-separated: {', '.join(STAGES)} (default: all)")
    parser.add_argument("--work", type=Path, help="work directory (kept; its uninterrupted runs are reused)")
    parser.add_argument("--soak", action="store_true", help="the soak instead of the campaign")
    parser.add_argument("--soak-frames", type=int, default=1000)
    parser.add_argument("--soak-node-seconds", type=float, default=3600.0,
                        help="dope_node's run on the stream (default: an hour)")
    parser.add_argument("--child-sweep", help=argparse.SUPPRESS)
    parser.add_argument("--child-pipeline", help=argparse.SUPPRESS)
    parser.add_argument("--session", help=argparse.SUPPRESS)
    parser.add_argument("--port", help=argparse.SUPPRESS)
    parser.add_argument("--control", help=argparse.SUPPRESS)
    parser.add_argument("--silent-after", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--reboot", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_sweep:
        return child_sweep(args)
    if args.child_pipeline:
        return child_pipeline(args)
    t0 = time.monotonic()
    if args.soak:
        soak(args)
        return 0
    rows = campaign(args)
    print_campaign(rows, time.monotonic() - t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
