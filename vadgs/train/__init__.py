"""Gaussian model, losses, densification strategies, trainer and evaluation."""

__all__: list[str] = []
