"""Fault campaign: kill, interrupt, corrupt, unplug and fill the disk under the real stages, then count.

    python benchmarks/faults.py [--trials 2] [--seed 0] [--only CLASS[,CLASS]] [--work DIR]
    python benchmarks/faults.py --soak [--soak-frames 1000] [--soak-node-seconds 300]

Small configs of the real stages, each run as a user runs it (`python -m n2d.cli dataset|train|reconstruct|
evaluate`; the capture sweep through `run_sweep`, the real driver and the emulated servo in another process, with
the rendered camera), in fault classes of `--trials` seeded trials each:
- kill -9 / SIGINT: the stage's process group (the stage and its render or NeuS workers, as a power cut, the OOM
  killer or Ctrl-C in a terminal) at a random time within an uninterrupted run's duration, then the same command
  again. Recovered: it finishes with the uninterrupted run's result (dataset: every frame's files byte for
  byte; sweep: the same views at the same angles; training: the planned steps, from the checkpoint; fast
  reconstruction: the same models_info.json). Work lost: frames, views or checkpointed steps that were finished
  at the kill and redone or missing after the rerun.
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
  which the table says.
One table: fault class, stage, trials, recovered, clean errors, work lost.

`--soak`: 1000 raster dataset frames in one render worker (its resident memory and open file descriptors sampled
every second: first / last / max, growth over the run) and `dope_node` on a stream for `--soak-node-seconds`
(latency of the first and the last minute).
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

from table import print_table

PY = sys.executable
CLI = [PY, "-m", "n2d.cli"]
HERE = Path(__file__).resolve()
SIZE = ["camera.width=160", "camera.height=120", "camera.focal_px=150"]
DATASET_SET = ["render.engine=raster", "scene.boards=0", *SIZE]
DATASET_FRAMES = 12
RECONSTRUCT_SET = [a for s in ("mesh.voxel_m=0.004", "mesh.target_faces=2000", "texture.size_px=128", "symmetry=none")
                   for a in ("--set", s)]
SWEEP_VIEWS = 8
SESSION_VIEWS = 12
SERVO_FAULTS = ("no_reply", "bad_crc", "overload", "disconnect")
CLASSES = ("kill9", "sigint", "corrupt", "servo", "disk")


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


def _start(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _stop(proc: subprocess.Popen, sig: int) -> Run:
    """Send `sig` to the process group of `proc` (a terminal's Ctrl-C reaches the whole group) and wait."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
    return Run(proc.returncode, "", err, 0.0)


def _again(stage: Stage, out: Path, first: Run) -> Run:
    """The same command again, unless the first run had finished before the fault reached it."""
    if first.rc == 0 or stage.looks_complete(out):
        return Run(0, "", "", 0.0)
    return _run(stage.command(out))


def kill_trials(stage: Stage, reference: Path, ref_s: float, sig: int, trials: int, rng: random.Random,
                tally: Tally) -> None:
    for i in range(trials):
        out = stage.work / f"{stage.name.split()[0]}-{sig}-{i}"
        proc = _start(stage.command(out))
        deadline = time.monotonic() + rng.uniform(0.25, 0.9) * ref_s
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        first = _stop(proc, sig)
        before = stage.finished(out)
        rerun = _again(stage, out, first)
        tally.trials += 1
        ok = rerun.rc == 0 and stage.same(out, reference)
        tally.recovered += ok
        tally.clean += _interrupted(first) or first.rc == 0
        tally.lost += stage.lost(before, out, rerun) if ok else len(before)
        if not ok:
            tally.notes.append(f"trial {i}: rerun exit {rerun.rc}: {rerun.stderr.strip().splitlines()[-1:]}")


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
    from n2d_common.errors import DeviceError, N2DError
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
    try:
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
    work = Path(args.work or tempfile.mkdtemp(prefix="n2d-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    rows: list[Tally] = []
    model = sample_object_dir("box")
    session = work / "session"
    if not session.exists():
        render_session(session, small_world("box", 160, 120), views=SESSION_VIEWS)
    refs = {}
    stages: dict[str, Stage] = {"dataset": DatasetStage(work, model)}
    ds = work / "ref-dataset"
    refs["dataset"] = (ds, _reference(stages["dataset"], ds))
    stages["train"] = TrainStage(work, ds)
    stages["reconstruct"] = ReconstructStage(work, session)
    for name in ("train", "reconstruct"):
        refs[name] = (work / f"ref-{name}", _reference(stages[name], work / f"ref-{name}"))
    servo_tmp = Path(tempfile.mkdtemp(prefix="n2d-servo-", dir="/tmp"))  # short: AF_UNIX names are limited
    emulator, link, control, control_path = _emulator(servo_tmp)
    try:
        sweep = SweepStage(work, link)
        sweep.command = (lambda f: lambda out, *more: f(out, "--control", control_path, *more))(sweep.command)
        stages["sweep"] = sweep
        refs["sweep"] = (work / "ref-sweep", _reference(sweep, work / "ref-sweep"))
        for cls, sig in (("kill9", signal.SIGKILL), ("sigint", signal.SIGINT)):
            if cls in only:
                for name, stage in stages.items():
                    tally = Tally("kill -9" if cls == "kill9" else "SIGINT", stage.name, unit=stage.unit)
                    kill_trials(stage, refs[name][0], refs[name][1], sig, args.trials, rng, tally)
                    rows.append(tally)
        if "corrupt" in only:
            eval_dope = refs["train"][0]
            for kind, stage_name, command in (
                    ("capture_session", "reconstruct", lambda d, out: stages["reconstruct"].command(out, d)),
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
        if "servo" in only:
            faults: dict[str, Tally] = {}
            sweep_fault_trials(sweep, control, refs["sweep"][0], args.trials, rng, faults)
            rows += list(faults.values())
        if "disk" in only:
            for name, stage in stages.items():
                tally = Tally("full disk", stage.name, unit=stage.unit)
                disk_trials(stage, refs[name][0], args.trials, rng, tally)
                rows.append(tally)
    finally:
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


def soak_node(seconds: float, work: Path) -> list[tuple]:
    """dope_node for `seconds` on a 30 Hz replay of dataset frames: latency of the first and the last minute, the
    node's memory and descriptors."""
    import threading

    import numpy as np
    from dope import _stream

    from n2d_dope.data import open_dataset, read_rgb

    model, dataset = work / "ref-train", work / "ref-dataset"
    replay = []
    for frame in open_dataset(dataset).frames[:30]:
        camera = json.loads((frame.chunk / "scene_camera.json").read_text())[str(frame.frame_id)]
        replay.append((read_rgb(frame.image), np.array(camera["cam_K"], dtype=float).reshape(3, 3)))
    samples, stop = [], threading.Event()

    def sample() -> None:
        while not stop.wait(1.0):
            nodes = [p for p in _descendants(os.getpid()) if "dope_node" in _cmdline(p)]
            stats = _proc_stats(nodes[-1]) if nodes else None
            if stats is not None:
                samples.append(stats)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    r = _stream(model, seconds, "fp32", replay)
    stop.set()
    lat, at = r["latency_ms"], np.asarray(r["arrivals_s"])
    minute = min(60.0, seconds / 3)
    first, last = lat[at - at[0] <= minute], lat[at >= at[-1] - minute]
    drift = 100 * (np.median(last) - np.median(first)) / np.median(first)
    rows = [(f"dope_node {seconds / 60:.0f} min on a 30 Hz replay: median latency first / last {minute:.0f} s",
             f"{np.median(first):.1f} / {np.median(last):.1f} ms", f"drift {drift:+.1f} %, {r['fps_out']:.1f} FPS out",
             "within 10 %", "met" if abs(drift) <= 10 else "not met")]
    if len(samples) > 10:
        rows += _flat_rows("dope_node", samples, min(10, len(samples) // 10))
    return rows


def soak(args) -> None:
    work = Path(args.work or tempfile.mkdtemp(prefix="n2d-faults-"))
    rows = soak_dataset(args.soak_frames, work) if args.soak_frames > 0 else []
    if args.soak_node_seconds > 0:
        if not (work / "ref-train").is_dir():
            raise SystemExit(f"--soak-node-seconds needs the campaign's trained model: run the campaign with --work "
                             f"{work} first")
        rows += soak_node(args.soak_node_seconds, work)
    print_table("Soak", rows, ("metric", "value", "note", "goal", "met"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=2, help="seeded trials per fault class and stage")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", help=f"fault classes, comma-separated: {', '.join(CLASSES)}")
    parser.add_argument("--work", type=Path, help="work directory (kept; its uninterrupted runs are reused)")
    parser.add_argument("--soak", action="store_true", help="the soak instead of the campaign")
    parser.add_argument("--soak-frames", type=int, default=1000)
    parser.add_argument("--soak-node-seconds", type=float, default=300.0)
    parser.add_argument("--child-sweep", help=argparse.SUPPRESS)
    parser.add_argument("--port", help=argparse.SUPPRESS)
    parser.add_argument("--control", help=argparse.SUPPRESS)
    parser.add_argument("--silent-after", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--reboot", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_sweep:
        return child_sweep(args)
    t0 = time.monotonic()
    if args.soak:
        soak(args)
        return 0
    rows = campaign(args)
    print_campaign(rows, time.monotonic() - t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
