"""Data-parallel DOPE training with torch.distributed: the process group, the launcher, and each rank's share.

Three ways in, one training: `train(..., ddp=N)` (`n2d train --ddp N`) starts N-1 helper processes on this
machine and runs rank 0 itself (so progress, cancel and the summary stay the caller's); `torchrun` (its RANK,
WORLD_SIZE, MASTER_ADDR, MASTER_PORT environment) on one machine or several; or a process group someone else
set up (Ray Train's TorchTrainer). The backend is gloo on CPUs, NCCL on CUDA. Each step's batch is the one a
single process trains on, split across the ranks (rank r takes its items r, r + N, ...), and each rank's loss is
weighed by its share, so the averaged gradient is the single process's (up to batch-norm statistics, which each
rank computes on its share). Rank 0 alone writes checkpoints and exports; a resumed run starts every rank from it.
"""

from __future__ import annotations

import datetime
import multiprocessing as mp
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.distributed as dist

from n2d_common.errors import Cancelled, N2DError

TIMEOUT_S = 300.0
"""How long a rank waits for the others at a collective before the run fails (a rank that died)."""


@dataclass(frozen=True)
class Ranks:
    """This process's place in the training: rank, world size, and the rank on its machine (its GPU index)."""

    rank: int = 0
    world: int = 1
    local: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the one that writes checkpoints, exports and reports."""
        return self.rank == 0


ONE = Ranks()
"""A single process."""


def backend(device: torch.device) -> str:
    return "nccl" if device.type == "cuda" else "gloo"


def current(device: torch.device) -> Ranks:
    """The ranks of this process: the initialised process group's, one from torchrun's environment (initialised
    here), or a single process."""
    if not dist.is_initialized() and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        dist.init_process_group(backend(device), init_method="env://",
                                timeout=datetime.timedelta(seconds=TIMEOUT_S))
    if not dist.is_initialized():
        return Ranks()
    return Ranks(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", dist.get_rank())))


def share(obj, ranks: Ranks):
    """Rank 0's `obj` on every rank."""
    if ranks.world == 1:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def shard(batch_items: list, ranks: Ranks) -> tuple[list, float]:
    """This rank's items of a batch and the weight of its loss (items * world / batch size), so the averaged
    gradient is the whole batch's. A rank left without an item trains on the first with weight 0 (every rank
    must take part in each step)."""
    mine = batch_items[ranks.rank::ranks.world]
    if not mine:
        return batch_items[:1], 0.0
    return mine, len(mine) * ranks.world / len(batch_items)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _init(rank: int, world: int, port: int, device_type: str) -> None:
    os.environ["LOCAL_RANK"] = str(rank)
    dist.init_process_group(backend(torch.device(device_type)), init_method=f"tcp://127.0.0.1:{port}", rank=rank,
                            world_size=world, timeout=datetime.timedelta(seconds=TIMEOUT_S))


def _helper(rank: int, world: int, port: int, device_type: str, fn: Callable, args: tuple, kwargs: dict) -> None:
    from n2d_common.process import die_with_parent

    die_with_parent()
    _init(rank, world, port, device_type)
    try:
        fn(*args, **kwargs)
    except Cancelled:
        pass  # rank 0 was cancelled and says so
    finally:
        dist.destroy_process_group()


def launch(world: int, device: torch.device, fn: Callable, args: tuple, kwargs: dict, main_kwargs: dict):
    """Run `fn(*args, **kwargs)` as `world` ranks on this machine (loopback): ranks 1.. in helper processes,
    rank 0 here with `main_kwargs` too (its progress and cancel, which need not pickle); returns rank 0's result."""
    if dist.is_initialized():
        raise N2DError("ddp: this process already belongs to a process group", "launch without --ddp (torchrun)")
    port = _free_port()
    ctx = mp.get_context("spawn")
    helpers = [ctx.Process(target=_helper, args=(r, world, port, device.type, fn, args, kwargs), daemon=True)
               for r in range(1, world)]
    for p in helpers:
        p.start()
    try:
        _init(0, world, port, device.type)
        try:
            return fn(*args, **kwargs, **main_kwargs)
        finally:
            dist.destroy_process_group()
    finally:
        for p in helpers:
            p.join(timeout=30)
            if p.is_alive():
                p.kill()
