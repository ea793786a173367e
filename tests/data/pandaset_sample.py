"""Write a benchmark scene (e.g. from ``make_segment``) as a PandaSet sequence folder, for the tests.

The layout and the conventions are PandaSet's (devkit ``pandaset/geometry.py``): poses sensor →
world as ``position`` + ``heading`` ``{w, x, y, z}``; cameras OpenCV with ``fx, fy, cx, cy``;
``lidar/NN.pkl.gz`` a gzip'd pickled DataFrame ``x, y, z, i, t, d`` of **world** points (``d``
0: Pandar64, 1: forward PandarGT); cuboids centred, ``dimensions.x`` the width, ``dimensions.y``
the length, ``yaw`` 0 facing ``(0, 1, 0)``. The world is the source's moved by :data:`GLOBAL`.

Besides the source's moving cars (each written twice, as PandaSet does in the LiDARs' overlap: a
``cuboids.sensor_id`` 0 box and a sibling ``1`` box :data:`SIBLING_SHIFT` metres ahead), the
cuboids hold a parked car whose box jitters (:data:`PARKED_JITTER`) and a walking pedestrian.
"""

from __future__ import annotations

import gzip
import json
import math
import pickle
import shutil
from pathlib import Path

import numpy as np

from vadgs.data import Scene
from vadgs.train.vad.instances import box_corners

#: the source world's origin in the written one (PandaSet's world is not the first pose's).
GLOBAL = np.array([120.0, -340.0, 4.0])
#: the Pandar64 frame in the ego frame (x forward, y left, z up): x right, y forward, z up, 1.8 m up.
LIDAR_IN_EGO = np.array([[0.0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 1, 1.8], [0, 0, 0, 1]])
#: the source's camera names → PandaSet's.
CAMERA_NAMES = {
    "front": "front_camera",
    "front_left": "front_left_camera",
    "front_right": "front_right_camera",
    "side_left": "left_camera",
    "side_right": "right_camera",
}
#: the sibling (PandarGT) box of a moving car lies this far ahead of its Pandar64 box (metres).
SIBLING_SHIFT = 0.3
#: the parked car's box centre jitters by up to this much (metres) from frame to frame.
PARKED_JITTER = 0.15
#: the cuboids are this much larger than the source's boxes on every side (annotators draw them loose;
#: a LiDAR return on the box's surface is then inside it).
BOX_MARGIN = 0.05
#: the extra (parked, walking) boxes float this high above the source scene: no point falls in them.
EXTRA_HEIGHT = 30.0
#: returns off the recording car's roof written into each sweep (d = 0), inside the loader's ego box.
ROOF_POINTS = 40
T0 = 1557539956.5
_CUBOID_COLUMNS = [
    "uuid",
    "label",
    "yaw",
    "stationary",
    "camera_used",
    "position.x",
    "position.y",
    "position.z",
    "dimensions.x",
    "dimensions.y",
    "dimensions.z",
    "attributes.object_motion",
    "cuboids.sibling_id",
    "cuboids.sensor_id",
    "attributes.rider_status",
    "attributes.pedestrian_behavior",
    "attributes.pedestrian_age",
]


def quat_wxyz(R: np.ndarray) -> list[float]:
    """Rotation matrix → quaternion (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat(scalar_first=True).tolist()


def pose_entry(m: np.ndarray) -> dict:
    """A 4×4 sensor → world pose as a PandaSet ``poses.json`` entry."""
    w, x, y, z = quat_wxyz(m[:3, :3])
    p = m[:3, 3]
    return {
        "position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
        "heading": {"w": w, "x": x, "y": y, "z": z},
    }


def write_pickle(df, path: Path) -> None:
    """A DataFrame as PandaSet stores it: pickled (protocol 3), gzip'd, strings as numpy objects."""
    import pandas as pd

    df = df.copy()
    for c in df.columns:
        if df[c].dtype == object or isinstance(df[c].dtype, pd.StringDtype):
            df[c] = np.asarray(df[c].tolist(), dtype=object)
            df[c] = df[c].astype(object)
    df.columns = pd.Index(list(df.columns), dtype=object)
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wb") as f:
        pickle.dump(df, f, protocol=3)


def box_row(uuid, label, centre, yaw, lwh, *, stationary=False, sensor=-1, sibling="-", motion="Moving"):
    """One cuboid row: ``lwh`` length, width, height; ``yaw`` PandaSet's (0 facing +y)."""
    return {
        "uuid": uuid,
        "label": label,
        "yaw": float(yaw),
        "stationary": bool(stationary),
        "camera_used": 0,
        "position.x": float(centre[0]),
        "position.y": float(centre[1]),
        "position.z": float(centre[2]),
        "dimensions.x": float(lwh[1]),
        "dimensions.y": float(lwh[0]),
        "dimensions.z": float(lwh[2]),
        "attributes.object_motion": motion,
        "cuboids.sibling_id": sibling,
        "cuboids.sensor_id": int(sensor),
        "attributes.rider_status": math.nan,
        "attributes.pedestrian_behavior": math.nan,
        "attributes.pedestrian_age": math.nan,
    }


def pandaset_yaw(object_to_world: np.ndarray) -> float:
    """PandaSet's yaw of a box whose x axis (length) is the heading: ``(-sin yaw, cos yaw) = heading``."""
    hx, hy = object_to_world[0, 0], object_to_world[1, 0]
    return math.atan2(-hx, hy)


def write_pandaset_sequence(src: Scene, root: Path) -> dict:
    """Write ``src`` as a PandaSet sequence folder ``root``; ground truth for the tests.

    Returns:
        ``lidar0``: the Pandar64 position at frame 0 in the source world (what the loader
        subtracts, less :data:`GLOBAL`); ``moving``: source track id → its Pandar64 uuid;
        ``centre``: source track id → ``(F, 3)`` box centres in the source world; ``parked``,
        ``pedestrian``: their uuids; ``d``: frame → the ``d`` column written.
    """
    import pandas as pd

    root.mkdir(parents=True)
    n = len(src.frames)
    shift = np.eye(4)
    shift[:3, 3] = GLOBAL
    lidar_poses = [shift @ f.ego_to_world.double().numpy() @ LIDAR_IN_EGO for f in src.frames]
    (root / "lidar").mkdir()
    (root / "lidar" / "poses.json").write_text(json.dumps([pose_entry(m) for m in lidar_poses]))
    (root / "lidar" / "timestamps.json").write_text(json.dumps([T0 + f.timestamp for f in src.frames]))
    (root / "meta").mkdir()
    (root / "meta" / "timestamps.json").write_text(json.dumps([T0 + f.timestamp for f in src.frames]))
    (root / "meta" / "gps.json").write_text(json.dumps([{"lat": 37.7, "long": -122.4, "height": 3.0}] * n))
    for cam, info in src.cameras_info.items():
        d = root / "camera" / CAMERA_NAMES[cam]
        d.mkdir(parents=True)
        K = info.K.double()
        (d / "intrinsics.json").write_text(
            json.dumps(
                {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}
            )
        )
        poses, stamps = [], []
        for f in src.frames:
            v = next(src.views[i] for i in f.view_ids if src.views[i].camera == cam)
            poses.append(pose_entry(shift @ v.cam_to_world.double().numpy()))
            stamps.append(T0 + v.timestamp)
            assert v.image is not None and v.image.suffix == ".jpg"
            shutil.copyfile(v.image, d / f"{f.index:02d}.jpg")
        (d / "poses.json").write_text(json.dumps(poses))
        (d / "timestamps.json").write_text(json.dumps(stamps))

    truth: dict = {"lidar0": lidar_poses[0][:3, 3] - GLOBAL, "d": {}}
    truth["moving"] = {tid: f"moving-{tid}-p64" for tid in src.tracks}
    truth["parked"], truth["pedestrian"] = "parked-jitter", "walker"
    truth["centre"] = {}
    for fi, f in enumerate(src.frames):
        lf = src.lidar(f.index)
        pts = lf.points.double().numpy()
        ego = f.ego_to_world.double().numpy()
        local = (pts - ego[:3, 3]) @ ego[:3, :3]  # ego frame: x forward
        ahead = (local[:, 0] > 0) & (np.abs(local[:, 1]) < 0.6 * local[:, 0])  # the PandarGT's ±31°
        # returns off the car's own roof (in the Pandar64 frame: x right, y forward, z up), as in PandaSet
        roof_local = np.stack([np.linspace(-0.9, 0.7, ROOF_POINTS), np.linspace(-0.8, 1.9, ROOF_POINTS),
                               np.full(ROOF_POINTS, -0.4)], 1)  # fmt: skip
        roof = roof_local @ lidar_poses[fi][:3, :3].T + lidar_poses[fi][:3, 3] - GLOBAL
        pts = np.concatenate([pts, roof])
        d = np.concatenate([ahead, np.zeros(ROOF_POINTS, dtype=bool)]).astype(np.int64)
        truth["d"][fi] = d
        world = pts + GLOBAL
        df = pd.DataFrame(
            {
                "x": world[:, 0],
                "y": world[:, 1],
                "z": world[:, 2],
                "i": np.linspace(0, 255, len(pts)).round(),
                "t": T0 + f.timestamp + np.linspace(0.0, 0.1, len(pts)),
                "d": d,
            }
        )
        write_pickle(df, root / "lidar" / f"{f.index:02d}.pkl.gz")

        rows = []
        for tid, t in sorted(src.tracks.items()):
            if not bool(t.valid[fi]):
                continue
            o2w = t.object_to_world[fi].double().numpy()
            lo, hi = (c.double().numpy() for c in box_corners(t).aminmax(dim=0))
            centre_local = (lo + hi) / 2
            centre = o2w[:3, :3] @ centre_local + o2w[:3, 3]
            truth["centre"].setdefault(tid, np.zeros((n, 3)))[fi] = centre
            yaw, lwh, heading = pandaset_yaw(o2w), hi - lo + 2 * BOX_MARGIN, o2w[:3, 0]
            p64, gt = truth["moving"][tid], f"moving-{tid}-gt"
            rows.append(box_row(p64, "Car", centre + GLOBAL, yaw, lwh, sensor=0, sibling=gt))
            rows.append(
                box_row(gt, "Car", centre + GLOBAL + SIBLING_SHIFT * heading, yaw, lwh, sensor=1, sibling=p64)
            )
        jitter = PARKED_JITTER * np.array([math.sin(2.1 * fi), math.cos(1.3 * fi), 0.0])
        parked = GLOBAL + np.array([6.0, 4.5, EXTRA_HEIGHT]) + jitter
        rows.append(box_row("parked-jitter", "Car", parked, 0.3 + 0.02 * math.sin(fi), (4.5, 1.9, 1.5),
                            stationary=True, motion="Parked"))  # fmt: skip
        walker = GLOBAL + np.array([8.0 + 0.15 * fi, -3.5, EXTRA_HEIGHT])
        rows.append(box_row("walker", "Pedestrian", walker, 0.0, (0.7, 0.6, 1.8), motion=math.nan))
        df = pd.DataFrame(rows, columns=_CUBOID_COLUMNS)
        write_pickle(df, root / "annotations" / "cuboids" / f"{f.index:02d}.pkl.gz")
    return truth
