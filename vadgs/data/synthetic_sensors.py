"""The sensors of a procedural segment (:mod:`vadgs.data.synthetic`): the rig, and what each sees.

The rig (:data:`RIG`, :func:`rig_cam_to_ego`, :data:`LIDAR_IN_EGO`) is Waymo-like: up to five
cameras and a spinning LiDAR on the roof. A segment's scene is boxes (:class:`SegmentWorld`,
:class:`SegmentBoxes`; each box a :class:`BoxKind`), cast with Embree on their triangles
(:func:`box_triangles`) at a frame's poses (:func:`frame_poses`, :class:`RayCaster`), so colour,
z-depth, instance ids and LiDAR agree exactly. :func:`render_view` renders a camera's colour, depth
and instance images; :func:`lidar_scan` a spin of the LiDAR. Colour is a procedural albedo (a
function of the surface point in the box's own frame, so every view, and a moving car's every pose,
agrees) times a Lambert sun plus ambient; there are no shadows and no camera noise. Sky: depth 0,
instance 0.
"""

from __future__ import annotations

import enum
import math
from typing import NamedTuple

import numpy as np

__all__ = [
    "LIDAR_IN_EGO",
    "RIG",
    "BoxKind",
    "RayCaster",
    "SegmentBoxes",
    "SegmentWorld",
    "box_triangles",
    "frame_poses",
    "lidar_scan",
    "render_view",
    "rig_cam_to_ego",
]


RIG: dict[str, tuple[float, bool]] = {
    "front": (0.0, False),
    "front_left": (45.0, False),
    "front_right": (-45.0, False),
    "side_left": (90.0, True),
    "side_right": (-90.0, True),
}
"""Camera name → (yaw in degrees, left positive; whether it uses ``side_height``), Waymo's order."""

#: The LiDAR's position in the ego frame (metres).
LIDAR_IN_EGO = np.array([0.0, 0.0, 2.0])


def rig_cam_to_ego(camera: str) -> np.ndarray:
    """``(4, 4)`` cam_to_ego of a :data:`RIG` camera (OpenCV axes, pitched 2° down)."""
    yaw = math.radians(RIG[camera][0])
    pitch = math.radians(-2.0)
    fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], 1)
    T[:3, 3] = [1.5 * math.cos(yaw), 0.9 * math.sin(yaw), 1.6]
    return T


class BoxKind(enum.IntEnum):
    """What a box is: it picks the box's procedural texture (:func:`render_view`)."""

    ROAD = 0
    WALKWAY = 1
    BUILDING = 2
    POLE = 3
    BOARD = 4
    CAR = 5


class SegmentBoxes(NamedTuple):
    """The scene's boxes; box ``b`` spans ``[-l/2, l/2] x [-w/2, w/2] x [0, h]`` in its own frame.

    Attributes:
        size: ``(B, 3)`` l, w, h.
        pose: ``(B, 4, 4)`` box_to_world of the static boxes (moving cars: frame 0).
        kind: ``(B,)`` int, a :class:`BoxKind`.
        instance: ``(B,)`` int instance id.
        color: ``(B, 3)`` float base colour.
        track: ``(B,)`` index into the moving cars, -1 for static boxes.
    """

    size: np.ndarray
    pose: np.ndarray
    kind: np.ndarray
    instance: np.ndarray
    color: np.ndarray
    track: np.ndarray


class SegmentWorld(NamedTuple):
    """A segment's scene: its boxes, its instance table, the moving cars' and the ego's poses.

    Attributes:
        boxes: every box (:class:`SegmentBoxes`).
        instances: the scene's instance table (``scene.json``'s ``instances``).
        car_poses: ``(M, F, 4, 4)`` object_to_world of each moving car per frame.
        ego_to_world: ``(F, 4, 4)``.
    """

    boxes: SegmentBoxes
    instances: list[dict]
    car_poses: np.ndarray
    ego_to_world: np.ndarray


# the 12 triangles of a unit box [-.5, .5]^2 x [0, 1] and their outward normals
_CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)])
_FACES = np.array([
    [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # -x, +x
    [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # -y, +y
    [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # bottom, top
])  # fmt: skip
_NORMALS = np.repeat(
    np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float), 2, 0
)


def box_triangles(size: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``(B * 12, 3, 3)`` world triangles of boxes ``size (B, 3)`` at ``pose (B, 4, 4)``."""
    local = _CORNERS[_FACES][None] * size[:, None, None, :].astype(np.float64)  # (B, 12, 3, 3)
    world = local @ pose[:, None, :3, :3].transpose(0, 1, 3, 2) + pose[:, None, None, :3, 3]
    return world.reshape(-1, 3, 3)


def frame_poses(world: SegmentWorld, frame: int) -> np.ndarray:
    """``(B, 4, 4)`` box_to_world of every box at a frame."""
    poses = world.boxes.pose.copy()
    moving = world.boxes.track >= 0
    poses[moving] = world.car_poses[world.boxes.track[moving], frame]
    return poses


class RayCaster:
    """Embree over the boxes of one frame (:func:`frame_poses`), with each triangle's sun light."""

    def __init__(self, world: SegmentWorld, frame: int):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.poses = frame_poses(world, frame)
        self.poses32 = self.poses.astype(np.float32)
        n_world = np.einsum("bij,tj->bti", self.poses[:, :3, :3], _NORMALS).reshape(-1, 3)
        self.light = (0.5 + 0.55 * np.clip(n_world @ _SUN, 0, None)).astype(np.float32)  # per triangle
        per_box = {
            "tx": self.poses32[:, 0, 3], "ty": self.poses32[:, 1, 3], "tz": self.poses32[:, 2, 3],
            "cos": self.poses32[:, 0, 0], "sin": self.poses32[:, 1, 0], "h": world.boxes.size[:, 2],
            "kind": world.boxes.kind,
        }  # fmt: skip
        self.tri = {k: np.repeat(v, 12) for k, v in per_box.items()}  # per triangle, for 1-D gathers
        self.boxes = world.boxes
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self.scene, box_triangles(world.boxes.size, self.poses).astype(np.float32))

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(t, prim)`` of rays ``origin (3,)`` + t ``dirs (N, 3)``; prim -1 (t inf) on a miss."""
        o = np.ascontiguousarray(np.broadcast_to(origin.astype(np.float32), dirs.shape))
        out = self.scene.run(o, np.ascontiguousarray(dirs, dtype=np.float32), output=1)
        prim = out["primID"].astype(np.int64)
        t = np.where(prim >= 0, out["tfar"], np.inf).astype(np.float32)
        return t, prim


# ---------------------------------------------------------------------------------------------------
# shading


def _hash(*ints: np.ndarray) -> np.ndarray:
    """A float in [0, 1) per element of integer arrays (a small integer hash; deterministic)."""
    h = np.full(np.broadcast(*ints).shape, 2166136261, dtype=np.uint32)
    for k, a in enumerate(ints):
        h ^= (a.astype(np.int64) * (0x9E3779B1 + 2 * k)).astype(np.uint32)
        h *= np.uint32(16777619)
        h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    return (h >> np.uint32(8)).astype(np.float32) / float(1 << 24)


_SUN = (np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])).astype(np.float32)
_HORIZON = np.array([0.78, 0.85, 0.93], dtype=np.float32)
_ZENITH = np.array([0.35, 0.55, 0.88], dtype=np.float32)


def _albedo(kind, p, n, base, h, box_id):
    """Procedural albedo ``(N, 3)`` from the box-frame point ``p``, normal ``n`` and box height ``h``.

    Each kind's pattern is computed on its own pixels only.
    """
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fine = _hash(np.floor(x * 12), np.floor(y * 12), np.floor(z * 12), box_id)
    out = base * (np.float32(0.82) + np.float32(0.3) * fine)[:, None]
    vertical = np.abs(n[:, 2]) < 0.5

    def of(k):
        i = np.flatnonzero(kind == k)
        return i, x[i], y[i], z[i]

    # buildings: a grid of windows on the facades (3 m wide bays, 3.2 m floors), roofs darker
    i, xi, yi, zi = of(BoxKind.BUILDING)
    u = np.where(np.abs(n[i, 1]) > 0.5, xi, yi) + box_id[i] * np.float32(1.37)
    bay, floor = (u / np.float32(3.0)) % 1.0, (zi / np.float32(3.2)) % 1.0
    win = vertical[i] & (zi > 1.2) & (zi < h[i] - 0.8)
    win &= (bay > 0.28) & (bay < 0.72) & (floor > 0.3) & (floor < 0.8)
    w = i[win]
    glass = 0.12 + 0.12 * _hash(np.floor(u[win] / 3.0), np.floor(zi[win] / 3.2), box_id[w])
    out[w] = glass[:, None] * np.array([1.0, 1.15, 1.4], dtype=np.float32)
    out[i[~vertical[i]]] *= 0.6
    # road: dashed centre line, solid lane edges; sidewalk: 1 m tiles
    i, xi, yi, _ = of(BoxKind.ROAD)
    ay = np.abs(yi)
    line = ((ay < 0.08) & ((xi % 6.0) < 3.0)) | (np.abs(ay - 7.0) < 0.08)
    line |= (np.abs(ay - 3.5) < 0.06) & ((xi % 9.0) < 3.0)
    out[i[line]] = 0.85
    i, xi, yi, _ = of(BoxKind.WALKWAY)
    joint = (((xi % 1.0) < 0.04) | (((yi + 0.5) % 1.0) < 0.04)) & ~vertical[i]
    out[i[joint]] *= 0.7
    # sign boards: a white ring on the coloured board (seen from both sides)
    i, _, yi, zi = of(BoxKind.BOARD)
    r = np.hypot(yi, zi - 0.5)
    out[i[(np.abs(n[i, 0]) > 0.9) & (r > 0.3) & (r < 0.42)]] = 0.92
    # cars: a dark window band, dark bumpers
    i, xi, _, zi = of(BoxKind.CAR)
    out[i[vertical[i] & (zi > 0.85) & (zi < 1.35) & (np.abs(xi) < 1.5)]] = 0.1
    out[i[zi < 0.35]] = 0.08
    return out


def _shade(caster: RayCaster, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, prim: np.ndarray):
    """``(N, 3)`` float32 colour of the rays ``origin (3,) + t dirs (N, 3)`` (sky where ``prim < 0``)."""
    hit = prim >= 0
    pr = np.maximum(prim, 0)
    th = np.where(hit, t, 0)
    tri = caster.tri
    # box frame: every box is turned about z only (yaw), so p = R_z(-yaw) (pw - t)
    dx = (origin[0] - np.take(tri["tx"], pr)) + th * dirs[:, 0]
    dy = (origin[1] - np.take(tri["ty"], pr)) + th * dirs[:, 1]
    c, s = np.take(tri["cos"], pr), np.take(tri["sin"], pr)
    p = np.empty((len(pr), 3), np.float32)
    p[:, 0] = c * dx + s * dy
    p[:, 1] = c * dy - s * dx
    h = np.take(tri["h"], pr)
    p[:, 2] = np.clip((origin[2] - np.take(tri["tz"], pr)) + th * dirs[:, 2], 0, h)
    b = pr // 12
    alb = _albedo(np.take(tri["kind"], pr), p, _NORMALS[pr % 12], np.take(caster.boxes.color, b, 0), h, b)
    rgb = alb * np.take(caster.light, pr)[:, None]
    sky = np.flatnonzero(~hit)
    if len(sky):
        d = dirs[sky]
        elev = np.clip(d[:, 2] / np.linalg.norm(d, axis=-1), 0, 1)[:, None]
        rgb[sky] = (1 - elev) * _HORIZON + elev * _ZENITH
    return rgb


_CHUNK = 1 << 19  # rays per Embree call


def render_view(
    caster: RayCaster, K: np.ndarray, cam_to_world: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rgb uint8 (H, W, 3), depth float16 (H, W), instance uint16 (H, W))`` of one view.

    Args:
        caster: the frame's boxes.
        K: ``(3, 3)`` pinhole intrinsics (pixel centres at integers).
        cam_to_world: ``(4, 4)``, OpenCV camera axes.
        size: ``(H, W)``.
    """
    h, w = size
    R, origin = cam_to_world[:3, :3], cam_to_world[:3, 3]
    rgb = np.empty((h * w, 3), np.uint8)
    depth = np.empty(h * w, np.float16)
    inst = np.empty(h * w, np.uint16)
    rows = max(1, _CHUNK // w)
    xs = (np.arange(w) - K[0, 2]) / K[0, 0]
    for r0 in range(0, h, rows):
        ys = (np.arange(r0, min(h, r0 + rows)) - K[1, 2]) / K[1, 1]
        cam = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], 1.0), -1).reshape(-1, 3)
        dirs = (cam @ R.T).astype(np.float32)  # camera z = 1: the hit distance t is the z-depth
        t, prim = caster.cast(origin, dirs)
        sl = slice(r0 * w, r0 * w + len(t))
        hit = prim >= 0
        depth[sl] = np.where(hit, t, 0)
        inst[sl] = np.where(hit, caster.boxes.instance[np.maximum(prim, 0) // 12], 0)
        rgb[sl] = np.clip(_shade(caster, origin, dirs, t, prim) * 255 + 0.5, 0, 255).astype(np.uint8)
    return rgb.reshape(h, w, 3), depth.reshape(h, w), inst.reshape(h, w)


def lidar_scan(
    caster: RayCaster,
    origin: np.ndarray,
    yaw: float,
    beams: int,
    vfov: tuple[float, float],
    num_points: int,
    max_range: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``(points (N, 3) float32 world, instance (N,) uint16)``: a spin of the LiDAR, N = ``num_points``.

    The azimuth step is refined until the hits (within ``max_range``) reach the requested count;
    then ``num_points`` of them are taken evenly in scan order (beam by beam).

    Args:
        caster: the frame's boxes.
        origin: ``(3,)`` the sensor's position in the world.
        yaw: the azimuth of the first ray (radians).
        beams: beams, evenly spread over ``vfov``.
        vfov: ``(lowest, highest)`` beam elevation in degrees.
        num_points: points wanted.
        max_range: the farthest hit kept (metres).
    """
    lo, hi = vfov
    elev = np.radians(np.linspace(hi, lo, beams))
    n_az = max(8, math.ceil(1.6 * num_points / beams))
    for _ in range(8):
        az = yaw + np.linspace(0, 2 * np.pi, n_az, endpoint=False)
        ce = np.cos(elev)[:, None]
        dirs = np.stack(np.broadcast_arrays(ce * np.cos(az), ce * np.sin(az), np.sin(elev)[:, None]), -1)
        t, prim = caster.cast(origin, dirs.reshape(-1, 3))
        keep = (prim >= 0) & (t <= max_range)
        if keep.sum() >= num_points:
            break
        n_az *= 2
    idx = np.flatnonzero(keep)
    if len(idx) > num_points:
        idx = idx[(np.arange(num_points) * len(idx)) // num_points]
    pts = origin + t[idx, None].astype(np.float64) * dirs.reshape(-1, 3)[idx]
    return pts.astype(np.float32), caster.boxes.instance[prim[idx] // 12].astype(np.uint16)
