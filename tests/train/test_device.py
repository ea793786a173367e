"""The training loop and VAD-GS on the ``device`` fixture's devices: nothing allocated on the CPU
that meets the model's tensors (the CUDA case runs where a GPU is present)."""

import dataclasses

import torch

from vadgs.geometry.rotation import normals_to_quats
from vadgs.train import losses as L
from vadgs.train.trainer import Trainer
from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig


def test_vad_training_runs_on_the_device(tiny_scene, tiny_config, device):
    vad = VisibilityDensifyConfig(every_cycles=1, max_instances=1, reconstruct=ReconstructConfig(max_crop=48))
    config = dataclasses.replace(tiny_config, iterations=19, vad=vad, device=str(device))
    trainer = Trainer(tiny_scene, config, progress=False)
    n0 = trainer.model.num_gaussians
    trainer.train()
    (event,) = trainer.state["vad_events"]  # after the first cycle of 18 views
    assert event["step"] == 17 and event["added"] > 0
    assert trainer.model.num_gaussians > n0
    for name, p in trainer.model.params.items():
        assert p.device.type == device.type, name
    for k in ("grad2d", "count"):
        assert trainer.state[k].device.type == device.type
    view = next(iter(trainer.state["vad_priors"]))
    targets = trainer.strategy.geometry_targets(trainer.state, view).to(device)
    out = trainer.render_view(view)
    terms = L.geometric_losses(targets, out.raster.depth, out.raster.normals, L.geometric_weights(0, 10))
    assert terms and all(t.device.type == device.type and torch.isfinite(t) for t in terms.values())


def test_normals_to_quats_follow_the_input(device):
    n = torch.nn.functional.normalize(torch.randn(8, 3, device=device, dtype=torch.float64), dim=-1)
    q = normals_to_quats(n)
    assert q.device.type == device.type and q.dtype == torch.float64
