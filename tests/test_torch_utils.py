"""Checkpoints are loaded without unpickling code: tensors and plain values load, anything else is refused."""

import collections

import pytest
import torch

from n2d_common.errors import ContractError
from n2d_common.torch_utils import atomic_torch_save, load_checkpoint


class Payload:
    """Stands for any object a foreign pickle could carry (its reduce could run code)."""

    def __init__(self):
        self.value = 1


def test_plain_checkpoint_loads(tmp_path):
    state = {"model": collections.OrderedDict(w=torch.ones(3)), "position": {"step": 4, "losses": [0.5, None]},
             "identity": {"object": "box", "size": (1, 2)}}
    atomic_torch_save(state, tmp_path / "ckpt.pt")
    loaded = load_checkpoint(tmp_path / "ckpt.pt")
    assert torch.equal(loaded["model"]["w"], torch.ones(3)) and loaded["position"]["step"] == 4


def test_pickled_objects_are_refused(tmp_path):
    torch.save({"model": {}, "extra": Payload()}, tmp_path / "evil.pt")
    with pytest.raises(ContractError, match="objects other than tensors"):
        load_checkpoint(tmp_path / "evil.pt")
    (tmp_path / "cut.pt").write_bytes((tmp_path / "evil.pt").read_bytes()[:40])
    with pytest.raises(ContractError, match="not a readable checkpoint"):
        load_checkpoint(tmp_path / "cut.pt")


def test_a_full_disk_is_an_oserror_and_keeps_the_old_checkpoint(tmp_path):
    """torch's zip writer reports a write that fails (here: a file size limit, as a full disk would) as a
    RuntimeError; atomic_torch_save turns it into an OSError naming the file (the CLI's disk-space hint)."""
    import subprocess
    import sys

    atomic_torch_save({"model": {"w": torch.ones(1)}}, tmp_path / "ckpt.pt")
    script = f"""
import resource, signal, torch
from n2d_common.torch_utils import atomic_torch_save
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))
try:
    atomic_torch_save({{"model": {{"w": torch.ones(1_000_000)}}}}, {str(tmp_path / "ckpt.pt")!r})
except OSError as exc:
    print("OSError", exc.filename)
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.stdout.split() == ["OSError", str(tmp_path / "ckpt.pt")], result.stderr
    assert torch.equal(load_checkpoint(tmp_path / "ckpt.pt")["model"]["w"], torch.ones(1))
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temporary file left
