"""The training loop.

:class:`Trainer` fits a :class:`~vadgs.train.model.GaussianModel` to a scene's training views,
sampled without replacement (:class:`~vadgs.train.sampler.ViewSampler`), on the loss of
:class:`~vadgs.train.objective.Objective` (colour, optional LiDAR depth, the paper's geometric
losses on a strategy's or a provider's priors, extra terms from a hook), with a densification
:class:`~vadgs.train.strategy.Strategy`: the standard one, VAD-GS's when ``TrainConfig.vad`` is set,
or any given one. The trainer hands strategies gsplat's arguments (``model.params``, the optimizer,
the state, the step, the render's ``info``) and, for VAD-GS, a
:class:`~vadgs.train.vad.StrategyContext`; strategies never see the trainer. This module holds the
trainer's state and one step (:meth:`Trainer.train_step`); :mod:`vadgs.train.loop` drives the steps
(progress bar, log, signals, checkpoints on the way, failure path) and defines
:class:`~vadgs.train.loop.TrainResult`.

Checkpoints (:class:`~vadgs.train.checkpoint.Checkpoint`, ``checkpoint.pt`` in the run folder)
hold everything the run depends on, so ``resume`` continues *exactly*. They are written atomically
every ``checkpoint_every`` steps and ``checkpoint_minutes``, at the end of the first sampling
cycle, at the end, when SIGINT / SIGTERM stop the loop (:func:`~vadgs.train.session.stop_on_signals`)
and when an exception stops it (the last completed step; see :meth:`Trainer.train`); saving never
changes the trajectory. A non-finite loss or parameter raises
:class:`~vadgs.train.divergence.NonFiniteLossError`, a diverging model
:class:`~vadgs.train.divergence.DivergenceError`, both naming the step; nothing is saved over the last
good checkpoint then. A run folder that holds a run is never reused by a new :class:`Trainer`
unless ``overwrite=True``; :meth:`Trainer.from_checkpoint` continues it.
"""

from __future__ import annotations

import math
import random
import time
import warnings
from collections.abc import Callable, MutableMapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import torch

from vadgs.checks import checks_enabled, first_false
from vadgs.data.scene import Scene
from vadgs.geometry.camera import invert_rigid
from vadgs.runfolder import record_files
from vadgs.train.appearance import AppearanceModel
from vadgs.train.checkpoint import (
    CHECKPOINT_NAME,
    Checkpoint,
    StepSnapshot,
    capture_rng,
    check_new_run,
    load_checkpoint,
    restore_rng,
    resumed_config,
    save_checkpoint,
)
from vadgs.train.config import TrainConfig, refine_steps
from vadgs.train.divergence import DivergenceMonitor, NonFiniteLossError
from vadgs.train.init import init_gaussians
from vadgs.train.loop import run_loop
from vadgs.train.model import PER_GAUSSIAN, GaussianModel, ModelRender, adam, make_optimizer
from vadgs.train.objective import Objective, render_hard_depth
from vadgs.train.sampler import ViewSampler
from vadgs.train.scenes import open_scene
from vadgs.train.strategy import DefaultStrategy, GeometryPriors, Strategy
from vadgs.train.vad import (
    StrategyContext,
    ViewRender,
    VisibilityAwareDensification,
    pack_state,
    unpack_state,
)
from vadgs.train.vad.inputs import VisibilityInputs

if TYPE_CHECKING:
    from vadgs.train.loop import TrainResult
    from vadgs.train.losses import GeometryTargets

__all__ = ["Trainer"]


def _scene_scale(scene: Scene, views: list[int]) -> float:
    centres = torch.stack([scene.views[v].cam_to_world[:3, 3] for v in views])
    return float((centres - centres.mean(0)).norm(dim=-1).max() * 1.1) or 1.0


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
        progress: show a tqdm progress bar (ETA, loss and PSNR of the last steps, and a line while a
            VAD-GS event runs).
        log: a ``print``-like callable for the run's messages when there is no bar: one line per
            VAD-GS event (its summary; with the bar they are written above it), and the warning
            when the schedule can never densify (else a :class:`UserWarning`). None: silent.
        callback: ``(trainer, step)`` called after every step (tests use it to interrupt).
        overwrite: ``out_dir`` may hold a previous run (a checkpoint or ``metrics.json``): the
            files it recorded in its manifest (:mod:`vadgs.runfolder`) are removed when
            :meth:`train` starts, checked here first. Without it such an ``out_dir`` raises
            ``ValueError``; continue a run with :meth:`from_checkpoint` instead. A non-empty
            ``out_dir`` that vadgs did not write raises ``ValueError`` either way.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> from vadgs.train.init import InitConfig
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
        overwrite: bool = False,
        log: Callable[[str], None] | None = None,
        _resuming: bool = False,
    ) -> None:
        self.scene = scene
        self.config = config or TrainConfig()
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.clear_previous = False
        if self.out_dir is not None and not _resuming:
            # before any work: a refused overwrite changes nothing
            check_new_run(self.out_dir, overwrite, "out_dir", "Trainer.from_checkpoint", "overwrite=True")
            self.clear_previous = overwrite
        if scene_ref is None and scene.root is not None and (Path(scene.root) / "scene.json").is_file():
            scene_ref = {"kind": "benchmark", "path": str(Path(scene.root).resolve()), "scale": scene.scale}
        self.scene_ref = scene_ref or {}
        self.device = torch.device(self.config.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device: {self.config.device!r} requested but CUDA is not available")
        self.progress = progress
        self.log = log
        self.callback = callback
        self.train_views = list(scene.train_views)
        self._cameras: dict[int, tuple[torch.Tensor, torch.Tensor, tuple[int, int]]] = {}  # camera()
        # render_view(): each view's inverted camera and sky rays (_rays), the rays per distinct camera
        self._view_rays: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._sky_rays: dict[tuple, torch.Tensor] = {}
        self._camera_keys: dict[int, tuple] = {}  # camera(): a view's K (bytes) and size, for _sky_rays
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
        self.appearance: AppearanceModel | None = None
        self.appearance_optimizer: torch.optim.Adam | None = None
        app = self.config.appearance
        if app is not None:  # zeros only: the random generators are not touched
            frames = len(scene.frames) if app.per_frame else None
            self.appearance = AppearanceModel(len(scene.camera_names), frames, app.centered).to(self.device)
            self.appearance_optimizer = adam(self.appearance.parameters(), lr=app.lr)
        self.strategy = strategy if strategy is not None else self._configured_strategy()
        if strategy is None and not _resuming:
            self._check_schedule()
        self.state = self.strategy.initialize_state(self.scene_scale)
        if geometry_targets is None and isinstance(self.strategy, GeometryPriors):
            geometry_targets = self._strategy_priors
        self.objective = Objective(
            scene, self.config, self.device, self.appearance, geometry_targets, extra_losses
        )
        self.step = 0
        self.train_s = 0.0
        self._stop = False
        self._saved_step: int | None = None
        self._saved_at: float | None = None
        self._updating = False
        self._divergence: DivergenceMonitor | None = None

    def _configured_strategy(self) -> Strategy:
        base = DefaultStrategy(self.config.strategy)
        if self.config.vad is None:
            return base
        strategy = VisibilityAwareDensification.from_config(self.config.vad, base=base)
        # the scene as data, the loop's context; the visibility index, built once, before the first step
        strategy.prepare(VisibilityInputs.from_scene(self.scene), self.strategy_context())
        return strategy

    def _check_schedule(self) -> None:
        """Say when the schedule can never densify, or never hold a VAD-GS event, in ``iterations`` steps."""
        cfg = self.config
        messages = []
        if cfg.iterations and not len(refine_steps(cfg)):
            s = cfg.strategy
            messages.append(
                f"no densification in {cfg.iterations} steps: refine_start_iter "
                f"{s.refine_start_iter}, refine_every {s.refine_every}, refine_stop_iter "
                f"{s.refine_stop_iter}; scale the schedule to the run (vadgs.train.config.scale_schedule, "
                "what vadgs train does for short runs) or lower --strategy.refine-start-iter"
            )
        vad = cfg.vad
        if cfg.iterations and vad is not None:
            first = vad.every_cycles * len(self.train_views) - 1  # the step that ends the first event's cycle
            if not first < vad.last_event_fraction * cfg.iterations:
                need = int(first / vad.last_event_fraction) + 1
                messages.append(
                    f"no VAD-GS event in {cfg.iterations} steps: the first comes after {vad.every_cycles} "
                    f"sampling cycles of the {len(self.train_views)} training views (step {first}) and none "
                    f"after {vad.last_event_fraction:g} of the run; raise --iterations to at least {need} "
                    "or lower --vad.every-cycles"
                )
        for msg in messages:
            if self.log is not None:
                self.log(f"WARNING: {msg}")
            else:
                warnings.warn(msg, UserWarning, stacklevel=3)

    def _strategy_priors(self, view: int) -> GeometryTargets | None:
        # bound in __init__ only when the strategy is GeometryPriors
        return cast(GeometryPriors, self.strategy).geometry_targets(self.state, view)

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
    def from_checkpoint(
        cls,
        path: str | Path,
        scene: Scene | None = None,
        config_changes: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> Trainer:
        """Continue a run from its checkpoint (exactly: RNGs, sampler, optimizer, strategy state).

        Args:
            path: the checkpoint or its run folder.
            scene: the scene (default: reloaded from the stored reference).
            config_changes: changes to the stored configuration that a resumed run can honour
                (:data:`~vadgs.train.checkpoint.RESUMABLE_CHANGES`): ``iterations`` (>= the
                checkpoint's step; extending a
                run also stretches the means' learning-rate decay and VAD-GS's event window, which
                follow ``iterations``), ``max_minutes``, ``device``, ``threads``,
                ``checkpoint_every``, ``checkpoint_minutes``, ``log_every``.
            **kwargs: further :class:`Trainer` arguments (``out_dir`` defaults to the checkpoint's folder).

        Raises:
            ValueError: on a corrupt or modified checkpoint, on a change that cannot be honoured,
                or without ``scene`` when the checkpoint stores no scene reference.
        """
        path = Path(path)
        ckpt = load_checkpoint(path)
        config = resumed_config(ckpt, config_changes)
        if scene is None:
            if not ckpt.scene_ref.get("path"):
                raise ValueError(
                    f"checkpoint {path}: no scene reference stored (trained from an in-memory scene); "
                    "pass scene="
                )
            scene = open_scene(ckpt.scene_ref)
        model = GaussianModel.from_state(ckpt.model, ckpt.model_extra)
        kwargs.setdefault("out_dir", path if path.is_dir() else path.parent)
        kwargs.setdefault("scene_ref", ckpt.scene_ref)
        trainer = cls(scene, config, model=model, _resuming=True, **kwargs)
        trainer.optimizer.load_state_dict(ckpt.optimizer)
        if trainer.appearance is not None:
            if ckpt.appearance is None:
                raise ValueError(f"checkpoint {path}: config.appearance is set but no appearance is stored")
            trainer.appearance.load_state_dict(ckpt.appearance["model"])
            assert trainer.appearance_optimizer is not None  # made with the appearance model
            trainer.appearance_optimizer.load_state_dict(ckpt.appearance["optimizer"])
        trainer.state = unpack_state(ckpt.strategy_state)
        trainer.sampler.load_state_dict(ckpt.sampler)
        restore_rng(ckpt.rng, trainer.generator)
        trainer.step = ckpt.step
        trainer.train_s = ckpt.train_s
        trainer._saved_step = trainer.step
        return trainer

    def checkpoint(self) -> Checkpoint:
        """The run's state now, as a :class:`~vadgs.train.checkpoint.Checkpoint`."""
        appearance = None
        if self.appearance is not None:
            assert self.appearance_optimizer is not None  # made with the appearance model
            appearance = {
                "model": self.appearance.state_dict(),
                "optimizer": self.appearance_optimizer.state_dict(),
            }
        return Checkpoint(
            step=self.step,
            config=self.config.to_dict(),
            scene_ref=self.scene_ref,
            model=self.model.state_dict(),
            model_extra=self.model.extra_state(),
            optimizer=self.optimizer.state_dict(),
            strategy_state=pack_state(self.state),
            sampler=self.sampler.state_dict(),
            rng=capture_rng(self.generator),
            train_s=self.train_s,
            appearance=appearance,
        )

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        """Write :meth:`checkpoint` atomically (``out_dir/checkpoint.pt`` by default), with its checksum.

        Raises:
            OSError: naming the file when it cannot be written (disk full...): the temporary file
                is removed and the previous checkpoint is left as it was.
        """
        default = path is None
        if path is None:
            if self.out_dir is None:
                raise ValueError("save_checkpoint: no path and no out_dir")
            path = self.out_dir / CHECKPOINT_NAME
        path = save_checkpoint(self.checkpoint(), path)
        if self.out_dir is not None:
            record_files(self.out_dir, [path])
        if default:
            self._saved_step = self.step
            self._saved_at = time.monotonic()
        return path

    def request_stop(self) -> None:
        """Stop at the end of the current step (and checkpoint); what SIGINT / SIGTERM do."""
        self._stop = True

    @property
    def stop_requested(self) -> bool:
        """True once :meth:`request_stop` was called: :meth:`train` stops after the current step."""
        return self._stop

    @property
    def checkpoint_step(self) -> int | None:
        """The step of the last checkpoint written to (or resumed from) ``out_dir``; None before one."""
        return self._saved_step

    @property
    def checkpoint_time(self) -> float | None:
        """``time.monotonic()`` when the last checkpoint was written to ``out_dir`` (None before one)."""
        return self._saved_at

    @property
    def updating(self) -> bool:
        """True while a step's update is applied (optimizer, strategy, checks).

        The state may be half changed then, so a failure is not undone by :meth:`restore`.
        """
        return self._updating

    def snapshot(self) -> StepSnapshot:
        """What a step consumes before it changes the parameters: the view sampler and the generators.

        :meth:`restore` of it undoes a step that failed before its update (:attr:`updating` False),
        so that the run continues exactly as if the step had never started.
        """
        return StepSnapshot(self.sampler.state_dict(), capture_rng(self.generator))

    def restore(self, snapshot: StepSnapshot) -> None:
        """Put back the sampler and generators of :meth:`snapshot`."""
        self.sampler.load_state_dict(snapshot.sampler)
        restore_rng(snapshot.rng, self.generator)

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

    def render_view(self, view: int, **kwargs: Any) -> ModelRender:
        """Render a scene view with the current model (on the trainer's device)."""
        world_to_cam, K, size = self.camera(view)
        frame = self.scene.view_frame_position(view)
        kept = self._view_rays.get(view)
        if kept is None:
            kept = self._view_rays[view] = self._rays(view, world_to_cam, K, size)
        c2w, rays = kept
        return self.model.render(
            world_to_cam, K, size, frame, self.config.raster, cam_to_world=c2w, sky_rays=rays, **kwargs
        )

    def _rays(
        self, view: int, world_to_cam: torch.Tensor, K: torch.Tensor, size: tuple[int, int]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """A view's inverted camera (its value check once) and its sky rays, those shared by equal cameras.

        The rays (12 bytes a pixel) are kept once per distinct intrinsics and size: a rig's few
        cameras (``K`` compared by its bytes on the host, from :meth:`camera`).
        """
        key = self._camera_keys[view]
        rays = self._sky_rays.get(key)
        if rays is None:
            rays = self._sky_rays[key] = self.model.sky_rays(K, size)
        return invert_rigid(world_to_cam), rays

    def camera(self, view: int) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
        """A view's ``world_to_cam (1, 4, 4)`` and ``K (1, 3, 3)`` on the device, and its ``(H, W)``.

        Made from ``scene.cameras([view])`` (its value checks) at a view's first use and kept: 100
        bytes a view, so that a step neither checks nor copies its camera again.
        """
        cam = self._cameras.get(view)
        if cam is None:
            cams = self.scene.cameras([view])
            cam = (cams.world_to_cam.to(self.device), cams.K.to(self.device), cams.image_size)
            self._cameras[view] = cam
            # the scene's cameras are on the host: the bytes of K, no read of a device
            self._camera_keys[view] = (cams.K.detach().cpu().numpy().tobytes(), tuple(cams.image_size))
        return cam

    def render_hard_depth(
        self, view: int, stride: int | None = None, fused: ModelRender | None = None
    ) -> torch.Tensor:
        """A view's :func:`~vadgs.train.objective.render_hard_depth` (the paper's hard depth loss's).

        ``(1, 1, ceil(H / s), ceil(W / s))``: the view's depth with every opacity fixed to 1 on
        every ``s = stride``-th pixel row and column (default ``config.geometry.hard_stride``), or
        ``fused``'s (the step's render made with ``hard_depth=True``).
        """
        s = self.config.geometry.hard_stride if stride is None else stride
        world_to_cam, K, size = self.camera(view)
        frame = self.scene.view_frame_position(view)
        return render_hard_depth(self.model, world_to_cam, K, size, frame, self.config.raster, s, fused)

    @torch.no_grad()
    def render_geometry(self, view: int) -> ViewRender:
        """Depth, opacity and normals of a view, without gradient (a strategy's ``render``)."""
        r = self.render_view(view).raster
        return ViewRender(r.depth[0], r.alpha[0], r.normals[0])

    def train_step(self) -> dict[str, float]:
        """One optimisation step on the next sampled view; returns the loss terms as floats."""
        step = self.step
        cfg = self.config
        self._updating = False
        for g in self.optimizer.param_groups:
            g["lr"] = self._lrs(step)[g["name"]]
        self.model.active_sh_degree = min(step // cfg.sh_degree_interval, self.model.sh_degree)
        view = self.sampler.next()
        # the hard depth composited in this pass (GeometricLossConfig.hard_fused), or rendered apart
        fused = cfg.geometry.hard_fused and self.objective.wants_hard(step, view)
        out = self.render_view(view, hard_depth=fused)
        info = {
            "raster": out.raster,
            "ids": out.ids,
            "image_size": tuple(out.color.shape[-2:]),
            "view": view,
            "frame": self.scene.view_frame_position(view),
            "generator": self.generator,
        }
        # a ParameterDict is a mutable mapping of str to tensors; its stubs do not say so
        params = cast(MutableMapping[str, torch.Tensor], self.model.params)
        self.strategy.step_pre_backward(params, self.optimizer, self.state, step, info)

        def render_hard(v: int, s: int) -> torch.Tensor:
            return self.render_hard_depth(v, s, out if fused else None)

        terms = self.objective(step, view, out, render_hard)
        total = torch.stack([t.reshape(()) for t in terms.values()]).sum()
        total.backward()
        self._updating = True
        # a non-finite loss: the fused optimizers skip the update on the device (no read here); the
        # step raises below, from the one read of the step
        # (total · 0 is NaN exactly when total is not finite: 3 kernels instead of isfinite's 6)
        found_inf = (total.detach() * 0).isnan().float()
        optimizers = [self.optimizer, *([self.appearance_optimizer] if self.appearance_optimizer else [])]
        for opt in optimizers:
            if all(g.get("fused") for g in opt.param_groups):
                opt.found_inf = found_inf  # type: ignore[attr-defined]  # the GradScaler hook
        for opt in optimizers:
            opt.step()
            opt.zero_grad(set_to_none=True)
        self.strategy.step_post_backward(params, self.optimizer, self.state, step, info)
        with torch.no_grad():
            color = self.objective.corrected_color(view, out.color.detach())
            mse = torch.mean((color.clamp(0, 1) - self.objective.image(view)) ** 2)
            # every logged number and the value checks in one read from the device: a parameter's
            # L1 norm (one multi-tensor kernel for all) is finite iff all its values are, short of
            # an overflow past 3e38, which _check_parameters tells apart
            named = self._checked_parameters() if checks_enabled() else []
            norms = torch._foreach_norm([t.detach() for _, t in named], 1) if named else []
            logged = [*(t.reshape(()) for t in terms.values()), total, mse, *(n.to(mse.dtype) for n in norms)]
            read = torch.stack(logged).tolist()
        res = dict(zip(terms, read[: len(terms)]))
        # the PSNR from the mean squared error read (in float64 on the host)
        res["total"], res["psnr"] = read[len(terms)], -10 * math.log10(max(read[len(terms) + 1], 1e-10))
        if not math.isfinite(res["total"]):  # the update was skipped (fused optimizers)
            raise NonFiniteLossError(
                step, f"loss terms { {k: v for k, v in res.items() if k != 'psnr'} } (view {view})"
            )
        if named and not all(map(math.isfinite, read[len(terms) + 2 :])):
            self._check_parameters(step, named)
        self.step = step + 1
        self._updating = False
        return res

    def _checked_parameters(self) -> list[tuple[str, torch.Tensor]]:
        """The parameters a step checks for NaN / inf after its update, named."""
        named = [
            (f"parameter {k!r}", self.model.params[k])
            for k in ("means", "log_scales", "opacity_logits", "sh_dc")
        ]
        if self.appearance is not None:
            named += [(f"appearance parameter {k!r}", p) for k, p in self.appearance.named_parameters()]
        return named

    def _check_parameters(self, step: int, named: list[tuple[str, torch.Tensor]] | None = None) -> None:
        """Raise :class:`NonFiniteLossError` naming a parameter with a NaN / inf after the update.

        One read from the device for all of them (a synchronisation on a GPU); the names only on a
        failure. :meth:`train_step` calls it only when the sums it read were not all finite.
        """
        named = self._checked_parameters() if named is None else named
        with torch.no_grad():
            failed = first_false([torch.isfinite(t).all() for _, t in named])
        if failed is not None:
            raise NonFiniteLossError(step, f"{named[failed][0]} after the optimizer step")

    def check_divergence(self, res: dict[str, float]) -> None:
        """Raise :class:`DivergenceError` if the model diverged (:class:`DivergenceMonitor`).

        Uses the colour loss already on the host every step; at step 1, every ``log_every`` steps
        and at the end of each cycle, one reduction over the static means.
        """
        cfg = self.config
        at = self.step % cfg.log_every == 0 or self.step % len(self.sampler) == 0 or self.step == 1
        if self._divergence is None:
            centre = torch.stack([self.scene.views[v].cam_to_world[:3, 3] for v in self.train_views]).mean(0)
            self._divergence = DivergenceMonitor(
                centre, self.scene_scale, cfg.diverge_distance, cfg.diverge_share, cfg.diverge_loss_factor
            )
        means = None
        if at and cfg.diverge_distance > 0:
            means = self.model.params["means"].detach()[self.model.node_ids < 0]
        self._divergence.check(self.step, res.get("color"), means, self.step >= len(self.sampler), at)

    def train(self) -> TrainResult:
        """Run to ``config.iterations`` (from the current step), checkpointing on the way.

        SIGINT / SIGTERM finish the current step, write the checkpoint and return with
        ``completed=False`` (a second SIGINT raises ``KeyboardInterrupt`` at once). Checkpoints
        are written every ``checkpoint_every`` steps, every ``checkpoint_minutes``, at the end of
        the first sampling cycle and at the end; none of them changes the trajectory.

        On an exception the last completed step is checkpointed (a step that failed before its
        optimizer update is undone first) and the exception is re-raised with a note naming the
        checkpoint (``e.__notes__``); divergence, non-finite values and failed writes keep the
        previous checkpoint. Stale ``.tmp`` files of a killed run are removed at the start.

        Raises:
            NonFiniteLossError: on a NaN / infinite loss or parameter, naming the step.
            DivergenceError: when the model diverges (see :class:`TrainConfig`), naming the step.
            OSError: when a checkpoint cannot be written (naming the file; the previous one is kept).
        """
        before = torch.get_num_threads()
        if self.config.threads:
            torch.set_num_threads(self.config.threads)
        try:
            return run_loop(self)
        finally:
            torch.set_num_threads(before)  # the process's thread count is the caller's
