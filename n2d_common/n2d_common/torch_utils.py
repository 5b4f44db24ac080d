"""Small PyTorch helpers shared by the stages: device choice, atomic saves, safe loads, thread counts."""

from __future__ import annotations

import errno
import os
import pickle
from contextlib import contextmanager
from pathlib import Path

import torch

from n2d_common.errors import ContractError


def resolve_device(name: str) -> torch.device:
    """"auto" is CUDA when available, else the CPU; other names are torch device names."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def atomic_torch_save(obj: dict, path: str | Path) -> None:
    """torch.save to a temporary file next to `path`, then rename it into place.

    A write that fails (torch's zip writer reports a full disk as a RuntimeError) raises OSError naming `path`, and
    the earlier file at `path` stays."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # contracts.LEFTOVER: removed if a kill leaves it
    try:
        torch.save(obj, tmp)
    except (OSError, RuntimeError) as exc:
        full = os.statvfs(path.parent).f_bavail == 0
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise
        raise OSError(errno.ENOSPC if full else errno.EIO, "no space left on device" if full
                      else f"could not write ({exc})", str(path)) from None
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """A checkpoint n2d wrote (tensors in dicts, lists and plain values), loaded without unpickling code: a file
    holding any other object (which torch's pickle loader could run) is refused with a clear error."""
    path = Path(path)
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ContractError(f"{path} holds objects other than tensors and plain values ({first[:200]}); n2d does "
                            "not load such a file, its pickle could run code",
                            "use a checkpoint written by n2d (or re-run the stage with --overwrite)") from None
    except (RuntimeError, EOFError, OSError) as exc:
        raise ContractError(f"{path} is not a readable checkpoint ({type(exc).__name__}: {str(exc)[:200]})",
                            "re-run the stage with --overwrite") from None


@contextmanager
def torch_threads(count: int):
    """Run torch's CPU ops with `count` threads inside the block (many small ops, e.g. rasterizing small images,
    run far slower with several threads on a busy machine), restoring the previous count after."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
