r"""Evaluation on the test split: image metrics, moving-object PSNR*, depth against ground truth.

- **PSNR**: mean over test images of the per-image PSNR of the full image (moving cars included),
  images clamped to ``[0, 1]`` (kornia ``psnr``); ``psnr_pooled`` is the PSNR of the MSE pooled
  over all test pixels.
- **PSNR\***: PSNR of the MSE pooled over the pixels of moving objects (instance ids of
  ``scene.tracks``, from the instance maps).
- **SSIM**: kornia's, 11×11 Gaussian window, mean over images.
- **Depth** (where the scene has ground-truth depth): AbsRel :math:`|d - d^*| / d^*` and
  :math:`\delta < 1.05` (fraction of pixels with :math:`\max(d/d^*, d^*/d) < 1.05`) of the
  rendered expected depth, on every pixel with ground truth (``all``), on the traffic sign
  (instances of class ``sign``) and on the upper facades (class ``building``, world height
  :math:`z > 5` m). A pixel where nothing is rendered counts as wrong.
- **LiDAR depth** (``lidar``, where the scene has LiDAR; real logs have no dense depth): the same
  AbsRel and :math:`\delta < 1.05`, the reference :math:`d^*` being the view's own frame's LiDAR
  sweep projected into it (:func:`~vadgs.data.lidar.lidar_depth_map`, the map the ``lidar`` loss
  term trains on: nearest camera-frame z per pixel, moving objects included), on the pixels a point
  falls on. A test frame's sweep is never used in training (initialisation, the ``lidar`` loss and
  VAD-GS's visibility read the training frames' sweeps only); it is taken at that frame's time,
  the moving objects at their poses of the frame, as the render. Not compensated: the motion
  between the sweep and the image exposure (rolling shutter, a spinning LiDAR's sweep time). Not
  removed: the parallax between the LiDAR and the camera (points the LiDAR sees but hidden from
  the camera behind a nearer surface are scored against it). And a pixel's nearest point stands
  for the whole pixel. So the reference has a floor: the dense ground truth itself scores δ < 1.05
  0.969 against street_a's LiDAR at 480×288 and 240×144, 0.889 at 120×72 (``docs/evaluation.md``).
  A scene with dense ground truth keeps its other groups unchanged and gets ``lidar`` in
  addition; a view whose frame has no sweep (or an empty one) adds nothing; novel views are
  scored against the sweep of their frame.
- **LPIPS**: only when the ``lpips`` package and its weights are available locally; otherwise
  the result says why it was skipped.
- **Appearance**: a model trained with a per-camera colour transform
  (:class:`~vadgs.train.appearance.AppearanceModel`, ``TrainConfig.appearance``) is evaluated on
  its renders corrected by the transform of the view's camera; the per-frame residuals, learned
  only on training images, are unknown for held-out frames and not used. The image metrics of
  the uncorrected renders are kept in :attr:`EvalMetrics.uncorrected`.

Novel views (:attr:`~vadgs.data.Scene.novel_views`, e.g. the test frames seen again from the rig
shifted 2 m sideways) are evaluated the same way, one :class:`EvalMetrics` per group, by
:func:`evaluate_split` with ``split="novel"``; each view is rendered at its own pose with the
moving objects at their poses of the view's frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from kornia.metrics import psnr as kpsnr
from kornia.metrics import ssim as kssim

from vadgs.data.lidar import lidar_depth_map
from vadgs.data.scene import Scene
from vadgs.geometry.camera import backproject_depth, invert_rigid
from vadgs.render import RasterConfig
from vadgs.train.appearance import AppearanceModel, correct_view
from vadgs.train.model import GaussianModel, ModelRender

__all__ = [
    "SPLITS",
    "EvalMetrics",
    "evaluate",
    "evaluate_split",
    "lpips_available",
    "render_test_view",
    "save_test_panels",
    "split_views",
    "view_name",
]

#: The splits :func:`evaluate_split` knows: the test views, and the novel (extrapolated) views by group.
SPLITS = ("test", "novel")


@dataclass(frozen=True)
class EvalMetrics:
    """Test metrics of a model (see the module docstring for the definitions).

    Attributes:
        psnr, psnr_pooled, psnr_star, ssim: image metrics (``psnr_star`` None without moving-object pixels).
        lpips: None when skipped; ``lpips_note`` says why.
        num_gaussians: the model's size; ``num_views``: test views evaluated.
        depth: ``{region: {"absrel", "delta_1.05", "pixels"}}`` for ``all``, ``sign``,
            ``upper_facade`` (against dense ground truth) and ``lidar`` (against the views' own
            LiDAR sweeps); regions without pixels are left out; empty without either.
        per_view: ``[{"view", "image", "psnr", "ssim"}]`` (``image``: :func:`view_name`; and
            ``"psnr_uncorrected"``, ``"ssim_uncorrected"`` with an appearance model).
        uncorrected: with an appearance model, ``psnr``, ``psnr_pooled``, ``psnr_star`` and
            ``ssim`` of the renders *without* its colour transform (the fields above are of the
            corrected renders); empty without one.
    """

    psnr: float
    psnr_pooled: float
    psnr_star: float | None
    ssim: float
    lpips: float | None
    lpips_note: str
    num_gaussians: int
    num_views: int
    depth: dict[str, dict[str, float]] = field(default_factory=dict)
    per_view: list[dict[str, float]] = field(default_factory=list)
    uncorrected: dict[str, float | None] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for JSON."""
        return asdict(self)


def view_name(scene: Scene, view: int) -> str:
    """A view's image as a person finds it: its path relative to the scene folder, or its camera and frame.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> view_name(load_scene(sample_scene_path()), 0)
        'images/front/016.png'
    """
    vi = scene.views[view]
    if vi.image is None:
        return f"{vi.camera}/{vi.frame}"
    if scene.root is not None and Path(vi.image).is_relative_to(scene.root):
        return Path(vi.image).relative_to(scene.root).as_posix()
    return Path(vi.image).name


def lpips_available() -> tuple[bool, str]:
    """Whether LPIPS can run offline, and why not."""
    try:
        import lpips  # noqa: F401
    except ImportError:
        return False, "LPIPS skipped: the 'lpips' package is not installed (no local weights)"
    return True, ""


def render_test_view(
    model: GaussianModel, scene: Scene, view: int, config: RasterConfig | None = None
) -> ModelRender:
    """Render one view of the scene at its frame (no gradient), on the model's device."""
    cams = scene.cameras([view])
    frame = scene.view_frame_position(view)
    dev = model.params["means"].device
    with torch.no_grad():
        return model.render(cams.world_to_cam.to(dev), cams.K.to(dev), cams.image_size, frame, config)


def _psnr(mse: float) -> float:
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


class _ImageStats:
    """PSNR, pooled PSNR, PSNR* and SSIM accumulated over the views of one evaluation."""

    def __init__(self) -> None:
        self.psnrs: list[float] = []
        self.ssims: list[float] = []
        self.se_all = self.n_all = self.se_dyn = self.n_dyn = 0.0

    def add(self, pred: torch.Tensor, gt: torch.Tensor, dynamic: torch.Tensor | None) -> tuple[float, float]:
        """Add one view (``pred`` clamped, ``dynamic`` a ``(1, H, W)`` mask or None); its PSNR and SSIM."""
        p = float(kpsnr(pred, gt, 1.0))
        s = float(kssim(pred, gt, 11).mean())
        self.psnrs.append(p)
        self.ssims.append(s)
        err = (pred - gt) ** 2
        self.se_all += float(err.sum())
        self.n_all += err.numel()
        if dynamic is not None:
            dyn = dynamic[:, None].expand_as(err)
            self.se_dyn += float(err[dyn].sum())
            self.n_dyn += float(dyn.sum())
        return p, s

    def summary(self) -> dict[str, Any]:  # floats; psnr_star None without moving-object pixels
        return {
            "psnr": round(sum(self.psnrs) / len(self.psnrs), 4),
            "psnr_pooled": round(_psnr(self.se_all / self.n_all), 4),
            "psnr_star": round(_psnr(self.se_dyn / self.n_dyn), 4) if self.n_dyn else None,
            "ssim": round(sum(self.ssims) / len(self.ssims), 4),
        }


class _DepthStats:
    """AbsRel and δ < 1.05 of rendered depth against a reference, pooled over the views, by region."""

    def __init__(self) -> None:
        self.acc: dict[str, list[float]] = {}

    def add(self, name: str, depth: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> None:
        """Add the pixels of ``mask`` (reference > 0 there); none: nothing (the region is left out)."""
        if not bool(mask.any()):
            return
        dd, gg = depth[mask], ref[mask]
        ratio = torch.maximum(dd / gg, gg / dd.clamp(min=1e-9))
        acc = self.acc.setdefault(name, [0.0, 0.0, 0.0])
        acc[0] += float(((dd - gg).abs() / gg).sum())
        acc[1] += float((ratio < 1.05).sum())
        acc[2] += float(mask.sum())

    def summary(self) -> dict[str, dict[str, float]]:
        return {
            k: {"absrel": round(a[0] / a[2], 5), "delta_1.05": round(a[1] / a[2], 5), "pixels": int(a[2])}
            for k, a in self.acc.items()
        }


def _lidar_depth(scene: Scene, view: int) -> torch.Tensor | None:
    """The view's own sweep projected into it (:func:`lidar_depth_map`), None without one."""
    if scene.lidar_loader is None:
        return None
    try:
        return lidar_depth_map(scene, view)
    except FileNotFoundError:  # a frame without a sweep, as the lidar loss term skips it
        return None


@torch.no_grad()
def evaluate(
    model: GaussianModel,
    scene: Scene,
    views: Sequence[int] | None = None,
    config: RasterConfig | None = None,
    progress: bool = False,
    with_lpips: bool = True,
    appearance: AppearanceModel | None = None,
) -> EvalMetrics:
    """Evaluate a model on test views.

    Args:
        model: the trained model.
        scene: its scene.
        views: views to evaluate (default ``scene.test_views``).
        config: rasterizer settings.
        progress: tqdm bar.
        with_lpips: compute LPIPS when available.
        appearance: the run's appearance model (``Trainer.appearance``): the metrics are of the
            renders corrected by the transform of each view's camera (without per-frame
            residuals: the frames are held out), and :attr:`EvalMetrics.uncorrected` holds the
            image metrics of the raw renders. LPIPS is of the corrected renders.

    Returns:
        :class:`EvalMetrics`.

    Raises:
        ValueError: when there is no view to evaluate, or ``appearance`` has another number of
            cameras than the scene.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> from vadgs.train.init import InitConfig, init_gaussians
        >>> scene = load_scene(sample_scene_path(), scale=0.25)
        >>> model = init_gaussians(scene, InitConfig(voxel_size=1.0, max_points=500, sh_degree=0))
        >>> m = evaluate(model, scene)
        >>> m.num_views, sorted(m.depth)
        (6, ['all', 'lidar', 'sign', 'upper_facade'])
    """
    from tqdm import tqdm

    views = list(scene.test_views if views is None else views)
    if not views:
        raise ValueError(f"scene {scene.name!r}: no test views to evaluate")
    if appearance is not None and appearance.num_cameras != len(scene.camera_names):
        raise ValueError(
            f"appearance: expected a model of the scene's {len(scene.camera_names)} cameras, "
            f"got {appearance.num_cameras}"
        )
    dynamic_ids = torch.tensor(sorted(scene.tracks), dtype=torch.long)
    sign_ids = torch.tensor(scene.instance_ids("sign"), dtype=torch.long)
    building_ids = torch.tensor(scene.instance_ids("building"), dtype=torch.long)
    ok_lpips, note = lpips_available() if with_lpips else (False, "LPIPS not requested")
    lpips_fn = None
    if ok_lpips:
        try:
            import lpips

            lpips_fn = lpips.LPIPS(net="alex", verbose=False)
        except Exception as e:
            ok_lpips, note = False, f"LPIPS skipped: could not load its weights locally ({type(e).__name__})"
    lp, per_view = [], []
    stats, raw_stats = _ImageStats(), _ImageStats()
    depth_stats = _DepthStats()
    for v in tqdm(views, disable=not progress, desc="eval"):
        out = render_test_view(model, scene, v, config)
        gt = scene.load_images([v])
        vi = scene.views[v]
        inst = scene.load_instances([v]) if vi.instances is not None else None
        dynamic = torch.isin(inst, dynamic_ids) if inst is not None and dynamic_ids.numel() else None
        color = correct_view(appearance, scene, v, out.color)
        pred = color.clamp(0, 1).cpu()  # the metrics on the CPU, beside the ground truth
        depth_map = out.raster.depth.cpu()
        p, s = stats.add(pred, gt, dynamic)
        per_view.append({"view": v, "image": view_name(scene, v), "psnr": round(p, 4), "ssim": round(s, 4)})
        if appearance is not None:
            p, s = raw_stats.add(out.color.clamp(0, 1).cpu(), gt, dynamic)
            per_view[-1].update(psnr_uncorrected=round(p, 4), ssim_uncorrected=round(s, 4))
        if lpips_fn is not None:
            lp.append(float(lpips_fn(pred * 2 - 1, gt * 2 - 1).mean()))
        if vi.depth is not None:
            gtd = scene.load_depths([v])
            valid = gtd > 0
            regions = {"all": valid}
            if inst is not None:
                if sign_ids.numel():
                    regions["sign"] = valid & torch.isin(inst, sign_ids)[:, None]
                if building_ids.numel():
                    cams = scene.cameras([v])
                    world = backproject_depth(gtd, cams.K, invert_rigid(cams.world_to_cam))
                    regions["upper_facade"] = (
                        valid & torch.isin(inst, building_ids)[:, None] & (world[:, 2:3] > 5.0)
                    )
            for name, mask in regions.items():
                depth_stats.add(name, depth_map, gtd, mask)
        lid = _lidar_depth(scene, v)
        if lid is not None:
            depth_stats.add("lidar", depth_map, lid.cpu(), lid > 0)
    depth = depth_stats.summary()
    return EvalMetrics(
        **stats.summary(),
        lpips=round(sum(lp) / len(lp), 4) if lp else None,
        lpips_note="" if lp else note,
        num_gaussians=model.num_gaussians,
        num_views=len(views),
        depth=depth,
        per_view=per_view,
        uncorrected=raw_stats.summary() if appearance is not None else {},
    )


def split_views(scene: Scene, split: str) -> dict[str, list[int]]:
    """The views of a split, by group: ``{"test": [...]}`` or ``{"shift+2.0": [...], ...}``.

    Raises:
        ValueError: for an unknown split, or one the scene has no views of.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> {k: len(v) for k, v in split_views(load_scene(sample_scene_path()), "test").items()}
        {'test': 6}
    """
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
    groups = {"test": scene.test_views} if split == "test" else scene.novel_groups()
    if not any(groups.values()):
        raise ValueError(f"scene {scene.name!r}: no {split} views (scene.json has no {split} views)")
    return groups


def evaluate_split(
    model: GaussianModel,
    scene: Scene,
    split: str = "test",
    config: RasterConfig | None = None,
    progress: bool = False,
    with_lpips: bool = True,
    appearance: AppearanceModel | None = None,
) -> dict[str, EvalMetrics]:
    """Evaluate a model on a split, one :class:`EvalMetrics` per group of :func:`split_views`.

    Args:
        model: the trained model.
        scene: its scene.
        split: ``"test"`` (one group, ``"test"``) or ``"novel"`` (one group per novel-view group,
            e.g. ``"shift+2.0"`` and ``"shift-2.0"``).
        config: rasterizer settings.
        progress: tqdm bar.
        with_lpips: compute LPIPS when available.
        appearance: the run's appearance model, if any (see :func:`evaluate`).

    Returns:
        Group name → :class:`EvalMetrics` (see :func:`evaluate`).

    Raises:
        ValueError: for an unknown split or one without views.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> from vadgs.train.init import InitConfig, init_gaussians
        >>> scene = load_scene(sample_scene_path(), scale=0.25)
        >>> model = init_gaussians(scene, InitConfig(voxel_size=1.0, max_points=500, sh_degree=0))
        >>> {k: m.num_views for k, m in evaluate_split(model, scene, "test").items()}
        {'test': 6}
    """
    return {
        name: evaluate(model, scene, views, config, progress, with_lpips, appearance)
        for name, views in split_views(scene, split).items()
    }


@torch.no_grad()
def save_test_panels(
    model: GaussianModel,
    scene: Scene,
    out_dir: str | Path,
    views: Sequence[int] | None = None,
    config: RasterConfig | None = None,
    progress: bool = False,
    appearance: AppearanceModel | None = None,
) -> list[Path]:
    """Write one PNG per view: render, ground truth, error, depth (and GT depth), normals.

    With ``appearance`` (the run's :class:`~vadgs.train.appearance.AppearanceModel`), the render
    is corrected by the transform of the view's camera, as in :func:`evaluate`.

    The file names are ``view<index>_<camera>_<frame>.png``, the camera's name made safe
    (:func:`vadgs.io.safe_filename`: a name with ``/`` or ``..`` cannot leave ``out_dir``).

    Returns:
        The written paths.
    """
    from tqdm import tqdm

    from vadgs.io import safe_filename
    from vadgs.viz import colorize_depth, image_to_uint8, save_panel

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    views = list(scene.test_views if views is None else views)
    paths = []
    for v in tqdm(views, disable=not progress, desc="render"):
        out = render_test_view(model, scene, v, config)
        color = correct_view(appearance, scene, v, out.color)
        pred = color.clamp(0, 1)[0]
        gt = scene.load_images([v])[0]
        err = (pred - gt).abs().mean(0, keepdim=True).clamp(max=0.25) * 4
        p = float(kpsnr(pred[None], gt[None], 1.0))
        normals = (-out.raster.normals[0] * 0.5 + 0.5) * (out.raster.normals[0].abs().sum(0) > 0)
        gtd = scene.load_depths([v])[0, 0] if scene.views[v].depth is not None else None
        vmax = float(gtd[gtd > 0].quantile(0.98)) if gtd is not None and bool((gtd > 0).any()) else None
        images = [image_to_uint8(pred), image_to_uint8(gt), image_to_uint8(err.expand(3, -1, -1)),
                  colorize_depth(out.raster.depth[0, 0], None, vmax), image_to_uint8(normals)]  # fmt: skip
        titles = [
            f"render ({p:.2f} dB)",
            "ground truth",
            "|error| (x4)",
            "rendered depth",
            "rendered normals",
        ]
        if gtd is not None:
            images.insert(4, colorize_depth(gtd, None, vmax))
            titles.insert(4, "ground-truth depth")
        vi = scene.views[v]
        name = f"view{v:03d}_{safe_filename(vi.camera)}_{vi.frame:03d}.png"
        paths.append(save_panel(images, titles, out_dir / name, columns=3))
    return paths
