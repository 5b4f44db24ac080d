"""On-disk contracts shared by every stage: the `n2d.json` manifest and atomic stage directories.

Each stage reads one directory and writes the next. A directory is *complete* only when its
manifest says so; the manifest is written last, atomically. Small outputs are built in a temporary
sibling (`<out>.partial`) and renamed into place on success, so a crash never leaves a directory
that looks finished; long, resumable jobs keep working in that sibling until they are done.

Manifest fields: kind, version, complete, created (UTC, ISO 8601), producer (package version),
inputs (name -> path), config (the stage config as a plain dict), extra (stage-specific facts).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from n2d_common.errors import ContractError

_UMASK = os.umask(0o022)
os.umask(_UMASK)
MANIFEST = "n2d.json"
VERSION = 1
KINDS = ("capture_session", "model", "dataset", "dope_model", "run", "sim_frames")
"""The directory kinds n2d writes, in pipeline order."""


LEFTOVER = ".*.tmp"
"""Name pattern of the temporary files of atomic writes (`.<name>.<random>.tmp`): a process killed half way
through a write leaves one, which the stage removes when it resumes and before it publishes its output."""


def remove_leftovers(directory: Path) -> int:
    """Delete the temporary files of interrupted atomic writes below `directory`; returns how many."""
    found = [p for p in Path(directory).rglob(LEFTOVER) if p.is_file()]
    for p in found:
        p.unlink(missing_ok=True)
    return len(found)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file in the same directory and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp creates 0600; outputs get the usual permissions
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Atomically write UTF-8 text."""
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Atomically write `obj` as indented JSON."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def write_manifest(directory: str | Path, kind: str, *, config: dict | None = None,
                   inputs: dict | None = None, extra: dict | None = None,
                   complete: bool = True) -> dict:
    """Write `directory/n2d.json` (atomically) and return it; call it after everything else is written."""
    if kind not in KINDS:
        raise ValueError(f"unknown directory kind {kind!r}; known: {', '.join(KINDS)}")
    from n2d_common import __version__

    manifest = {
        "kind": kind,
        "version": VERSION,
        "complete": complete,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "producer": f"n2d {__version__}",
        "inputs": {k: str(v) for k, v in (inputs or {}).items()},
        "config": config or {},
        "extra": extra or {},
    }
    atomic_write_json(Path(directory) / MANIFEST, manifest)
    return manifest


def read_manifest(directory: str | Path) -> dict | None:
    """The manifest of `directory`, or None when it has none. Raises ContractError if it is unreadable."""
    path = Path(directory) / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ContractError(f"{path} is corrupt ({exc})", "delete the directory and run the stage again") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("kind"), str):
        raise ContractError(f"{path} is not an n2d manifest", "is this directory from another tool?")
    version = manifest.get("version", 0)
    if isinstance(version, bool) or not isinstance(version, int):
        raise ContractError(f"{path} has format version {version!r}, not a whole number",
                            "delete the directory and run the stage again")
    for key in ("config", "extra", "inputs"):
        if not isinstance(manifest.setdefault(key, {}), dict):
            raise ContractError(f"{path}: {key} is a {type(manifest[key]).__name__}, not a mapping",
                                "delete the directory and run the stage again")
    return manifest


def open_stage(directory: str | Path, kind: str) -> dict:
    """Check that `directory` is a complete n2d directory of `kind` and return its manifest.

    Refuses, with a message saying what to do, a missing directory, one without a manifest
    (foreign), one of another kind, one from a newer n2d, and one whose producer did not finish.
    """
    directory = Path(directory)
    if not directory.is_dir():
        partial = _partial(directory)
        hint = (f"an unfinished run is in {partial}: run the stage again with --resume"
                if partial.is_dir() else "check the path, or run the stage that writes it")
        raise ContractError(f"{directory} does not exist", hint)
    manifest = read_manifest(directory)
    if manifest is None:
        raise ContractError(f"{directory} has no {MANIFEST}: it was not written by n2d, or not finished",
                            f"give a {kind.replace('_', ' ')} directory written by n2d")
    if manifest["kind"] != kind:
        raise ContractError(f"{directory} is a {manifest['kind'].replace('_', ' ')}, not a {kind.replace('_', ' ')}",
                            "check the order of the arguments")
    if manifest.get("version", 0) > VERSION:
        raise ContractError(f"{directory} was written by a newer n2d (format {manifest['version']} > {VERSION})",
                            "update n2d")
    if not manifest.get("complete"):
        raise ContractError(f"{directory} is incomplete: the {kind.replace('_', ' ')} was not finished",
                            "run the stage again with --resume, or delete the directory")
    return manifest


def _partial(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


class StageWriter:
    """A stage output under construction: write into `.path`, then `finish()` publishes it.

    Use through `stage_output()`. `.path` is `<out>.partial`; `.resumed` says whether it held an
    earlier unfinished run of the same kind (the stage then skips what is already there).
    """

    def __init__(self, out: Path, kind: str, resumed: bool):
        self.out = out
        self.kind = kind
        self.path = _partial(out)
        self.resumed = resumed
        self.finished = False

    def finish(self, *, config: dict | None = None, inputs: dict | None = None,
               extra: dict | None = None) -> dict:
        """Write the complete manifest and rename the directory into place (replacing an old output)."""
        remove_leftovers(self.path)
        manifest = write_manifest(self.path, self.kind, config=config, inputs=inputs, extra=extra)
        old = None
        if self.out.exists():
            old = self.out.with_name(f".{self.out.name}.old-{os.getpid()}")
            os.replace(self.out, old)
        os.replace(self.path, self.out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        self.finished = True
        return manifest


@contextmanager
def stage_output(out: str | Path, kind: str, *, overwrite: bool = False, resume: bool = True,
                 config: dict | None = None) -> Iterator[StageWriter]:
    """Open the output directory `out` of a stage of `kind` for writing.

    - `out` exists and is complete: refused unless `overwrite` (the old one is replaced only
      once the new one is finished, so nothing is lost if the new run fails).
    - `out` exists but is not an n2d directory of `kind`: always refused.
    - `<out>.partial` from an earlier run of the same job (kind and config): reused when `resume`;
      unfinished work of another job is discarded only with `overwrite`, else refused.
    The partial directory carries an incomplete manifest with `config` so a resumed run can check
    that it continues the same job. Until `finish()` (on an exception, or when a job stops half way
    on purpose) the partial directory stays, for the next run to resume.
    """
    out = Path(out).absolute()
    if out.exists():
        manifest = read_manifest(out) if out.is_dir() else None
        if manifest is None:
            if out.is_dir() and not any(out.iterdir()):
                out.rmdir()
            else:
                raise ContractError(f"{out} exists and is not an n2d directory",
                                    "choose another output path; n2d never writes into foreign directories")
        elif manifest["kind"] != kind:
            raise ContractError(f"{out} already holds a {manifest['kind'].replace('_', ' ')}",
                                "choose another output path")
        elif not overwrite:
            raise ContractError(f"{out} already exists", "choose another output path, or pass --overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = _partial(out)
    resumed = False
    if partial.exists():
        previous = read_manifest(partial)
        if previous is None:
            raise ContractError(f"{partial} exists and is not an n2d directory", "move it away")
        same_job = previous["kind"] == kind and (config is None or previous.get("config") == config)
        if resume and same_job:
            resumed = True
            remove_leftovers(partial)
        elif overwrite:
            shutil.rmtree(partial)
        else:
            why = "of another job (its config differs)" if not same_job else "of an earlier run"
            raise ContractError(f"{partial} holds unfinished work {why}",
                                "re-run with the same config to resume, or pass --overwrite to discard it")
    if not resumed:
        partial.mkdir()
        write_manifest(partial, kind, config=config, complete=False)
    yield StageWriter(out, kind, resumed)


@contextmanager
def discard_on_bad_input(stage: StageWriter, progress_file: str) -> Iterator[None]:
    """Inside a stage's `with stage_output(...)`: a ContractError (bad input found while working, e.g. a damaged
    frame) raised before the job kept any work (no `progress_file` in a partial directory this run created)
    removes the partial directory, so a bad input leaves nothing behind; kept work stays for a resume."""
    try:
        yield
    except ContractError:
        if not stage.resumed and not (stage.path / progress_file).exists():
            shutil.rmtree(stage.path, ignore_errors=True)
        raise
