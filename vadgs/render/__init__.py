"""Pure-torch differentiable Gaussian splatting."""

__all__: list[str] = []
