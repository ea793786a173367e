"""The loss of a training step: every term, by name, from a render of one view.

:class:`Objective` holds what the terms need besides the render (the scene's images and LiDAR
depth maps, read when a view is trained and kept on the host in a byte-bounded
:class:`~vadgs.data.cache.ByteCache`, uint8 images and sparse depth, moved to the training device
per step; the appearance model; the priors of the paper's geometric losses; extra terms from a
hook) and returns the weighted terms of a step: the colour loss of
the appearance-corrected render, the appearance regulariser, the sparse LiDAR depth term and
:func:`~vadgs.train.losses.geometric_losses` (normal, hard and soft depth) on the view's
:class:`~vadgs.train.losses.GeometryTargets`. :class:`~vadgs.train.trainer.Trainer` sums them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from vadgs.data.cache import ByteCache, SparseDepth, from_uint8, to_uint8
from vadgs.data.lidar import lidar_depth_map
from vadgs.data.scene import Scene
from vadgs.train import losses as L
from vadgs.train.appearance import AppearanceModel, correct_view, view_camera
from vadgs.train.config import TrainConfig
from vadgs.train.losses import GeometryTargets
from vadgs.train.model import GaussianModel, ModelRender

if TYPE_CHECKING:
    from vadgs.render import RasterConfig

__all__ = ["Objective", "render_hard_depth"]


def render_hard_depth(
    model: GaussianModel,
    world_to_cam: torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    frame: int,
    config: RasterConfig | None = None,
    stride: int = 1,
    fused: ModelRender | None = None,
) -> torch.Tensor:
    r"""The depth of :math:`\mathcal{L}_\text{hard}` (paper, Sec. 4.4, Eq. (eq.loss)): opacities fixed to 1.

    The paper's hard depth loss measures "depth errors using fixed [...] Gaussian opacities": the
    view's depth rendered with every opacity 1 (no gradient to the opacity logits), the first
    surface along each ray, which a floater cannot escape by fading. The one place the trainer
    gets it from, two ways with the same values (to float32 rounding at ``stride`` 1):

    - a second, depth-only render of the model
      (:meth:`~vadgs.train.model.GaussianModel.render_depth` with ``opacity_override=1.0``) on
      every ``stride``-th pixel row and column: a camera with ``fx, fy, cx, cy`` divided by
      ``stride`` (``GeometricLossConfig.hard_stride``); pixel ``(s i, s j)`` of the view is
      pixel ``(i, j)`` here;
    - ``fused``: the step's own render, made with ``hard_depth=True``
      (:func:`~vadgs.render.rasterize_gaussians` composites the hard depth in the same pass;
      ``GeometricLossConfig.hard_fused``): its ``raster.hard_depth``, no render here.

    Args:
        model: the Gaussians.
        world_to_cam: ``(1, 4, 4)`` the view's camera.
        K: ``(1, 3, 3)`` its intrinsics at the view's size.
        image_size: the view's ``(H, W)``.
        frame: the view's frame position (moving objects posed there).
        config: the rasterizer's settings.
        stride: the pixel stride (>= 1; 1 with ``fused``).
        fused: the step's render of this view made with ``hard_depth=True``, or None.

    Returns:
        ``(1, 1, ceil(H / stride), ceil(W / stride))`` depth (0 where no Gaussian is hit).
    """
    if fused is not None:
        if stride != 1:
            raise ValueError(
                f"stride: expected 1 with a fused render (its hard depth is per pixel), got {stride}"
            )
        hard = fused.raster.hard_depth
        if hard is None:
            raise ValueError(
                "fused: expected a render made with hard_depth=True, got one without a hard depth"
            )
        return hard
    if stride < 1:
        raise ValueError(f"stride: expected an integer >= 1, got {stride}")
    K = K.clone()
    K[:, :2] /= stride
    h, w = image_size
    size = (-(-h // stride), -(-w // stride))
    return model.render_depth(world_to_cam, K, size, frame, config, opacity_override=1.0).depth


class Objective:
    """The weighted loss terms of a step (see the module docstring).

    Args:
        scene: the scene whose views are trained.
        config: the run's :class:`~vadgs.train.config.TrainConfig` (its ``geometry``: the geometric
            losses' weights, schedule and hard stride).
        device: where the loss is computed (images and LiDAR depth are moved there per step).
        appearance: the appearance model, or None.
        geometry_targets: ``view -> GeometryTargets | None``, the geometric losses' priors, or None.
        extra_losses: ``(step, render, view) -> {name: scalar}`` added as given, or None.
        cache_gb: the host memory the images and LiDAR depth maps are kept in (GB, 2^30 bytes;
            None: ``config.cache_gb``); the least recently trained views are read again.
    """

    def __init__(
        self,
        scene: Scene,
        config: TrainConfig,
        device: torch.device,
        appearance: AppearanceModel | None = None,
        geometry_targets: Callable[[int], GeometryTargets | None] | None = None,
        extra_losses: Callable[[int, ModelRender, int], dict[str, torch.Tensor]] | None = None,
        cache_gb: float | None = None,
    ) -> None:
        self.scene = scene
        self.config = config
        self.device = device
        self.appearance = appearance
        self.geometry_targets = geometry_targets
        self.extra_losses = extra_losses
        gb = config.cache_gb if cache_gb is None else cache_gb
        self.cache = ByteCache(max(1, int(gb * 2**30)))
        self._last_image: tuple[int, torch.Tensor] | None = None

    def image(self, view: int) -> torch.Tensor:
        """Training image ``(1, 3, H, W)`` float32 on the device (kept as uint8 on the host).

        The last view's is kept on the device too: a step asks for it twice (its loss, its PSNR).
        """
        if self._last_image is None or self._last_image[0] != view:
            kept = self.cache.get(("image", view), lambda: to_uint8(self.scene.load_images([view])))
            self._last_image = (view, from_uint8(kept, self.device))
        return self._last_image[1]

    def lidar_depth(self, view: int) -> torch.Tensor | None:
        """Sparse LiDAR depth ``(1, 1, H, W)`` of a view on the device, None without a LiDAR point there."""
        if self.scene.lidar_loader is None:
            return None

        def read() -> SparseDepth:
            try:
                return SparseDepth.from_dense(lidar_depth_map(self.scene, view))
            except FileNotFoundError:
                return SparseDepth.from_dense(torch.zeros(1, 1, *self.scene.image_size(view)))

        sparse = self.cache.get(("lidar", view), read)
        return sparse.to_dense(self.device) if sparse.points else None

    def corrected_color(self, view: int, color: torch.Tensor) -> torch.Tensor:
        """A render's colour ``(1, 3, H, W)`` after the view's appearance transform, if any."""
        return correct_view(self.appearance, self.scene, view, color, held_out=False)

    def wants_hard(self, step: int, view: int) -> bool:
        """Whether the step's loss includes the hard depth term (its render may then composite it).

        :meth:`~vadgs.train.losses.GeometricLossConfig.hard_applies` at ``step``, for a view with a
        target depth; the depth itself is :func:`render_hard_depth`'s.
        """
        cfg = self.config
        if self.geometry_targets is None or not cfg.geometry.hard_applies(step, cfg.iterations):
            return False
        targets = self.geometry_targets(view)
        return targets is not None and targets.depth is not None

    def __call__(
        self, step: int, view: int, out: ModelRender, render_hard: Callable[[int, int], torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Every loss term of a step (already weighted), by name.

        Args:
            step: the step (the geometric losses' schedule).
            view: the view rendered.
            out: its raw render; the colour loss compares its :meth:`corrected_color` with the
                image; ``extra_losses`` get it as given.
            render_hard: ``(view, s) -> (1, 1, ceil(H/s), ceil(W/s))`` the view's
                :func:`render_hard_depth` on every ``s``-th pixel row and column (``s =
                config.geometry.hard_stride``, the stride the targets are sampled at); called on
                the steps the hard depth loss applies.
        """
        cfg = self.config
        color = self.corrected_color(view, out.color)
        terms = {"color": L.color_loss(color, self.image(view), cfg.ssim_weight)}
        if self.appearance is not None:
            app = cfg.appearance
            assert app is not None  # the appearance model is made from it
            camera = view_camera(self.scene, view)
            cam, frame = self.appearance.penalty(camera, self.scene.view_frame_position(view))
            terms["appearance"] = app.reg * cam + app.frame_reg * frame
        if cfg.lambda_lidar > 0:
            lid = self.lidar_depth(view)
            if lid is not None:
                terms["lidar"] = cfg.lambda_lidar * L.depth_loss(out.raster.depth, lid)
        targets = self.geometry_targets(view) if self.geometry_targets is not None else None
        if targets is not None:
            targets = targets.to(self.device)
            geo = cfg.geometry
            w = geo.weights(step, cfg.iterations)
            hard = None
            if targets.depth is not None and geo.hard_applies(step, cfg.iterations):
                hard = render_hard(view, geo.hard_stride)
            terms.update(
                L.geometric_losses(
                    targets,
                    out.raster.depth,
                    out.raster.normals,
                    w,
                    hard,
                    geo.hard_stride,
                    min_share=geo.min_prior_share,
                )
            )
        if self.extra_losses is not None:
            terms.update(self.extra_losses(step, out, view))
        return terms
