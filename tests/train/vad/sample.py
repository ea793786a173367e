"""What the tests of :mod:`vadgs.train.vad` share about the bundled sample: its instances, a model of
given points and a trainer sharing a prebuilt index (the fixtures ``scene``, ``index`` and
``gt_points`` are in this folder's ``conftest.py``)."""

from __future__ import annotations

import torch

from vadgs.geometry import project_points
from vadgs.train.config import TrainConfig
from vadgs.train.model import GaussianModel
from vadgs.train.trainer import Trainer
from vadgs.train.vad import InstanceReconstruction, VisibilityDensifyConfig

__all__ = ["BUILDING", "CAR", "SIGN", "hits_on_car", "sample_model", "sample_trainer"]

BUILDING = 9  # a large facade of the sample scene with LiDAR on its lower part
CAR = 65  # the overtaken moving car
SIGN = 61  # the sample's traffic sign: about 100 pixels at half resolution


def sample_model(scene, points, colors, spacing):
    """A static model of the sample: one opaque Gaussian per point, of the points' ``spacing``."""
    n = points.shape[0]
    f = len(scene.frames)
    return GaussianModel(
        points,
        colors,
        torch.log(spacing)[:, None].expand(n, 3).clone(),
        torch.full((n,), -1),
        torch.zeros(0, f, 4, 4),
        torch.zeros(0, f, dtype=torch.bool),
        [],
        sh_degree=0,
        init_opacity=0.95,
    )


def sample_trainer(scene, model, index, **cfg):
    """A trainer of ``model`` with VAD-GS settings ``cfg``, its strategy sharing the prebuilt ``index``."""
    trainer = Trainer(
        scene,
        TrainConfig(iterations=100, checkpoint_every=10**6, vad=VisibilityDensifyConfig(**cfg)),
        model=model,
        progress=False,
    )
    trainer.strategy.index = index  # share the module's prebuilt index
    return trainer


def hits_on_car(scene, ref, points, instances):
    """Per other view of ``ref``'s camera with >= 50 of the object-frame ``points`` in the image
    (posed by the car's track at that frame): the fraction that lands on the car's mask."""
    track = scene.tracks[CAR]
    hits = []
    for v in scene.train_views:
        if scene.views[v].camera != scene.views[ref].camera or v == ref:
            continue
        o2w = track.object_to_world[scene.frame_position(scene.views[v].frame)]
        world = points @ o2w[:3, :3].T + o2w[:3, 3]
        cams = scene.cameras([v])
        uv, z = project_points(world[None], cams.K, cams.world_to_cam)
        h, w = cams.image_size
        u, vv = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
        ok = (z[0] > 0) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
        if int(ok.sum()) >= 50:
            hits.append(float((instances(v)[vv[ok], u[ok]] == CAR).float().mean()))
    return hits


def sample_reconstruction(
    instance: int, points: int, consistent: int, track: int | None = None
) -> InstanceReconstruction:
    """A reconstruction of ``points`` random points (``consistent`` pixels), seeded by ``instance``."""
    g = torch.Generator().manual_seed(instance)
    return InstanceReconstruction(
        points=torch.rand(points, 3, generator=g),
        normals=torch.tensor([[0.0, 0.0, 1.0]]).repeat(points, 1),
        colors=torch.full((points, 3), 0.5),
        spacing=torch.full((points,), 0.05),
        track=track,
        views=[0],
        depth=[torch.zeros(1, 4, 4)],
        normal=[torch.zeros(3, 4, 4)],
        reason="ok" if points else "explained",
        work=1.0,
        consistent=consistent,
    )
