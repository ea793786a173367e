"""vadgs: VAD-GS, visibility-aware densification for 3D Gaussian splatting, as PyTorch components.

Subpackages, imported one way (geometry → render / mvs / select → train):

- :mod:`vadgs.geometry`: cameras, poses, plane homographies, voxel grids and the voxel z-buffer.
- :mod:`vadgs.render`: a pure-torch differentiable Gaussian splatting renderer.
- :mod:`vadgs.mvs`: batched PatchMatch multi-view stereo, consistency checks and fusion.
- :mod:`vadgs.select`: diversity-aware view selection (max-weight k-clique).
- :mod:`vadgs.train`: the Gaussian model, losses, densification strategies and the trainer.
- :mod:`vadgs.data`: scene loaders (the benchmark scene format, COLMAP, DGP).
"""

from vadgs.checks import checking, checks_enabled, set_checks_enabled

__version__ = "0.1.0.dev0"

__all__ = ["__version__", "checking", "checks_enabled", "set_checks_enabled"]
