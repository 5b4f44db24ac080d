"""`n2d dataset --cluster`: frames rendered on a real local Ray cluster (a head and a worker node started with
`ray start` on loopback), a worker node and the head killed mid-run, the dataset byte for byte the one-machine
run's; bad clusters give clear errors and no dataset that looks complete."""

import errno
import hashlib
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers import LocalCluster, free_port

from n2d_common.cluster import Node
from n2d_common.config import load_config
from n2d_common.errors import N2DError
from n2d_dataset import cluster
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dataset.writer import RECORDS
from n2d_sim.objects import sample_object_dir

MODELS = [sample_object_dir("box")]
SMALL = ["frames=6", "camera.width=160", "camera.height=120", "camera.focal_px=150", "render.engine=raster",
         "scene.distractors=[1,2]", "workers=2"]


def small_config(*more: str) -> DatasetConfig:
    return load_config(DatasetConfig, overrides=SMALL + list(more))


def hashes(root: Path) -> dict[str, str]:
    """sha256 of every file of a dataset but its manifest (which holds the wall time)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "n2d.json"}


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    out = tmp_path_factory.mktemp("plain") / "ds"
    generate_dataset(MODELS, out, small_config())
    return out


@pytest.mark.slow
def test_killed_worker_and_head_resume_to_the_same_dataset(plain, tmp_path):
    """Two nodes render; the worker node is killed after the first frame (its frame goes to the head's slot);
    then a run whose head (with the driver on it) is killed resumes on a new cluster. Both datasets are the
    one-machine dataset, file for file (sha256)."""
    import ray  # noqa: F401  installed by install.sh (pinned): a missing Ray is a failure, not a skip

    nodes = LocalCluster()
    try:
        nodes.start("head", head=True)
        nodes.start("worker", head=False)
        killed = threading.Event()

        def kill_worker(p):
            if p.info.get("frames_done", 0) >= 1 and not killed.is_set():
                killed.set()
                nodes.kill("worker")

        out = tmp_path / "worker_killed"
        generate_dataset(MODELS, out, small_config(), progress=kill_worker, cluster=nodes.address)
        assert killed.is_set()
        assert hashes(out) == hashes(plain)

        # The head dies with the driver on it, after some frames are in.
        out = tmp_path / "head_killed"
        cli = subprocess.Popen([sys.executable, "-m", "n2d.cli", "dataset", str(MODELS[0]), str(out), "--cluster",
                                nodes.address, *(a for s in SMALL for a in ("--set", s))],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        records = out.with_name(out.name + ".partial") / RECORDS
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and cli.poll() is None and len(list(records.glob("*.json"))) < 2:
            time.sleep(0.05)
        assert cli.poll() is None, cli.communicate()[0][-3000:]
        nodes.kill("head")
        cli.kill()
        cli.wait()
        assert not out.exists() and 2 <= len(list(records.glob("*.json"))) < 6
        nodes.start("head", head=True)
        summary = generate_dataset(MODELS, out, small_config(), cluster=nodes.address)
        assert summary["resumed_frames"] >= 2
        assert hashes(out) == hashes(plain)
    finally:
        nodes.stop()


def test_unreachable_cluster_is_named(tmp_path):
    out = tmp_path / "ds"
    address = f"127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(N2DError, match=f"cannot reach the Ray cluster at {address}"):
        generate_dataset(MODELS, out, small_config(), cluster=address)
    assert time.monotonic() - t0 < 10 and not out.exists() and not out.with_name("ds.partial").exists()
    with pytest.raises(N2DError, match="not HOST:PORT"):
        generate_dataset(MODELS, tmp_path / "ds2", small_config(), cluster="nowhere")


def test_a_node_with_another_n2d_or_without_bpy_is_named():
    info = {"node": "10.0.0.7", "host": "lab-pc-3", "version": "0.0.9", "bpy": True}
    with pytest.raises(N2DError, match=r"node 10.0.0.7 \(lab-pc-3\) runs n2d 0.0.9"):
        cluster.check_node(info, "raster")
    from n2d_common import __version__

    info["version"] = __version__
    cluster.check_node(info, "raster")
    with pytest.raises(N2DError, match=r"lab-pc-3\) has no bpy"):
        cluster.check_node(info | {"bpy": False}, "cycles")


def test_a_full_disk_on_the_driver_is_named(tmp_path, monkeypatch):
    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(cluster, "atomic_write_bytes", full)
    with pytest.raises(N2DError, match=f"disk of {tmp_path} on {socket.gethostname()}.*is full"):
        cluster.write_frame_files(tmp_path, [("records/000000.json", b"{}")])
    assert not (tmp_path / RECORDS).exists()


def test_slots_follow_the_cluster():
    nodes = [Node("a", 4.0, 0.0), Node("b", 2.0, 0.0)]
    assert cluster.slots(nodes, small_config("workers=0"), "raster") == (6, {"num_cpus": 1}, 1)
    assert cluster.slots(nodes, small_config("workers=0"), "cycles") == (2, {"num_cpus": 2}, 2)
    gpu = [Node("a", 8.0, 2.0)]
    assert cluster.slots(gpu, small_config("workers=0"), "cycles") == (2, {"num_cpus": 1, "num_gpus": 1}, 1)


def test_ray_is_imported_only_for_a_cluster():
    code = ("import sys, n2d_dataset.generate, n2d_dope.train, n2d.cli; "
            "assert 'ray' not in sys.modules, 'ray imported'; print('ok')")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "ok" in run.stdout, run.stderr[-2000:]
