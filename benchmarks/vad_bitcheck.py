"""Fingerprint of a short VAD-GS run on street_a: did a code change alter the pipeline's numerics?

Trains ``STEPS`` steps of street_a at half resolution with the street config, ADC every 10 steps
from step 10 and a VAD-GS event after every sampling cycle (90 training views: the first event
after step 89), on one thread, and prints the events, the number of Gaussians, a SHA-1 of the
parameters and the last loss. Run it at two commits; equal fingerprints mean identical numerics
(the full 1350-step comparison of ``vad_ablation.py`` then gives the same numbers)::

    python benchmarks/vad_bitcheck.py ../shared/data/street_a --steps 100

Reproducibility: ``--busy 2`` runs two busy-looping processes beside the training (a loaded
machine), ``--threads 2`` trains on two torch threads, ``--all-instances`` lets the event's work
budget (not ``max_instances``) decide where it stops; the fingerprint must not depend on the
first (the event's budget counts work, not seconds). ``--no-budget``: no work budget (as the
fingerprints before it were taken, with ``time_budget=None``).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import torch

from vadgs.data import load_scene
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig


def main() -> None:
    """Train, then print the fingerprint."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="street_a folder")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--busy", type=int, default=0, help="busy-looping processes beside the run")
    ap.add_argument("--all-instances", action="store_true", help="no max_instances: the work budget decides")
    ap.add_argument("--no-budget", action="store_true", help="work_budget None (the fingerprints before it)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = TrainConfig.from_dict(json.loads((Path(__file__).parent / "street_config.json").read_text()))
    cfg = dataclasses.replace(
        cfg,
        iterations=args.steps,
        strategy=dataclasses.replace(cfg.strategy, refine_start_iter=10, refine_every=10),
        checkpoint_every=0,
        vad=VisibilityDensifyConfig(
            every_cycles=1,
            max_instances=None if args.all_instances else 2,
            work_budget=None if args.no_budget else VisibilityDensifyConfig.work_budget,
        ),
    )
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    try:
        fingerprint(args, cfg)
    finally:
        for p in busy:  # only the processes started here
            p.kill()
            p.wait()


def fingerprint(args: argparse.Namespace, cfg: TrainConfig) -> None:
    """Train ``cfg`` on the scene and print the events and the parameters' SHA-1."""
    trainer = Trainer(load_scene(args.scene, scale=0.5), cfg, progress=False)
    loss = float("nan")
    for _ in range(cfg.iterations):
        loss = trainer.train_step()["total"]
    h = hashlib.sha1()
    for k in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        h.update(trainer.model.params[k].detach().cpu().numpy().tobytes())
    events = trainer.state["vad_events"]
    print("events (step, added):", [(e["step"], e["added"]) for e in events])
    print("events (attempted, skipped, work):", [(e["attempted"], e["skipped"], e["work"]) for e in events])
    print(f"{trainer.model.num_gaussians} Gaussians, params sha1 {h.hexdigest()[:12]}, last loss {loss!r}")


if __name__ == "__main__":
    main()
