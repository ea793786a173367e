"""A small Argoverse 2 sensor-dataset log written from known geometry (for the reader's tests).

The layout, file names, columns and dtypes are the release's (as the ``av2`` devkit reads them):
``city_SE3_egovehicle.feather`` (here at ~77 Hz, not at the sensors' timestamps),
``calibration/{egovehicle_SE3_sensor,intrinsics}.feather``, ``sensors/lidar/<ts>.feather``
(float16 ``x, y, z`` in the ego frame at the sweep's time, uint8 ``intensity`` and
``laser_number``, uint32 ``offset_ns``), ``sensors/cameras/<camera>/<ts>.jpg`` (20 Hz, each camera
with its own phase) and ``annotations.feather``.

Geometry (all known in closed form, see :class:`Truth`): the ego drives at a constant velocity and
yaw rate (so slerp + linear interpolation of its poses is exact), a wall and a ground patch are
static, car ``moving`` drives along the city x axis, car ``parked`` stands still with labels that
jitter by up to 3 cm, and a pedestrian walks.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
from PIL import Image
from scipy.spatial.transform import Rotation

T0 = 315_966_265_659_927_216  # an AV2-like nanosecond timestamp of the first sweep
SWEEP_NS = 100_000_000
CAMERA_NS = 50_000_000
LOG_ID = "0c6e62d7-bdfa-3061-8d3d-03b13aa21f68"
#: camera → (yaw in the ego frame, image phase relative to the sweeps in ns)
CAMERAS = {
    "ring_front_center": (0.0, 3_000_000),
    "ring_front_left": (0.8, 17_000_000),
    "ring_side_right": (-1.4, -21_000_000),
}
WIDTH, HEIGHT = 40, 30
FOCAL = 24.0
#: ego → city at time t (seconds since T0): yaw rate 0.3 rad/s, velocity (8, 1.5, 0.05) m/s
YAW_RATE, VELOCITY, CITY_ORIGIN = 0.3, np.array([8.0, 1.5, 0.05]), np.array([2500.0, -1300.0, 12.0])
MOVING_START, MOVING_VELOCITY = np.array([2520.0, -1296.0, 12.8]), np.array([5.0, 0.0, 0.0])
PARKED = np.array([2515.0, -1306.0, 12.75])
CAR_LWH = np.array([4.5, 1.9, 1.6])


def quat_wxyz(m: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(m[..., :3, :3]).as_quat(scalar_first=True)


def se3(rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, t
    return m


def city_SE3_ego(t_s: float) -> np.ndarray:
    """The true ego → city pose at ``t_s`` seconds after :data:`T0`."""
    return se3(Rotation.from_euler("z", 0.1 + YAW_RATE * t_s).as_matrix(), CITY_ORIGIN + VELOCITY * t_s)


def camera_to_ego(yaw: float) -> np.ndarray:
    """An OpenCV camera (x right, y down, z forward) looking along ego yaw ``yaw``, 1.6 m up."""
    cv_in_ego = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    rot = Rotation.from_euler("z", yaw).as_matrix() @ cv_in_ego
    return se3(rot, np.array([1.2, 0.0, 1.6]) + 0.3 * np.array([np.cos(yaw), np.sin(yaw), 0.0]))


UP_LIDAR = se3(Rotation.from_euler("z", 0.01).as_matrix(), np.array([1.35, 0.0, 1.9]))
DOWN_LIDAR = se3(Rotation.from_euler("x", 0.02).as_matrix(), np.array([1.35, 0.0, 1.75]))


def moving_box(t_s: float) -> np.ndarray:
    return se3(Rotation.from_euler("z", 0.0).as_matrix(), MOVING_START + MOVING_VELOCITY * t_s)


def parked_box(k: int) -> np.ndarray:
    jitter = np.random.default_rng(k).uniform(-0.03, 0.03, 3)
    return se3(Rotation.from_euler("z", 1.2 + 0.01 * jitter[0]).as_matrix(), PARKED + jitter)


def pedestrian_box(t_s: float) -> np.ndarray:
    return se3(np.eye(3), np.array([2512.0, -1292.0, 12.9]) + np.array([0.0, 1.4, 0.0]) * t_s)


class Truth(NamedTuple):
    sweeps_ns: list[int]
    images_ns: dict[str, list[int]]
    log_dir: Path


def static_points() -> np.ndarray:
    """City points of a wall ahead, a wall on the left, and the ground."""
    rng = np.random.default_rng(0)
    ys, zs = np.meshgrid(np.linspace(-1330, -1270, 50), np.linspace(12.0, 18.0, 12))
    wall = np.stack([np.full(ys.size, 2545.0), ys.ravel(), zs.ravel()], -1)
    xs, zs = np.meshgrid(np.linspace(2495, 2545, 50), np.linspace(12.0, 16.0, 8))
    left = np.stack([xs.ravel(), np.full(xs.size, -1280.0), zs.ravel()], -1)
    right = left * np.array([1.0, 0.0, 1.0]) + np.array([0.0, -1318.0, 0.0])
    ground = np.stack(
        [rng.uniform(2495, 2545, 1500), rng.uniform(-1318, -1280, 1500), np.full(1500, 12.0)], -1
    )
    return np.concatenate([wall, left, right, ground])


def box_surface(box: np.ndarray, lwh: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` city points inside a box, near its faces (at 80 % of the half extents)."""
    u = np.random.default_rng(seed).uniform(-1, 1, (n, 3))
    u[np.arange(n), np.arange(n) % 3] = np.sign(u[np.arange(n), np.arange(n) % 3])
    local = 0.4 * u * lwh
    return local @ box[:3, :3].T + box[:3, 3]


def jpeg(rng: np.random.Generator) -> bytes:
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    base = np.stack([xx / WIDTH, yy / HEIGHT, 0.5 + 0.5 * np.sin(xx / 3.0)], -1)
    img = np.clip(base + rng.normal(0, 0.05, base.shape), 0, 1)
    buf = io.BytesIO()
    Image.fromarray((img * 255).astype(np.uint8)).save(buf, format="JPEG", quality=95)
    return buf.getvalue()


def write_feather(path: Path, columns: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    feather.write_feather(pa.table(columns), path)


def write_log(
    split_dir: Path, num_sweeps: int = 8, k123: tuple[float, float, float] = (-0.1, 0.02, 0.0)
) -> Truth:
    """Write the log to ``split_dir/LOG_ID``; the true timestamps."""
    log = split_dir / LOG_ID
    sweeps = [T0 + k * SWEEP_NS + int(k * 137) for k in range(num_sweeps)]  # slightly irregular
    # poses: every 13 ms (never at a sensor timestamp), from before the first image to after the last
    pose_ts = np.arange(T0 - 40_000_000, sweeps[-1] + 40_000_000, 13_000_000) + 111
    cols: dict = {"timestamp_ns": pa.array(pose_ts, pa.int64())}
    mats = np.stack([city_SE3_ego((t - T0) * 1e-9) for t in pose_ts])
    q = quat_wxyz(mats)
    cols.update({k: q[:, i] for i, k in enumerate(("qw", "qx", "qy", "qz"))})
    cols.update({k: mats[:, i, 3] for i, k in enumerate(("tx_m", "ty_m", "tz_m"))})
    write_feather(log / "city_SE3_egovehicle.feather", cols)

    names = [*CAMERAS, "up_lidar", "down_lidar", "stereo_front_left"]
    ext = [camera_to_ego(CAMERAS[n][0]) for n in CAMERAS] + [UP_LIDAR, DOWN_LIDAR, camera_to_ego(0.0)]
    q = quat_wxyz(np.stack(ext))
    write_feather(
        log / "calibration" / "egovehicle_SE3_sensor.feather",
        {
            "sensor_name": names,
            **{k: q[:, i] for i, k in enumerate(("qw", "qx", "qy", "qz"))},
            **{k: [float(e[i, 3]) for e in ext] for i, k in enumerate(("tx_m", "ty_m", "tz_m"))},
        },
    )
    cams = [*CAMERAS, "stereo_front_left"]  # the stereo camera has calibration but no images here
    write_feather(
        log / "calibration" / "intrinsics.feather",
        {
            "sensor_name": cams,
            "fx_px": [FOCAL] * len(cams),
            "fy_px": [FOCAL * 1.01] * len(cams),
            "cx_px": [19.3] * len(cams),
            "cy_px": [14.8] * len(cams),
            "k1": [k123[0]] * len(cams),
            "k2": [k123[1]] * len(cams),
            "k3": [k123[2]] * len(cams),
            "height_px": pa.array([HEIGHT] * len(cams), pa.int64()),
            "width_px": pa.array([WIDTH] * len(cams), pa.int64()),
        },
    )

    rng = np.random.default_rng(1)
    images: dict[str, list[int]] = {}
    for n, (_, phase) in CAMERAS.items():
        folder = log / "sensors" / "cameras" / n
        folder.mkdir(parents=True)
        stamps = [T0 + phase + j * CAMERA_NS + int(rng.integers(0, 500)) for j in range(2 * num_sweeps)]
        stamps = [t for t in stamps if T0 - 30_000_000 <= t <= sweeps[-1] + 30_000_000]
        for t in stamps:
            (folder / f"{t}.jpg").write_bytes(jpeg(rng))
        images[n] = [min(stamps, key=lambda t, s=s: abs(t - s)) for s in sweeps]

    static = static_points()
    uuids = {
        "moving": "9a1f0c22-2d6e-4b3f-9a55-6f0f1e2d3c4b",
        "parked": "1b2c3d4e-0000-4a4a-8b8b-000000000001",
        "walker": "77777777-aaaa-4bbb-8ccc-dddddddddddd",
    }
    ann: dict[str, list] = {
        k: []
        for k in (
            "timestamp_ns",
            "track_uuid",
            "category",
            "length_m",
            "width_m",
            "height_m",
            "qw",
            "qx",
            "qy",
            "qz",
            "tx_m",
            "ty_m",
            "tz_m",
            "num_interior_pts",
        )
    }
    for k, s in enumerate(sweeps):
        t = (s - T0) * 1e-9
        ego = city_SE3_ego(t)
        city_to_ego = np.linalg.inv(ego)
        boxes = {
            "moving": (moving_box(t), CAR_LWH, "REGULAR_VEHICLE"),
            "parked": (parked_box(k), CAR_LWH, "REGULAR_VEHICLE"),
            "walker": (pedestrian_box(t), np.array([0.6, 0.6, 1.8]), "PEDESTRIAN"),
        }
        pts = [
            static,
            box_surface(boxes["moving"][0], CAR_LWH, 200, k),
            box_surface(boxes["parked"][0], CAR_LWH, 150, 100 + k),
        ]
        city = np.concatenate(pts)
        local = city @ city_to_ego[:3, :3].T + city_to_ego[:3, 3]
        n = len(local)
        write_feather(
            log / "sensors" / "lidar" / f"{s}.feather",
            {
                "x": pa.array(local[:, 0].astype(np.float16)),
                "y": pa.array(local[:, 1].astype(np.float16)),
                "z": pa.array(local[:, 2].astype(np.float16)),
                "intensity": pa.array(rng.integers(0, 255, n).astype(np.uint8)),
                "laser_number": pa.array(rng.integers(0, 64, n).astype(np.uint8)),
                "offset_ns": pa.array(rng.integers(0, 99_000_000, n).astype(np.uint32)),
            },
        )
        for key, (box, lwh, cat) in boxes.items():
            in_ego = city_to_ego @ box
            qb = quat_wxyz(in_ego)
            ann["timestamp_ns"].append(s)
            ann["track_uuid"].append(uuids[key])
            ann["category"].append(cat)
            ann["length_m"].append(float(lwh[0]))
            ann["width_m"].append(float(lwh[1]))
            ann["height_m"].append(float(lwh[2]))
            for i, c in enumerate(("qw", "qx", "qy", "qz")):
                ann[c].append(float(qb[i]))
            for i, c in enumerate(("tx_m", "ty_m", "tz_m")):
                ann[c].append(float(in_ego[i, 3]))
            ann["num_interior_pts"].append(100)
    ann_cols = {k: v for k, v in ann.items()}
    ann_cols["timestamp_ns"] = pa.array(ann["timestamp_ns"], pa.int64())
    ann_cols["num_interior_pts"] = pa.array(ann["num_interior_pts"], pa.int64())
    ann_cols["category"] = pa.array(ann["category"]).dictionary_encode()  # pandas writes categoricals so
    write_feather(log / "annotations.feather", ann_cols)
    return Truth(sweeps, images, log)
