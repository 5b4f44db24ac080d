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
