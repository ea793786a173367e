"""Pure-torch differentiable 3D Gaussian splatting (see ``docs/render.md``).

:func:`rasterize_gaussians` renders colour, opacity, expected and median depth and normals, with
the per-Gaussian screen radii, visibility and 2D-mean gradients that densification needs;
:class:`GaussianRasterizer` is its ``nn.Module``. The pieces are public too: EWA projection,
spherical harmonics (and their rotation), tile binning, compositing and 3DGS PLY input/output.
:func:`rasterize_gaussians_gsplat` renders the same inputs with gsplat (``RasterConfig(backend="gsplat")``).
"""

from vadgs.render.common import RasterConfig, RenderOutput
from vadgs.render.composite import CompositeOutput, composite_gaussians
from vadgs.render.gsplat_backend import rasterize_gaussians_gsplat
from vadgs.render.ply import GaussianPly, load_ply, read_raw_ply, save_ply, write_raw_ply
from vadgs.render.projection import ProjectedGaussians, project_gaussians
from vadgs.render.sh import (
    SH_C0,
    eval_sh,
    num_sh_bases,
    rgb_to_sh,
    rotate_sh,
    sh_basis,
    sh_rotation,
    sh_to_rgb,
)
from vadgs.render.splat import GaussianRasterizer, rasterize_gaussians
from vadgs.render.tiles import TileBins, bin_gaussians

__all__ = [
    "SH_C0",
    "CompositeOutput",
    "GaussianPly",
    "GaussianRasterizer",
    "ProjectedGaussians",
    "RasterConfig",
    "RenderOutput",
    "TileBins",
    "bin_gaussians",
    "composite_gaussians",
    "eval_sh",
    "load_ply",
    "num_sh_bases",
    "project_gaussians",
    "rasterize_gaussians",
    "rasterize_gaussians_gsplat",
    "read_raw_ply",
    "rgb_to_sh",
    "rotate_sh",
    "save_ply",
    "sh_basis",
    "sh_rotation",
    "sh_to_rgb",
    "write_raw_ply",
]
