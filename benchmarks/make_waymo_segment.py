"""Write a benchmark-format scene as a Waymo v2 segment (``vadgs.data.waymo_writer.write_waymo_segment``).

The parquet components land in ``OUT/<component>/<segment>.parquet``, the layout that
``vadgs convert waymo OUT --scene SEGMENT`` and ``vadgs.data.load_waymo`` read; images and range
images are written frame by frame (one row group each), so memory stays bounded. Prints the
summary, the wall time and the size on disk. Run from the repository root, e.g.::

    python benchmarks/make_segment.py /tmp/segment_mid --preset mid
    python benchmarks/make_waymo_segment.py /tmp/segment_mid /tmp/waymo_mid
    /usr/bin/time -v vadgs convert waymo /tmp/waymo_mid --scene segment --out /tmp/converted_mid
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from vadgs.data.waymo_writer import write_waymo_segment


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, help="the benchmark scene folder (scene.json)")
    ap.add_argument("out", type=Path, help="the Waymo split folder to write the components into")
    ap.add_argument("--segment", help="segment_context_name (default: the scene's name)")
    ap.add_argument("--columns", type=int, help="range-image width (default: twice the scan's azimuths)")
    ap.add_argument("--box-origin", choices=("bottom", "center"), default="bottom")
    ap.add_argument("--overwrite", action="store_true", help="replace the segment's component files")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    try:
        info = write_waymo_segment(
            args.scene,
            args.out,
            args.segment,
            columns=args.columns,
            box_origin=args.box_origin,
            overwrite=args.overwrite,
            progress=not args.no_progress,
        )
    except ValueError as e:
        ap.error(str(e))
    seconds = time.perf_counter() - start
    size = sum(p.stat().st_size for p in args.out.glob(f"*/{info.segment}.parquet"))
    print(info)
    print(
        f"{args.out}: segment {info.segment!r}, {info.frames} frames, {info.views} images, range images "
        f"{info.range_image_shape[0]}x{info.range_image_shape[1]} ({info.returns} of {info.points} points "
        f"kept), {info.boxes} boxes; {seconds:.0f} s, {size / 2**20:.0f} MiB"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
