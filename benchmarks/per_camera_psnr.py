"""Per-camera test PSNR of runs, from the per-view figures ``vadgs train`` / ``vadgs eval`` write.

For each run folder (its ``metrics.json``: ``test.per_view``, one ``{"image", "psnr"}`` a test
view), the mean PSNR of each camera's test views, the camera being the image's folder. With
``--against BASE``, each view's PSNR minus the same view's in BASE. Used for issue 47
(docs/results.md, "A real log": where the PSNR differences between the baseline and VAD-GS are)::

    python benchmarks/per_camera_psnr.py runs/ps36-s2-base runs/ps36-s2-vad --against runs/ps36-s2-base
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def per_view(run: Path) -> dict[str, float]:
    """``{image: psnr}`` of a run's test views (``RUN/metrics.json``)."""
    path = run / "metrics.json"
    if not path.is_file():
        raise FileNotFoundError(f"run: expected {path} (a finished vadgs run), found none")
    return {v["image"]: float(v["psnr"]) for v in json.loads(path.read_text())["test"]["per_view"]}


def camera_means(views: dict[str, float]) -> dict[str, float]:
    """Mean PSNR of each camera's views (the camera: the image's parent folder)."""
    groups: dict[str, list[float]] = defaultdict(list)
    for image, psnr in views.items():
        groups[Path(image).parent.name].append(psnr)
    return {cam: sum(v) / len(v) for cam, v in sorted(groups.items())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="run folders")
    ap.add_argument("--against", type=Path, help="a run whose per-view PSNR is subtracted, view by view")
    args = ap.parse_args()
    base = per_view(args.against) if args.against else None
    for run in args.runs:
        views = per_view(run)
        means = " | ".join(f"{cam} {m:.2f}" for cam, m in camera_means(views).items())
        print(f"{run}: {means}")
        if base is not None and run != args.against:
            for image, psnr in views.items():
                print(f"  {image}: {psnr - base[image]:+.2f} dB")


if __name__ == "__main__":
    main()
