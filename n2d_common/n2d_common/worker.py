"""Long jobs in a worker process: progress flows back, cancel reaches the job, errors keep their type.

ROS nodes run stage jobs (reconstruction, dataset rendering) through `run_in_worker` so the node's
executor stays responsive, a cancel stops the job cleanly (the job sees its cancel event, saves its
checkpoint and raises Cancelled), and a crash of the job cannot take the node down. The worker is a
fresh interpreter (multiprocessing "spawn"): nothing of the parent's ROS context is inherited.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from n2d_common.errors import Cancelled, N2DError
from n2d_common.progress import ProgressFn, no_progress

KILL_AFTER_CANCEL_S = 60.0
"""How long a cancelled job may take to save its state and stop before its process is killed."""


def _worker(fn: Callable, kwargs: dict, messages: mp.Queue, cancel) -> None:
    from n2d_common.process import die_with_parent

    die_with_parent()
    try:
        result = fn(**kwargs, progress=lambda p: messages.put(("progress", p)), cancel=cancel)
        messages.put(("result", result))
    except N2DError as exc:
        messages.put(("error", type(exc), exc.message, exc.hint))
    except BaseException as exc:
        messages.put(("error", N2DError, f"{type(exc).__name__}: {exc}", "this is a bug in n2d; please report it"))


def run_in_worker(fn: Callable, kwargs: dict, *, progress: ProgressFn = no_progress,
                  cancel: threading.Event | None = None, children: bool = False) -> Any:
    """Call `fn(**kwargs, progress=..., cancel=...)` in a new process and return its result.

    `fn` must be importable (a module-level function). Its progress reports are forwarded to
    `progress`; setting `cancel` sets the job's own cancel event. N2DError subclasses raised by the job
    are raised here with their message and hint; a process that dies without a word raises N2DError.
    `children`: the job starts processes of its own (a daemonic process may not; the worker still dies with its
    parent).
    """
    ctx = mp.get_context("spawn")
    messages, job_cancel = ctx.Queue(), ctx.Event()
    proc = ctx.Process(target=_worker, args=(fn, kwargs, messages, job_cancel), daemon=not children)
    proc.start()
    cancelled_at = None
    try:
        while True:
            if cancel is not None and cancel.is_set() and not job_cancel.is_set():
                job_cancel.set()
                cancelled_at = time.monotonic()
            try:
                message = messages.get(timeout=0.2)
            except queue.Empty:
                if not proc.is_alive():
                    raise N2DError(f"the worker process died (exit code {proc.exitcode})",
                                   "check free memory and the log; re-run to resume") from None
                if cancelled_at is not None and time.monotonic() - cancelled_at > KILL_AFTER_CANCEL_S:
                    proc.kill()
                    raise Cancelled("the job was cancelled and killed after not stopping in time",
                                    "re-run to resume from the last checkpoint") from None
                continue
            if message[0] == "progress":
                progress(message[1])
            elif message[0] == "result":
                return message[1]
            else:
                _, cls, text, hint = message
                raise cls(text, hint)
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
            proc.join()

