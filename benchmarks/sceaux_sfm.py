"""Structure from motion on the sceaux castle photos with pycolmap: the COLMAP project for the benchmark.

Downscales the 11 photos (2832x2128) by ``--factor`` (default 4: 708x532, area filter) into
``OUT/images`` (smaller images for the benchmark's training runs), then runs
:func:`vadgs.data.sfm.run_sfm` on them in place (what ``vadgs sfm OUT/images --out OUT`` does: SIFT
with one shared SIMPLE_RADIAL camera, exhaustive matching, incremental mapping into
``OUT/sparse/0``, the largest model). Deterministic up to COLMAP's own RANSAC seeding, which
pycolmap fixes (``random_seed``), on one thread. For your own photos, at their own sizes and
unchanged, use ``vadgs sfm PHOTOS --out PROJECT`` instead.

Run (from the repository root; ../shared present; about a minute on one CPU core):

    python benchmarks/sceaux_sfm.py /work/shared/data/real/sceaux_castle/images --out /work/runs/sceaux

``--mixed-sizes`` makes a photo collection instead: every photo at its own size and with its own
camera (see :data:`MIXED_FACTORS`).

then train on the project folder, e.g. ``vadgs train /work/runs/sceaux --out ...`` (see
``docs/results.md``, "A COLMAP scene").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from PIL import Image

MIXED_FACTORS = (1.0, 1.3, 1.6, 1.15)
"""``--mixed-sizes``: photo ``i`` is downscaled by ``factor * MIXED_FACTORS[i % 4]`` and cropped by
``i % 3`` percent on the right: a collection of photos of different sizes, one camera each."""


def downscale_images(src: Path, dst: Path, factor: int, mixed: bool = False) -> list[str]:
    """Write every JPG/PNG of ``src`` to ``dst`` at ``1 / factor`` of its size (PNG, lossless).

    ``mixed``: every photo at its own size (see :data:`MIXED_FACTORS`), as in a photo collection.
    """
    dst.mkdir(parents=True, exist_ok=True)
    names = []
    photos = [p for p in sorted(src.iterdir()) if p.suffix.lower() in (".jpg", ".jpeg", ".png")]
    for i, p in enumerate(photos):
        f = factor * (MIXED_FACTORS[i % len(MIXED_FACTORS)] if mixed else 1.0)
        with Image.open(p) as im:
            im = im.convert("RGB")
            small = im.resize((int(im.width / f), int(im.height / f)), Image.Resampling.BOX)
        if mixed and i % 3:
            small = small.crop((0, 0, small.width * (100 - i % 3) // 100, small.height))
        name = p.stem + ".png"
        small.save(dst / name)
        names.append(name)
    return names


def run_benchmark_sfm(out: Path, threads: int = 1, seed: int = 0, per_image: bool = False) -> dict:
    """:func:`vadgs.data.sfm.run_sfm` on ``out/images`` in place (exhaustive matching); a summary.

    ``per_image``: one camera per photo, else one shared camera. The features are detected on
    the downscaled photos as they are (no further limit).
    """
    import pycolmap

    from vadgs.data.sfm import run_sfm

    res = run_sfm(
        out / "images",
        out,
        matcher="exhaustive",
        camera_mode="per-image" if per_image else "single",
        max_image_size=0,
        overwrite=True,
        threads=threads,
        seed=seed,
        progress=False,
    )
    best = pycolmap.Reconstruction(str(res.model))
    return {
        "images": res.num_photos,
        "registered": res.registered,
        "points": res.num_points,
        "mean_track_length": round(best.compute_mean_track_length(), 2),
        "mean_reprojection_error_px": round(res.mean_reprojection_error, 3),
        "cameras": res.num_cameras,
        "image_sizes": sorted({(c.width, c.height) for c in best.cameras.values()}),
        "camera": str(next(iter(best.cameras.values()))),
        "features_and_matching_s": round(res.seconds["features"] + res.seconds["matching"], 1),
        "mapping_s": res.seconds["mapping"],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("images", type=Path, help="the photos (../shared/data/real/sceaux_castle/images)")
    p.add_argument("--out", type=Path, required=True, help="COLMAP project folder to write")
    p.add_argument("--factor", type=int, default=4, help="downscale factor of the photos (default 4)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mixed-sizes", action="store_true", help="photos of different sizes, one camera each")
    args = p.parse_args()
    names = downscale_images(args.images, args.out / "images", args.factor, args.mixed_sizes)
    sfm = run_benchmark_sfm(args.out, args.threads, args.seed, per_image=args.mixed_sizes)
    summary = {"factor": args.factor, "mixed_sizes": args.mixed_sizes, "names": names, **sfm}
    (args.out / "sfm.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
