"""A small photo collection with known cameras: a textured room with a box in it, ray-cast (for SfM tests).

The world has ``+z`` up: a floor ``z = 0`` and four walls around ``[-4, 4]^2`` (3 units high) and a
box ``[-0.8, 0.8]^2 x [0, 1.6]`` in the middle, every face with its own seeded multi-scale noise
texture (the blobs SIFT finds). The cameras stand on an arc of radius 3 at height 1.5 looking at
the box, as a photographer walking around an object. Photos are written as PNG or JPEG, at
their own sizes: one is 1.5x larger (a different camera), one is stored sideways with the EXIF
orientation tag 6 that shows it upright (its pixel grid is portrait; the camera rolled by 90°).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image
from scipy.ndimage import gaussian_filter, map_coordinates

#: The faces: (origin, edge u, edge v) of each textured rectangle (points origin + a u + b v, a, b in [0, 1]).
_FACES = [
    ((-4, -4, 0), (8, 0, 0), (0, 8, 0)),  # floor
    ((-4, -4, 0), (8, 0, 0), (0, 0, 3)),  # walls
    ((-4, 4, 0), (8, 0, 0), (0, 0, 3)),
    ((-4, -4, 0), (0, 8, 0), (0, 0, 3)),
    ((4, -4, 0), (0, 8, 0), (0, 0, 3)),
    ((-0.8, -0.8, 1.6), (1.6, 0, 0), (0, 1.6, 0)),  # the box: top and sides
    ((-0.8, -0.8, 0), (1.6, 0, 0), (0, 0, 1.6)),
    ((-0.8, 0.8, 0), (1.6, 0, 0), (0, 0, 1.6)),
    ((-0.8, -0.8, 0), (0, 1.6, 0), (0, 0, 1.6)),
    ((0.8, -0.8, 0), (0, 1.6, 0), (0, 0, 1.6)),
]


def _texture(rng: np.random.Generator, size: int = 384) -> np.ndarray:
    """``(size, size, 3)`` in [0, 1]: noise blurred at several scales, a colour per scale."""
    tex = np.zeros((size, size, 3))
    for sigma in (1.5, 4.0, 10.0):
        noise = gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
        tex += (noise / noise.std())[..., None] * rng.uniform(0.3, 1.0, 3)
    return 1.0 / (1.0 + np.exp(-1.2 * tex))


def look_at(position: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``(4, 4)`` camera-to-world, OpenCV axes (x right, y down, z forward), no roll."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    c2w[:3, 3] = position
    return c2w


def render(c2w: np.ndarray, K: np.ndarray, size: tuple[int, int], textures: list, supersample: int = 2):
    """Ray-cast the room: ``(H, W, 3)`` uint8 (``size`` = ``(H, W)``; pixel centres at integers)."""
    h, w = size
    s = supersample
    v, u = np.mgrid[0 : h * s, 0 : w * s].astype(np.float64)
    pix = np.stack([(u + 0.5) / s - 0.5, (v + 0.5) / s - 0.5, np.ones_like(u)], -1)
    rays = pix @ np.linalg.inv(K).T @ c2w[:3, :3].T
    origin = c2w[:3, 3]
    best = np.full(rays.shape[:2], np.inf)
    color = np.zeros((*rays.shape[:2], 3))
    for (o, eu, ev), tex in zip(_FACES, textures):
        o, eu, ev = (np.asarray(a, dtype=np.float64) for a in (o, eu, ev))
        n = np.cross(eu, ev)
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((o - origin) @ n) / denom
        hit = origin + t[..., None] * rays - o
        a = hit @ eu / (eu @ eu)
        b = hit @ ev / (ev @ ev)
        ok = (t > 1e-6) & (t < best) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        best = np.where(ok, t, best)
        n_tex = tex.shape[0] - 1
        coords = [b[ok] * n_tex, a[ok] * n_tex]
        color[ok] = np.stack([map_coordinates(tex[..., c], coords, order=1) for c in range(3)], -1)
    color = color.reshape(h, s, w, s, 3).mean(axis=(1, 3))
    return np.round(color * 255).astype(np.uint8)


#: The photo stored sideways (EXIF orientation 6) and the one 1.5x larger.
SIDEWAYS, LARGER = 5, 3


def photo_cameras(num: int = 10, size: tuple[int, int] = (180, 240)) -> dict:
    """The cameras of :func:`write_photo_set` (upright, as rendered): on the arc, looking at the box.

    Returns:
        ``{"cam_to_world" (N, 4, 4), "K" (N, 3, 3), "sizes" [(H, W)]}``, focal length ``0.9 W``.
    """
    c2ws, Ks, sizes = [], [], []
    for i in range(num):
        angle = np.deg2rad(-70 + 140 * i / max(num - 1, 1))
        position = np.array([3.0 * np.cos(angle), 3.0 * np.sin(angle), 1.5 + 0.2 * np.sin(3 * angle)])
        c2ws.append(look_at(position, np.array([0.0, 0.0, 0.7])))
        h, w = size if i != LARGER else (int(size[0] * 1.5), int(size[1] * 1.5))
        Ks.append(np.array([[0.9 * w, 0, (w - 1) / 2], [0, 0.9 * w, (h - 1) / 2], [0, 0, 1]]))
        sizes.append((h, w))
    return {"cam_to_world": np.stack(c2ws), "K": np.stack(Ks), "sizes": sizes}


def sideways(c2w: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, tuple]:
    """The camera of an upright photo's pixel grid turned 90° counter-clockwise (``np.rot90``).

    That grid is what a photo stored sideways with EXIF orientation 6 holds: ``(W, H)`` pixels,
    ``raw[r, c] = upright[c, W - 1 - r]``; its camera is the upright one rolled about its z axis.
    """
    h, w = size
    roll = np.eye(4)
    roll[:3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # columns: raw axes in upright axes
    K = np.array([[K[0, 0], 0, (h - 1) / 2], [0, K[1, 1], (w - 1) / 2], [0, 0, 1]])
    return c2w @ roll, K, (w, h)


def write_photo_set(folder: Path, num: int = 10, size: tuple[int, int] = (180, 240), seed: int = 0) -> dict:
    """Write ``num`` photos of the room into ``folder``; return their true cameras.

    Photo :data:`LARGER` is 1.5x larger (its own camera), photo :data:`SIDEWAYS` a JPEG stored
    sideways with EXIF orientation 6 (rotate 90° clockwise to show it: its pixel grid is
    ``(W, H)``, its camera rolled, :func:`sideways`), the others PNGs of ``size`` ``(H, W)``, all
    with the focal length ``0.9 W`` (:func:`photo_cameras`).

    Returns:
        ``{"names", "cam_to_world" (N, 4, 4) of the stored pixel grids, "K" (N, 3, 3), "sizes" [(H, W)]}``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    textures = [_texture(rng) for _ in _FACES]
    cams = photo_cameras(num, size)
    names = []
    for i in range(num):
        image = render(cams["cam_to_world"][i], cams["K"][i], cams["sizes"][i], textures)
        if i == SIDEWAYS:
            exif = Image.Exif()
            exif[0x0112] = 6
            name = f"photo_{i:02d}.jpg"
            Image.fromarray(np.ascontiguousarray(np.rot90(image))).save(folder / name, exif=exif, quality=95)
            c2w, K, hw = sideways(cams["cam_to_world"][i], cams["K"][i], cams["sizes"][i])
            cams["cam_to_world"][i], cams["K"][i], cams["sizes"][i] = c2w, K, hw
        else:
            name = f"photo_{i:02d}.png"
            Image.fromarray(image).save(folder / name)
        names.append(name)
    return {"names": names, **cams}
