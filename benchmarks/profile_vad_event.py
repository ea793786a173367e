"""Where one VAD-GS event spends its time, before issue 21 (legacy) and now, on street_a / street_b.

    python benchmarks/profile_vad_event.py ../shared/data/street_a [--path legacy|current]

The legacy path is vadgs at commit 274c932, read from the git history
(``bench_vad_event.legacy_package``). Uses the checkpoint of ``benchmarks/bench_vad_event.py``
(300 street-config steps with the strategy attached, no event; trained and written to
``runs/bench_vad_event/`` if absent), runs one event
under cProfile on one torch thread and prints the seconds and shares of its steps: detection
(renders + incompleteness test), view selection, crops, PatchMatch, consistency (+ planar
completion), fusion, adding the Gaussians, and the renders made during reconstruction.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import pstats
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_vad_event import _checkpoint, _fresh, _legacy_strategy, _warm_index

from vadgs.data import load_scene

# step -> (file suffixes, function names) whose cumulative time it is; the legacy path's files and
# names are those of vadgs at commit 274c932 (bench_vad_event.legacy_package), the current path's today's
STEPS = {
    "selection": (("select/selector.py",), ("select_views",)),
    "crops": (("reconstruct.py", "instance_crops.py", "vad/crops.py"), ("_crop_group", "crop_group")),
    "patchmatch": (("patchmatch.py",), ("patchmatch",)),
    "consistency": (("reconstruct.py", "vad/fusion.py"), ("_consistent", "consistent_depth")),
    "fusion": (("mvs/fusion.py",), ("fuse_depth_maps",)),
    "add": (("vad.py", "vad/strategy.py", "vad/event.py"), ("_add", "add_reconstructions")),
    "renders": (("trainer.py",), ("render_geometry",)),
}


def profile(scene_dir: str, path: str) -> dict[str, float]:
    torch.set_num_threads(1)
    name = Path(scene_dir).name
    scene = load_scene(scene_dir, scale=0.5)
    ckpt = _checkpoint(name)
    index = _warm_index(name, scene, path == "legacy")
    trainer = _fresh(scene, ckpt)
    if path == "legacy":
        strategy = _legacy_strategy(trainer, index)
    else:
        strategy = trainer.strategy
        strategy.index = index
        strategy.config = dataclasses.replace(strategy.config, work_budget=None, time_budget=None)
    st = trainer.state
    prof = cProfile.Profile()
    prof.enable()
    event = strategy.densify(trainer.model.params, trainer.optimizer, st, trainer.step)
    prof.disable()
    stats = pstats.Stats(prof).stats
    cum = {}
    for step, (suffix, names) in STEPS.items():
        cum[step] = sum(v[3] for (f, _, n), v in stats.items() if f.endswith(suffix) and n in names)
    out = {"total": event["total_s"], "detection": event["detect_s"], **cum}
    out["other"] = out["total"] - out["detection"] - sum(cum[k] for k in STEPS if k != "renders")
    out["instances attempted"] = len(event["instances"])
    out["Gaussians added"] = event["added"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--path", choices=["legacy", "current"], nargs="+", default=["legacy", "current"])
    args = ap.parse_args()
    rows = {p: profile(args.scene, p) for p in args.path}
    keys = list(next(iter(rows.values())))
    print(f"| step ({Path(args.scene).name}) | " + " | ".join(f"{p} s | share" for p in rows) + " |")
    print("|---|" + "---|---|" * len(rows))
    for k in keys:
        cells = []
        for r in rows.values():
            v = r[k]
            if k in ("instances attempted", "Gaussians added"):
                cells += [f"{v}", ""]
            else:
                cells += [f"{v:.2f}", f"{100 * v / r['total']:.0f} %"]
        print(f"| {k} | " + " | ".join(cells) + " |")
    print("(renders: inside detection for legacy; PatchMatch priors made during reconstruction)")


if __name__ == "__main__":
    main()
