"""Fixtures of the MVS tests (helpers in ``mvs_scenes.py``)."""

from __future__ import annotations

import pytest
import torch

from .mvs_scenes import PlaneScene, plane_scene


@pytest.fixture
def fronto_scene() -> PlaneScene:
    return plane_scene()


@pytest.fixture
def slanted_scene() -> PlaneScene:
    return plane_scene(normal=(0.35, -0.25, -1.0), z0=2.0, seed=1)


@pytest.fixture(autouse=True)
def _single_thread():
    """One intra-op thread: on a shared, oversubscribed CPU the OpenMP barriers of two threads
    make the many small ops of PatchMatch 10-20x slower. Restored after each test."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
