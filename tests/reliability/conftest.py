"""The tiny sample scene and training config of ``tests/train`` (the same fixtures, re-exported)."""

from tests.train.conftest import tiny_config, tiny_scene  # noqa: F401
