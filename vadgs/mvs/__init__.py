"""Batched PatchMatch multi-view stereo, consistency checks and fusion."""

__all__: list[str] = []
