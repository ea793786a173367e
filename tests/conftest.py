"""Fixtures shared by every test package: ``device`` runs a test on the CPU and, where CUDA is
present, again on the GPU (the CUDA case is reported as skipped elsewhere); ``dtype``."""

from __future__ import annotations

import pytest
import torch

_CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=_CUDA)])
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture
def dtype() -> torch.dtype:
    return torch.float32
