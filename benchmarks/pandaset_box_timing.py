"""When a PandaSet camera fires against when the LiDAR caught the cars its image shows.

A moving car's voxel prior is its grid posed by the frame's cuboid; the image is taken at the
camera's own timestamp. If the cuboid (fitted to the sweep's points) and the image were tens of
milliseconds apart, the prior would sit off the car in the image. For each moving vehicle's
cuboid with enough Pandar64 points and its centre in front of a camera, this prints the camera's
timestamp minus the median capture time (column ``t``) of the points inside the cuboid, and the
same against the sweep's own timestamp. Used for issue 47 on PandaSet 002 (docs/results.md, "A
real log")::

    python benchmarks/pandaset_box_timing.py /data/pandaset/002 --frames 0:36 \\
        --cameras front_left_camera,front_camera,front_right_camera
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from vadgs.data.pandaset import PANDASET_VEHICLES, pandaset_box_to_matrix, pandaset_pose_to_matrix
from vadgs.data.pickles import read_pickled_dataframe


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence", type=Path, help="a PandaSet sequence folder (camera/, lidar/, annotations/)")
    ap.add_argument("--frames", default="0:36", help="START:STOP of the file numbers")
    ap.add_argument("--cameras", default="front_left_camera,front_camera,front_right_camera")
    ap.add_argument("--min-points", type=int, default=30, help="points a cuboid must hold to be timed")
    args = ap.parse_args()
    root = args.sequence
    start, stop = (int(x) for x in args.frames.split(":"))
    cams = args.cameras.split(",")
    lidar_ts = json.loads((root / "lidar" / "timestamps.json").read_text())
    cam_ts = {c: json.loads((root / "camera" / c / "timestamps.json").read_text()) for c in cams}
    cam_poses = {c: json.loads((root / "camera" / c / "poses.json").read_text()) for c in cams}
    by_cam: dict[str, list[float]] = defaultdict(list)
    sweep_offset: dict[str, list[float]] = defaultdict(list)
    for f in range(start, stop):
        pts = read_pickled_dataframe(root / "lidar" / f"{f:02d}.pkl.gz", f"PandaSet lidar/{f:02d}.pkl.gz")
        boxes = read_pickled_dataframe(
            root / "annotations" / "cuboids" / f"{f:02d}.pkl.gz", f"PandaSet cuboids/{f:02d}.pkl.gz"
        )
        keep = pts["d"].to_numpy() == 0  # the Pandar64, whose sweep the cameras are triggered by
        xyz = pts[["x", "y", "z"]].to_numpy()[keep]
        t = pts["t"].to_numpy()[keep]
        for _, b in boxes.iterrows():
            if b["label"] not in PANDASET_VEHICLES or bool(b.get("stationary", False)):
                continue
            o2w = pandaset_box_to_matrix([b["position.x"], b["position.y"], b["position.z"]], b["yaw"])
            local = (xyz - o2w[:3, 3]) @ o2w[:3, :3]  # box frame: x length, y width, z up
            half = np.array([b["dimensions.y"], b["dimensions.x"], b["dimensions.z"]]) / 2
            inside = (np.abs(local) < half).all(axis=1)
            if inside.sum() < args.min_points:
                continue
            caught = float(np.median(t[inside]))
            for c in cams:
                c2w = pandaset_pose_to_matrix(cam_poses[c][f], f"camera/{c}/poses.json[{f}]")
                p = np.linalg.inv(c2w) @ np.append(o2w[:3, 3], 1.0)
                if p[2] > 1.0 and abs(p[0] / p[2]) < 0.9:  # the centre in front, inside ~84° across
                    by_cam[c].append(1000 * (cam_ts[c][f] - caught))
                    sweep_offset[c].append(1000 * (cam_ts[c][f] - lidar_ts[f]))
    print("camera | cuboids | camera - points caught (ms): median, max |.| | camera - sweep timestamp (ms)")
    for c in cams:
        d = np.array(by_cam[c])
        if d.size == 0:
            print(f"{c} | 0 | - | -")
            continue
        print(
            f"{c} | {d.size} | {np.median(d):+.1f}, {np.abs(d).max():.1f} | {np.median(sweep_offset[c]):+.1f}"
        )


if __name__ == "__main__":
    main()
