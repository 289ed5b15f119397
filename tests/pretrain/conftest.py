"""Fixtures shared by the encoder's tests (test_model, test_quantize): one torch thread, and the tiny encoder of
test_model's cameras and grid for ``fuse_pool`` 1 and 2 (eval mode, non-trivial BatchNorm statistics)."""

from __future__ import annotations

import pytest
import torch

from pretrain.model import BEVEncoder
from tests.pretrain.test_model import cameras, randomise_norms, tiny_config


@pytest.fixture
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module", params=[1, 2], ids=["fuse_pool1", "fuse_pool2"])
def encoder(request) -> BEVEncoder:
    torch.manual_seed(0)
    enc = BEVEncoder(tiny_config(fuse_pool=request.param), cameras())
    randomise_norms(enc, torch.Generator().manual_seed(1))
    return enc.eval()
