"""gsplat's own ``simple_trainer.py`` with the VAD-GS diff, ``default`` vs ``vad``, on the CPU.

Copies gsplat v1.5.3's ``examples/`` (``../shared/third_party/gsplat-v1.5.3``), applies
``examples/gsplat_simple_trainer.diff``, and runs the real script twice on the same COLMAP project
through the CPU stand-ins of :mod:`tests.train.gsplat_simple_trainer` (gsplat's pure-torch
rasterization path; see there). Prints, for ``default`` and ``vad``: PSNR / SSIM on gsplat's test
split (every 8th image) at the same step, the Gaussians, the wall time (and its ratio), and each
VAD-GS event (step, flagged instances, what was reconstructed, Gaussians added)::

    python benchmarks/gsplat_trainer.py                       # the tests' COLMAP sample
    python benchmarks/gsplat_trainer.py --data DIR --factor 4 --steps 300 -- --vad.every-cycles 2

Arguments after ``--`` go to the ``vad`` run only (``--vad.*`` flags); ``--both="..."`` to both
(e.g. an earlier densification schedule for a short run:
``--both="--strategy.refine-start-iter 100 --strategy.refine-every 50"``).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.train.gsplat_simple_trainer import prepare_data, prepare_examples, run_trainer


def run_pair(data: Path, factor: int, steps: int, vad_args: list[str], both: list[str], tmp: Path) -> dict:
    """Both runs on ``data``; returns ``{name: record}`` with the test-split metrics in ``"val"``."""
    examples = prepare_examples(tmp)
    out = {}
    for name, extra in (("default", []), ("vad", vad_args)):
        res = tmp / f"results_{name}"
        argv = [
            name, "--data_dir", str(data), "--data_factor", str(factor), "--result_dir", str(res),
            "--max_steps", str(steps), "--eval_steps", str(steps), "--save_steps", str(steps),
            "--disable_viewer", "--disable_video", *both, *extra,
        ]  # fmt: skip
        rec = run_trainer(examples, argv, tmp / f"{name}.json", timeout=6 * 3600)
        rec["val"] = json.loads((res / "stats" / f"val_step{steps - 1:04d}.json").read_text())
        rec["argv"] = argv
        out[name] = rec
    return out


def report(runs: dict) -> str:
    """The comparison as text."""
    lines = []
    for name, rec in runs.items():
        v = rec["val"]
        lines.append(
            f"{name:8s} PSNR {v['psnr']:.3f} dB  SSIM {v['ssim']:.4f}  {v['num_GS']} Gaussians  "
            f"wall {rec['wall_s']:.1f} s  events {len(rec['events'])}"
        )
    d, v = runs["default"], runs["vad"]
    lines.append(
        f"vad - default: {v['val']['psnr'] - d['val']['psnr']:+.3f} dB, Gaussians x"
        f"{v['val']['num_GS'] / d['val']['num_GS']:.2f}, wall time x{v['wall_s'] / d['wall_s']:.2f}"
    )
    cfg = v.get("config", {})
    if "voxels" in cfg:
        lines.append(
            f"vad: {cfg['voxels']} voxels, gsplat scene_scale {cfg['scene_scale']:.3f}, "
            f"lengths {cfg.get('lengths')}"
        )
    for e in v["events"]:
        what = ", ".join(
            f"#{i['instance']} ({i['class']}) +{i['added']} [{i['reason']}]" for i in e["instances"]
        )
        lines.append(
            f"  event at step {e['step']}: {e['flagged_instances']} instances flagged "
            f"({e['flagged']}/{e['tested']} view tests), skipped {e['skipped']}, +{e['added']} "
            f"Gaussians in {e['total_s']:.1f} s: {what}"
        )
    return "\n".join(lines)


def main() -> None:
    """Parse, run, print."""
    argv = sys.argv[1:]
    vad_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None, help="COLMAP project (default: the tests' sample)")
    ap.add_argument("--factor", type=int, default=2, help="gsplat's --data_factor")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--both", default="", help='flags for both runs: --both="--flag value"')
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as t:
        tmp = args.keep or Path(t)
        tmp.mkdir(parents=True, exist_ok=True)
        data = args.data
        if data is None:
            from tests.data.colmap_sample import write_sample_colmap

            data = tmp / "colmap"
            write_sample_colmap(data, n_points=1500)
        prepare_data(data, args.factor)
        runs = run_pair(data.resolve(), args.factor, args.steps, vad_args, shlex.split(args.both), tmp)
        print(report(runs))


if __name__ == "__main__":
    main()
