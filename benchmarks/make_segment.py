"""Write a procedural driving segment in the benchmark scene format (``vadgs.data.synthetic.make_segment``).

Presets:

- ``tiny``: 4 frames x 2 cameras at 64x48, 2,000 LiDAR points a frame, 3 moving cars (tests);
- ``mid``: 50 frames of the ``waymo`` rig;
- ``waymo``: a segment-sized scene: 200 frames x 5 cameras (front, front_left, front_right at
  1920x1280; side_left, side_right at 1920x886, like Waymo), 150,000 LiDAR points a frame
  (64 beams, -17.6 to +2.4 degrees, 75 m), 4 moving cars.

Any field of :class:`~vadgs.data.synthetic.SegmentConfig` can override the preset. Prints the
wall time and the size on disk at the end. Run from the repository root, e.g.::

    nice python benchmarks/make_segment.py /tmp/segment_waymo --preset waymo --workers 2
    python benchmarks/make_segment.py /tmp/seg --preset tiny --frames 8 --image-format png
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

from vadgs.data.synthetic import SegmentConfig, check_segment_folder, make_segment

WAYMO = SegmentConfig(
    frames=200, cameras=5, width=1920, height=1280, side_height=886, lidar_points=150_000, moving_cars=4,
    parked_cars=8, signs=4,
)  # fmt: skip
PRESETS = {
    "tiny": SegmentConfig(),
    "mid": dataclasses.replace(WAYMO, frames=50),
    "waymo": WAYMO,
}


def disk_size(folder: Path) -> tuple[int, int]:
    """``(bytes, files)`` under a folder."""
    total = count = 0
    for root, _, files in os.walk(folder):
        for f in files:
            total += os.path.getsize(os.path.join(root, f))
            count += 1
    return total, count


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the scene folder to write")
    ap.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    ap.add_argument("--workers", type=int, default=2, help="processes rendering frames (default 2)")
    ap.add_argument(
        "--overwrite", action="store_true", help="replace the segment it wrote in OUT (its files only)"
    )
    ap.add_argument("--no-progress", action="store_true")
    for f in dataclasses.fields(SegmentConfig):
        if f.name == "lidar_vfov":
            ap.add_argument("--lidar-vfov", type=float, nargs=2, metavar=("MIN", "MAX"))
            continue
        kind = {"int": int, "float": float, "str": str, "int | None": int}[str(f.type)]
        ap.add_argument("--" + f.name.replace("_", "-"), type=kind, help=f"override the preset's {f.name}")
    args = ap.parse_args(argv)
    names = [f.name for f in dataclasses.fields(SegmentConfig)]
    fields = {name: getattr(args, name) for name in names if getattr(args, name) is not None}
    if "lidar_vfov" in fields:
        fields["lidar_vfov"] = tuple(fields["lidar_vfov"])
    try:
        cfg = dataclasses.replace(PRESETS[args.preset], **fields)
        check_segment_folder(args.out, args.overwrite, "--overwrite")  # refused before any work
    except ValueError as e:
        ap.error(str(e))
    print(cfg)
    start = time.perf_counter()
    make_segment(args.out, cfg, workers=args.workers, progress=not args.no_progress, overwrite=args.overwrite)
    seconds = time.perf_counter() - start
    size, files = disk_size(args.out)
    views = cfg.frames * cfg.cameras
    print(
        f"{args.out}: {cfg.frames} frames, {views} views, {cfg.lidar_points} LiDAR points a frame; "
        f"{seconds:.0f} s ({seconds / cfg.frames:.2f} s a frame, {args.workers} workers), "
        f"{size / 2**20:.0f} MiB in {files} files"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
