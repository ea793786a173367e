"""Diversity-aware view selection."""

__all__: list[str] = []
