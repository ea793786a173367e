"""Gaussian model, losses, densification strategies, trainer and evaluation (see ``docs/train.md``)."""

from vadgs.train.appearance import AppearanceConfig, AppearanceModel, apply_affine
from vadgs.train.config import TrainConfig
from vadgs.train.divergence import NonFiniteLossError
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.loop import TrainResult
from vadgs.train.losses import (
    GeometricLossConfig,
    GeometryTargets,
    color_loss,
    depth_loss,
    depth_loss_hard,
    depth_loss_soft,
    geometric_weights,
    normal_loss,
)
from vadgs.train.model import GaussianModel, Gaussians, ModelRender, gaussians_at, make_optimizer
from vadgs.train.results.evaluate import EvalMetrics, evaluate, evaluate_split, save_test_panels
from vadgs.train.results.export import export_model, export_world
from vadgs.train.results.trajectory import ego_trajectory, make_trajectory
from vadgs.train.results.video import render_video
from vadgs.train.sampler import ViewSampler
from vadgs.train.strategy import DefaultStrategy, DefaultStrategyConfig, Strategy
from vadgs.train.strategy.ops import (
    add_gaussians,
    duplicate,
    remove_gaussians,
    reset_opacity,
    split,
)
from vadgs.train.trainer import Trainer

__all__ = [
    "AppearanceConfig",
    "AppearanceModel",
    "DefaultStrategy",
    "DefaultStrategyConfig",
    "EvalMetrics",
    "GaussianModel",
    "Gaussians",
    "GeometricLossConfig",
    "GeometryTargets",
    "InitConfig",
    "ModelRender",
    "NonFiniteLossError",
    "Strategy",
    "TrainConfig",
    "TrainResult",
    "Trainer",
    "ViewSampler",
    "add_gaussians",
    "apply_affine",
    "color_loss",
    "depth_loss",
    "depth_loss_hard",
    "depth_loss_soft",
    "duplicate",
    "ego_trajectory",
    "evaluate",
    "evaluate_split",
    "export_model",
    "export_world",
    "gaussians_at",
    "geometric_weights",
    "init_gaussians",
    "make_optimizer",
    "make_trajectory",
    "normal_loss",
    "remove_gaussians",
    "render_video",
    "reset_opacity",
    "save_test_panels",
    "split",
]
