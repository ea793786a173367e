"""The training loop: configuration, optimisation, checkpoints and exact resume.

:class:`Trainer` fits a :class:`~vadgs.train.model.GaussianModel` to a scene's training views,
sampled without replacement (:class:`~vadgs.train.sampler.ViewSampler`), with the colour loss,
an optional sparse LiDAR depth term, the paper's geometric losses on priors
(:class:`~vadgs.train.losses.GeometryTargets` from a provider or from a strategy that implements
:class:`~vadgs.train.strategy.GeometryPriors`, through :func:`~vadgs.train.losses.geometric_losses`),
extra losses from a hook, and a densification :class:`~vadgs.train.strategy.Strategy`: the standard
one, VAD-GS's when ``TrainConfig.vad`` is set, or any given one. The trainer hands strategies
gsplat's arguments (``model.params``, the optimizer, the state, the step, the render's ``info``) and,
for VAD-GS, a :class:`~vadgs.train.vad.StrategyContext`; strategies never see the trainer.

Checkpoints (``checkpoint.pt`` in the run folder) hold the step, the configuration, the scene
reference, the model, Adam's state, the strategy state, the sampler and every random generator, so
``resume`` continues *exactly* (the same parameters as an uninterrupted run). They are written
atomically (temporary file + rename) every ``checkpoint_every`` steps, at the end, and when the
run is interrupted (SIGINT / SIGTERM stop the loop at the end of the current step). A non-finite
loss or parameter raises :class:`NonFiniteLossError` naming the step; nothing is saved over the last
good checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import random
import resource
import signal
import threading
import time
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch

from vadgs.checks import checks_enabled
from vadgs.data.scene import Scene
from vadgs.render import RasterConfig
from vadgs.train import losses as L
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.losses import GeometryTargets
from vadgs.train.model import PER_GAUSSIAN, GaussianModel, ModelRender
from vadgs.train.ops import make_optimizer
from vadgs.train.sampler import ViewSampler
from vadgs.train.strategy import DefaultStrategy, DefaultStrategyConfig, GeometryPriors, Strategy
from vadgs.train.vad import StrategyContext, ViewRender, VisibilityAwareDensification, VisibilityDensifyConfig

__all__ = [
    "CHECKPOINT_NAME",
    "GeometryTargets",
    "LearningRates",
    "NonFiniteLossError",
    "TrainConfig",
    "TrainResult",
    "Trainer",
    "lidar_depth_map",
    "load_checkpoint",
    "open_scene",
]

CHECKPOINT_NAME = "checkpoint.pt"
_FORMAT = "vadgs-train-checkpoint"
_VERSION = 1


class NonFiniteLossError(FloatingPointError):
    """A loss or parameter became NaN / infinite; ``step`` says when."""

    def __init__(self, step: int, what: str) -> None:
        super().__init__(f"non-finite value at step {step}: {what}")
        self.step = step


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates (3DGS's).

    ``means`` decays exponentially to ``means_final``; both are multiplied by the scene scale.
    """

    means: float = 1.6e-4
    means_final: float = 1.6e-6
    quats: float = 1e-3
    log_scales: float = 5e-3
    opacity_logits: float = 5e-2
    sh_dc: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20
    sky: float = 1e-2


@dataclass(frozen=True)
class TrainConfig:
    """Everything a run depends on.

    Composed frozen dataclasses; JSON round trip with :meth:`to_dict` / :meth:`from_dict`.

    Attributes:
        iterations: optimisation steps (one view each).
        seed: seeds the sampler, the split noise and torch.
        init: :class:`~vadgs.train.init.InitConfig`.
        strategy: :class:`~vadgs.train.strategy.DefaultStrategyConfig`.
        raster: :class:`~vadgs.render.RasterConfig`.
        lr: :class:`LearningRates`.
        ssim_weight: λ of the colour loss.
        sh_degree_interval: the active SH degree grows by one every this many steps.
        lambda_lidar: weight of the relative L1 between the rendered depth and the view's own
            LiDAR sweep projected into it (0 disables; the baseline's only geometric term).
        lambda_normal, lambda_hard, lambda_soft, hard_until: the paper's geometric loss weights
            (applied to priors: VAD-GS's, or a :class:`GeometryTargets` provider's).
        hard_every: the hard depth loss (an extra render with opacities fixed to 1) is applied on
            every ``hard_every``-th step only, to bound its cost (1: the paper's schedule).
        vad: :class:`~vadgs.train.vad.VisibilityDensifyConfig` to train with VAD-GS's
            visibility-aware densification (extending ``strategy``); None: standard ADC only.
            Stored in checkpoints: a resumed run continues with the same strategy.
        device: where the model, images and losses live (``"cpu"``, ``"cuda"``, ``"cuda:1"``);
            the scene and its visibility index stay on the CPU.
        checkpoint_every: steps between checkpoints (0 = only at the end / on interruption).
        log_every: steps between log lines in ``log.jsonl``.
        max_minutes: stop (and checkpoint) after this much training time (0 = no limit).
        threads: ``torch.set_num_threads`` (0 = leave).
    """

    iterations: int = 3000
    seed: int = 0
    init: InitConfig = field(default_factory=InitConfig)
    strategy: DefaultStrategyConfig = field(default_factory=DefaultStrategyConfig)
    raster: RasterConfig = field(default_factory=RasterConfig)
    lr: LearningRates = field(default_factory=LearningRates)
    ssim_weight: float = 0.2
    sh_degree_interval: int = 1000
    lambda_lidar: float = 0.05
    lambda_normal: float = 0.02
    lambda_hard: float = 0.1
    lambda_soft: float = 0.1
    hard_until: float = 0.8
    hard_every: int = 4
    vad: VisibilityDensifyConfig | None = None
    device: str = "cpu"
    checkpoint_every: int = 500
    log_every: int = 50
    max_minutes: float = 0.0
    threads: int = 0

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ValueError(f"iterations: expected >= 0, got {self.iterations}")
        if self.sh_degree_interval < 1 or self.log_every < 1 or self.hard_every < 1:
            raise ValueError(
                "sh_degree_interval, log_every, hard_every: expected >= 1, got "
                f"{self.sh_degree_interval}, {self.log_every}, {self.hard_every}"
            )
        try:
            torch.device(self.device)
        except (RuntimeError, TypeError):
            raise ValueError(
                f"device: expected a torch device such as 'cpu' or 'cuda', got {self.device!r}"
            ) from None

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON-serialisable)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`, type-checked (:func:`vadgs.config.config_from_dict`).

        Raises:
            ValueError: on an unknown key or a value of the wrong type, naming the field's path
                (``config.strategy.refine_every: expected int, got str 'abc'``).

        Example:
            >>> c = TrainConfig(iterations=10)
            >>> TrainConfig.from_dict(c.to_dict()) == c
            True
        """
        from vadgs.config import config_from_dict

        return config_from_dict(cls, d)

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with changes; nested fields as ``"init.max_points"``."""
        flat = self.to_dict()
        for k, v in changes.items():
            parts = k.split(".")
            target = flat
            for p in parts[:-1]:
                target = target[p]
            if parts[-1] not in target:
                raise ValueError(f"config: unknown field {k!r}")
            target[parts[-1]] = v
        return TrainConfig.from_dict(flat)


def _from_dict(cls: type, d: Any, where: str) -> Any:
    """Build a (nested) frozen config dataclass from a plain dict, naming bad or unknown keys."""
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected an object with keys of {cls.__name__}, got {d!r}")
    known = {f.name for f in dataclasses.fields(cls)}
    bad = set(d) - known
    if bad:
        raise ValueError(f"{where}: unknown keys {sorted(bad)}")
    hints = typing.get_type_hints(cls)
    kw: dict[str, Any] = {}
    for k, v in d.items():
        kw[k] = _from_value(hints[k], v, f"{where}.{k}")
    try:
        return cls(**kw)
    except TypeError as e:
        raise ValueError(f"{where}: {e}") from None


def _from_value(tp: Any, v: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if v is None:
            return None
        return _from_value(args[0], v, where) if len(args) == 1 else v
    if dataclasses.is_dataclass(tp):
        return v if isinstance(v, tp) else _from_dict(tp, v, where)
    if origin is tuple and isinstance(v, (list, tuple)):
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_value(args[0], x, where) for x in v)
        return tuple(_from_value(a, x, where) for a, x in zip(args, v))
    return v


class TrainResult(NamedTuple):
    """What :meth:`Trainer.train` returns.

    Attributes:
        step: steps done in total.
        completed: True when ``iterations`` were reached, False when interrupted / out of time.
        reason: ``"done"``, ``"interrupted"`` or ``"time limit"``.
        train_s: training seconds, all sessions of the run together.
        peak_rss_mb: peak resident memory of the process (MiB).
        num_gaussians: final count.
    """

    step: int
    completed: bool
    reason: str
    train_s: float
    peak_rss_mb: float
    num_gaussians: int


def open_scene(ref: dict[str, Any]) -> Scene:
    """Load the scene a run refers to: ``{"kind": "benchmark" | "dgp", "path": ..., "scale": ..., ...}``.

    ``dgp`` references may carry ``cameras`` and ``test_frames``.
    """
    from vadgs.data import load_dgp, load_scene

    kind = ref.get("kind", "benchmark")
    if kind == "benchmark":
        return load_scene(ref["path"], scale=float(ref.get("scale", 1.0)))
    if kind == "dgp":
        return load_dgp(
            ref["path"],
            cameras=ref.get("cameras"),
            scale=float(ref.get("scale", 1.0)),
            test_frames=tuple(ref.get("test_frames", ())),
        )
    raise ValueError(f"scene reference: unknown kind {kind!r}")


def lidar_depth_map(scene: Scene, view: int) -> torch.Tensor:
    """The view's own LiDAR sweep projected into it: ``(1, 1, H, W)`` nearest z per pixel, 0 elsewhere.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> d = lidar_depth_map(scene, 0)
        >>> d.shape, bool((d > 0).any())
        (torch.Size([1, 1, 144, 240]), True)
    """
    from vadgs.geometry.camera import project_points

    v = scene.views[view]
    cams = scene.cameras([view])
    h, w = cams.image_size
    pts = scene.lidar(v.frame).points
    uv, z = project_points(pts[None], cams.K, cams.world_to_cam)
    u, vv = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
    ok = (z[0] > 0.1) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
    flat = vv[ok] * w + u[ok]
    depth = torch.full((h * w,), float("inf"))
    depth.scatter_reduce_(0, flat, z[0][ok], reduce="amin")
    depth[torch.isinf(depth)] = 0.0
    return depth.reshape(1, 1, h, w)


def _scene_scale(scene: Scene, views: list[int]) -> float:
    centres = torch.stack([scene.views[v].cam_to_world[:3, 3] for v in views])
    return float((centres - centres.mean(0)).norm(dim=-1).max() * 1.1) or 1.0


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :class:`Trainer` (``weights_only`` unpickling).

    Raises:
        FileNotFoundError: if it does not exist.
        ValueError: if it is corrupt, truncated or not a vadgs training checkpoint.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"checkpoint {path} is corrupt or unreadable ({type(e).__name__}: {e})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != _FORMAT:
        raise ValueError(f"checkpoint {path}: not a vadgs training checkpoint")
    if int(ckpt.get("version", -1)) != _VERSION:
        raise ValueError(f"checkpoint {path}: unsupported version {ckpt.get('version')}")
    missing = [
        k
        for k in ("step", "config", "model", "model_extra", "optimizer", "strategy_state", "sampler", "rng")
        if k not in ckpt
    ]
    if missing:
        raise ValueError(f"checkpoint {path}: missing entries {missing}")
    return ckpt


class Trainer:
    """Train a :class:`~vadgs.train.model.GaussianModel` on a scene.

    Args:
        scene: the scene (training views = ``scene.train_views``).
        config: :class:`TrainConfig`.
        out_dir: run folder (checkpoints, ``log.jsonl``, ``config.json``); None = no files.
        scene_ref: how to reload the scene (stored in checkpoints; see :func:`open_scene`).
        strategy: a densification strategy to use instead of the configured one (default:
            :class:`~vadgs.train.vad.VisibilityAwareDensification` with ``config.vad`` when set,
            extending :class:`~vadgs.train.strategy.DefaultStrategy` with ``config.strategy``;
            else that standard strategy alone). Given strategies are not stored in checkpoints:
            pass them again to :meth:`from_checkpoint`.
        geometry_targets: ``view -> GeometryTargets | None``: priors for the paper's normal / hard /
            soft depth losses (default: the strategy's, when it implements
            :class:`~vadgs.train.strategy.GeometryPriors`, as VAD-GS does).
        extra_losses: ``(step, render, view) -> {name: scalar}`` added to the loss as given.
        colmap_points: SfM points for the initialisation.
        model: start from this model instead of :func:`~vadgs.train.init.init_gaussians`.
        progress: show a tqdm progress bar.
        callback: ``(trainer, step)`` called after every step (tests use it to interrupt).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path(), scale=0.25)
        >>> cfg = TrainConfig(iterations=2, init=InitConfig(voxel_size=1.0, max_points=500, sh_degree=0))
        >>> result = Trainer(scene, cfg, progress=False).train()
        >>> result.step, result.completed
        (2, True)
    """

    def __init__(
        self,
        scene: Scene,
        config: TrainConfig | None = None,
        out_dir: str | Path | None = None,
        scene_ref: dict[str, Any] | None = None,
        strategy: Strategy | None = None,
        geometry_targets: Callable[[int], GeometryTargets | None] | None = None,
        extra_losses: Callable[[int, ModelRender, int], dict[str, torch.Tensor]] | None = None,
        colmap_points: Any = None,
        model: GaussianModel | None = None,
        progress: bool = True,
        callback: Callable[[Trainer, int], None] | None = None,
    ) -> None:
        self.scene = scene
        self.config = config or TrainConfig()
        self.out_dir = Path(out_dir) if out_dir is not None else None
        if scene_ref is None and scene.root is not None and (Path(scene.root) / "scene.json").is_file():
            scene_ref = {"kind": "benchmark", "path": str(Path(scene.root).resolve()), "scale": scene.scale}
        self.scene_ref = scene_ref or {}
        self.device = torch.device(self.config.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device: {self.config.device!r} requested but CUDA is not available")
        self.geometry_targets = geometry_targets
        self.extra_losses = extra_losses
        self.progress = progress
        self.callback = callback
        if self.config.threads:
            torch.set_num_threads(self.config.threads)
        self.train_views = list(scene.train_views)
        if not self.train_views:
            raise ValueError(f"scene {scene.name!r}: no training views")
        torch.manual_seed(self.config.seed)
        random.seed(self.config.seed)
        self.generator = torch.Generator().manual_seed(self.config.seed + 1)
        self.sampler = ViewSampler(self.train_views, seed=self.config.seed)
        model = model if model is not None else init_gaussians(scene, self.config.init, colmap_points)
        self.model = model.to(self.device)
        self.scene_scale = _scene_scale(scene, self.train_views)
        self.optimizer = make_optimizer(self.model, self._lrs(0))
        self.strategy = strategy if strategy is not None else self._configured_strategy()
        self.state = self.strategy.initialize_state(self.scene_scale)
        self.step = 0
        self.train_s = 0.0
        self._images: dict[int, torch.Tensor] = {}
        self._lidar: dict[int, tuple[torch.Tensor, bool]] = {}
        self._stop = False

    def _configured_strategy(self) -> Strategy:
        base = DefaultStrategy(self.config.strategy)
        if self.config.vad is None:
            return base
        return VisibilityAwareDensification(self.scene, self.strategy_context(), self.config.vad, base=base)

    def strategy_context(self) -> StrategyContext:
        """What a strategy may know of this loop: render a view, step counts, the generator, nodes."""
        return StrategyContext(
            render=self.render_geometry,
            total_steps=self.config.iterations,
            steps_per_cycle=len(self.sampler),
            generator=self.generator,
            track_nodes={t: k for k, t in enumerate(self.model.track_ids)},
        )

    # -- resume ---------------------------------------------------------------------------------------

    @classmethod
    def from_checkpoint(cls, path: str | Path, scene: Scene | None = None, **kwargs: Any) -> Trainer:
        """Continue a run from its checkpoint (exactly: RNGs, sampler, optimizer, strategy state).

        Args:
            path: the checkpoint or its run folder.
            scene: the scene (default: reloaded from the stored reference).
            **kwargs: further :class:`Trainer` arguments (``out_dir`` defaults to the checkpoint's folder).

        Raises:
            ValueError: on a corrupt checkpoint, or without ``scene`` when the checkpoint stores no
                scene reference.
        """
        path = Path(path)
        ckpt = load_checkpoint(path)
        config = TrainConfig.from_dict(ckpt["config"])
        if scene is None:
            if not ckpt["scene_ref"].get("path"):
                raise ValueError(
                    f"checkpoint {path}: no scene reference stored (trained from an in-memory scene); "
                    "pass scene="
                )
            scene = open_scene(ckpt["scene_ref"])
        model = GaussianModel.from_state(ckpt["model"], ckpt["model_extra"])
        kwargs.setdefault("out_dir", path if path.is_dir() else path.parent)
        kwargs.setdefault("scene_ref", ckpt["scene_ref"])
        trainer = cls(scene, config, model=model, **kwargs)
        trainer.optimizer.load_state_dict(ckpt["optimizer"])
        trainer.state = ckpt["strategy_state"]
        trainer.sampler.load_state_dict(ckpt["sampler"])
        torch.set_rng_state(ckpt["rng"]["torch"])
        trainer.generator.set_state(ckpt["rng"]["generator"])
        random.setstate(_to_py_random_state(ckpt["rng"]["python"]))
        trainer.step = int(ckpt["step"])
        trainer.train_s = float(ckpt.get("train_s", 0.0))
        return trainer

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint content."""
        return {
            "format": _FORMAT,
            "version": _VERSION,
            "step": self.step,
            "config": self.config.to_dict(),
            "scene_ref": self.scene_ref,
            "model": self.model.state_dict(),
            "model_extra": self.model.extra_state(),
            "optimizer": self.optimizer.state_dict(),
            "strategy_state": self.state,
            "sampler": self.sampler.state_dict(),
            "rng": {
                "torch": torch.get_rng_state(),
                "generator": self.generator.get_state(),
                "python": _from_py_random_state(random.getstate()),
            },
            "train_s": self.train_s,
        }

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        """Write the checkpoint atomically (``out_dir/checkpoint.pt`` by default)."""
        if path is None:
            if self.out_dir is None:
                raise ValueError("save_checkpoint: no path and no out_dir")
            path = self.out_dir / CHECKPOINT_NAME
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_save(self.state_dict(), path)
        return path

    def request_stop(self) -> None:
        """Stop at the end of the current step (and checkpoint); what SIGINT / SIGTERM do."""
        self._stop = True

    # -- the loop -------------------------------------------------------------------------------------

    def _lrs(self, step: int) -> dict[str, float]:
        lr = self.config.lr
        t = min(step / max(self.config.iterations, 1), 1.0)
        means = math.exp((1 - t) * math.log(lr.means) + t * math.log(lr.means_final))
        scale = getattr(self, "scene_scale", 1.0)
        out = {k: getattr(lr, k) for k in PER_GAUSSIAN if k != "means"}
        out["means"] = means * scale
        out["sky"] = lr.sky
        return out

    def image(self, view: int) -> torch.Tensor:
        """Training image ``(1, 3, H, W)`` (cached)."""
        if view not in self._images:
            self._images[view] = self.scene.load_images([view]).to(self.device)
        return self._images[view]

    def lidar_depth(self, view: int) -> torch.Tensor | None:
        """Sparse LiDAR depth of a view on the trainer's device (cached), None without LiDAR there."""
        if self.scene.lidar_loader is None:
            return None
        if view not in self._lidar:
            try:
                d = lidar_depth_map(self.scene, view)
            except FileNotFoundError:
                d = torch.zeros(1, 1, *self.scene.image_size(view))
            self._lidar[view] = (d.to(self.device), bool((d > 0).any()))  # decided once, not per step
        depth, any_point = self._lidar[view]
        return depth if any_point else None

    def render_view(self, view: int, **kwargs: Any) -> ModelRender:
        """Render a scene view with the current model (on the trainer's device)."""
        cams = self.scene.cameras([view])
        frame = self.scene.view_frame_position(view)
        return self.model.render(
            cams.world_to_cam.to(self.device),
            cams.K.to(self.device),
            cams.image_size,
            frame,
            self.config.raster,
            **kwargs,
        )

    @torch.no_grad()
    def render_geometry(self, view: int) -> ViewRender:
        """Depth, opacity and normals of a view, without gradient (a strategy's ``render``)."""
        r = self.render_view(view).raster
        return ViewRender(r.depth[0], r.alpha[0], r.normals[0])

    def compute_losses(self, step: int, view: int, out: ModelRender) -> dict[str, torch.Tensor]:
        """Every loss term of a step (already weighted), by name."""
        cfg = self.config
        gt = self.image(view)
        terms = {"color": L.color_loss(out.color, gt, cfg.ssim_weight)}
        if cfg.lambda_lidar > 0:
            lid = self.lidar_depth(view)
            if lid is not None:
                terms["lidar"] = cfg.lambda_lidar * L.depth_loss(out.raster.depth, lid)
        targets = None
        if self.geometry_targets is not None:
            targets = self.geometry_targets(view)
        elif isinstance(self.strategy, GeometryPriors):
            targets = self.strategy.geometry_targets(self.state, view)
        if targets is not None:
            targets = targets.to(self.device)
            w = L.geometric_weights(
                step, cfg.iterations, cfg.lambda_normal, cfg.lambda_hard, cfg.lambda_soft, cfg.hard_until
            )
            hard = None
            if w["hard"] > 0 and targets.depth is not None and step % cfg.hard_every == 0:
                hard = self.render_view(view, opacity_override=1.0).raster.depth
            terms.update(L.geometric_losses(targets, out.raster.depth, out.raster.normals, w, hard))
        if self.extra_losses is not None:
            terms.update(self.extra_losses(step, out, view))
        return terms

    def train_step(self) -> dict[str, float]:
        """One optimisation step on the next sampled view; returns the loss terms as floats."""
        step = self.step
        cfg = self.config
        for g in self.optimizer.param_groups:
            g["lr"] = self._lrs(step)[g["name"]]
        self.model.active_sh_degree = min(step // cfg.sh_degree_interval, self.model.sh_degree)
        view = self.sampler.next()
        out = self.render_view(view)
        info = {
            "raster": out.raster,
            "ids": out.ids,
            "image_size": tuple(out.color.shape[-2:]),
            "view": view,
            "frame": self.scene.view_frame_position(view),
            "generator": self.generator,
        }
        params = self.model.params
        self.strategy.step_pre_backward(params, self.optimizer, self.state, step, info)
        terms = self.compute_losses(step, view, out)
        total = torch.stack([t.reshape(()) for t in terms.values()]).sum()
        if checks_enabled() and not bool(torch.isfinite(total)):
            bad = {k: float(v.detach()) for k, v in terms.items()}
            raise NonFiniteLossError(step, f"loss terms {bad} (view {view})")
        total.backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.strategy.step_post_backward(params, self.optimizer, self.state, step, info)
        if checks_enabled():
            for k in ("means", "log_scales", "opacity_logits", "sh_dc"):
                if not bool(torch.isfinite(self.model.params[k]).all()):
                    raise NonFiniteLossError(step, f"parameter {k!r} after the optimizer step")
        self.step = step + 1
        with torch.no_grad():
            mse = torch.mean((out.color.detach().clamp(0, 1) - self.image(view)) ** 2)
        res = {k: float(v.detach()) for k, v in terms.items()}
        res["total"] = float(total.detach())
        res["psnr"] = float(-10 * torch.log10(mse.clamp(min=1e-10)))
        if not math.isfinite(res["total"]):  # the floats above are read anyway: no extra sync
            raise NonFiniteLossError(
                step, f"loss terms { {k: v for k, v in res.items() if k != 'psnr'} } (view {view})"
            )
        return res

    def train(self) -> TrainResult:
        """Run to ``config.iterations`` (from the current step), checkpointing on the way.

        SIGINT / SIGTERM finish the current step, write the checkpoint and return with
        ``completed=False`` (a second SIGINT raises ``KeyboardInterrupt`` at once).

        Raises:
            NonFiniteLossError: on a NaN / infinite loss or parameter, naming the step.
        """
        from tqdm import tqdm

        cfg = self.config
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            (self.out_dir / "config.json").write_text(
                json.dumps({"config": cfg.to_dict(), "scene": self.scene_ref}, indent=2)
            )
        handlers = self._install_signal_handlers()
        reason = "done"
        bar = tqdm(
            total=cfg.iterations,
            initial=self.step,
            disable=not self.progress,
            desc="train",
            dynamic_ncols=True,
        )
        log = (self.out_dir / "log.jsonl").open("a") if self.out_dir is not None else None
        try:
            while self.step < cfg.iterations:
                t0 = time.perf_counter()
                res = self.train_step()
                self.train_s += time.perf_counter() - t0
                bar.update(1)
                for event in self.state.pop("pending_log", None) or []:
                    if log is not None:
                        log.write(json.dumps({"step": self.step, "event": event}, default=str) + "\n")
                        log.flush()
                    if self.progress and "summary" in event:
                        bar.write(f"step {self.step}: {event['summary']}")
                if self.step % cfg.log_every == 0 or self.step == 1:
                    bar.set_postfix(
                        loss=f"{res['total']:.4f}", psnr=f"{res['psnr']:.2f}", n=self.model.num_gaussians
                    )
                    if log is not None:
                        log.write(
                            json.dumps(
                                {
                                    "step": self.step,
                                    "n": self.model.num_gaussians,
                                    "train_s": round(self.train_s, 2),
                                    "refine": self.state.get("last_refine", {}),
                                    **{k: round(v, 6) for k, v in res.items()},
                                }
                            )
                            + "\n"
                        )
                        log.flush()
                if self.callback is not None:
                    self.callback(self, self.step)
                if self._stop:
                    reason = "interrupted"
                    break
                if cfg.max_minutes and self.train_s > cfg.max_minutes * 60:
                    reason = "time limit"
                    break
                if (
                    cfg.checkpoint_every
                    and self.step % cfg.checkpoint_every == 0
                    and self.out_dir is not None
                ):
                    self.save_checkpoint()
        finally:
            bar.close()
            if log is not None:
                log.close()
            self._restore_signal_handlers(handlers)
        if self.out_dir is not None:
            self.save_checkpoint()
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        return TrainResult(
            self.step, self.step >= cfg.iterations, reason, self.train_s, peak, self.model.num_gaussians
        )

    def _install_signal_handlers(self) -> dict[int, Any]:
        if threading.current_thread() is not threading.main_thread():
            return {}

        def handler(signum: int, _frame: Any) -> None:
            if self._stop and signum == signal.SIGINT:
                raise KeyboardInterrupt
            self._stop = True

        old = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, handler)
        return old

    @staticmethod
    def _restore_signal_handlers(old: dict[int, Any]) -> None:
        for sig, h in old.items():
            signal.signal(sig, h)


def _from_py_random_state(st: tuple) -> list:
    return [st[0], list(st[1]), st[2]]


def _to_py_random_state(st: list) -> tuple:
    return (int(st[0]), tuple(int(x) for x in st[1]), st[2])
