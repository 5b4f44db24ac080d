"""Connecting to a Ray cluster: the addresses n2d accepts, a clear error when one cannot be reached, its nodes.

Ray is imported here only, and only when a cluster is asked for: a run without `--cluster` never loads it.
Addresses: `ray://HOST:PORT` (a Ray Client server, the head's port 10001 by default: the driver may run on any
machine), `HOST:PORT` (the head's GCS port, 6379 by default: the driver runs on a node of the cluster), `auto`
(the cluster this machine was joined to with `ray start`), `local` (a private cluster of this machine alone,
started for the run on loopback and stopped after it).
"""

from __future__ import annotations

import ipaddress
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from types import ModuleType

from n2d_common.errors import N2DError

LOCAL, AUTO = "local", "auto"
CONNECT_TIMEOUT_S = 5.0
"""How long a cluster address may take to accept a TCP connection before it counts as unreachable."""


@dataclass(frozen=True)
class Node:
    """One alive node of the cluster and the resources it offers."""

    ip: str
    cpus: float
    gpus: float


def _host_port(address: str) -> tuple[str, int]:
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        raise N2DError(f"cluster address {address!r} is not HOST:PORT, ray://HOST:PORT, auto or local",
                       "give the head's address, e.g. ray://192.168.1.10:10001 or 192.168.1.10:6379")
    return host.strip("[]"), int(port)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def check_reachable(address: str) -> None:
    """Raise N2DError naming the address when nothing accepts a connection there (a wrong address, a head that
    is not running, a firewall), instead of Ray's long retries."""
    host, port = _host_port(address)
    try:
        socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise N2DError(f"cannot reach the Ray cluster at {address} ({exc.strerror or exc})",
                       "start the head with `ray start --head` on that machine, and check the address, the port "
                       "and the firewall") from None


def _import_ray() -> ModuleType:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        import ray
    except ImportError:
        raise N2DError("a cluster run needs Ray, which is not installed here",
                       "install it with the pin of constraints.txt: pip install ray -c constraints.txt") from None
    return ray


_CLUSTER_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@contextmanager
def _stay_on_loopback() -> Iterator[None]:
    """Keep a one-machine Ray on loopback while the connection lasts. Ray swaps a loopback address for the
    machine's network address unless it believes it runs without a cluster (its switch for Windows and macOS,
    read from the environment by the processes it starts and as a constant in this one); n2d sets that switch
    for `local` and loopback clusters, so no Ray server of theirs listens beyond this machine, and puts both
    back afterwards, so a later `ray start` from this process may still join nodes."""
    from ray._private import ray_constants

    before_env, before_constant = os.environ.get(_CLUSTER_SWITCH), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[_CLUSTER_SWITCH] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = before_constant
        if before_env is None:
            os.environ.pop(_CLUSTER_SWITCH, None)
        else:
            os.environ[_CLUSTER_SWITCH] = before_env


@contextmanager
def connect(address: str) -> Iterator[ModuleType]:
    """Connect this process to the Ray cluster at `address` and yield the `ray` module; disconnect afterwards
    (stopping a `local` cluster). A process already connected (a pipeline driving several stages) stays so."""
    if address not in (LOCAL, AUTO):
        check_reachable(address)  # before Ray's own retries, which take minutes
    ray = _import_ray()
    if ray.is_initialized():
        yield ray
        return
    kwargs: dict = {"log_to_driver": False, "logging_level": "warning"}
    loopback = address == LOCAL or (address != AUTO and _is_loopback(_host_port(address)[0]))  # local, tests
    tmp = None
    if address == LOCAL:
        tmp = tempfile.mkdtemp(prefix="n2d_ray_", dir="/tmp" if os.path.isdir("/tmp") else None)
        kwargs |= {"include_dashboard": False, "_temp_dir": tmp}
    else:
        kwargs["address"] = address
    with _stay_on_loopback() if loopback else nullcontext():
        try:
            ray.init(**kwargs)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            if tmp:
                shutil.rmtree(tmp, ignore_errors=True)
            raise N2DError(f"could not connect to the Ray cluster {address!r}: {exc}",
                           "check that `ray status` on the head lists the nodes, and that this machine runs the "
                           "same Ray and Python versions") from None
        try:
            yield ray
        finally:
            ray.shutdown()
            if tmp:
                shutil.rmtree(tmp, ignore_errors=True)


def nodes(ray: ModuleType) -> list[Node]:
    """The alive nodes of the connected cluster."""
    return [Node(n["NodeManagerAddress"], n["Resources"].get("CPU", 0.0), n["Resources"].get("GPU", 0.0))
            for n in ray.nodes() if n.get("Alive")]
