"""``vadgs sfm``: a folder of photos → a COLMAP project (:func:`vadgs.data.sfm.run_sfm`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import tyro

from vadgs.checks import checked, int_field
from vadgs.cli._common import Command, Flag, Positional

__all__ = ["SfmCommand"]


@dataclass(frozen=True)
class SfmCommand(Command):
    """Reconstruct the cameras of a folder of photos with pycolmap into a COLMAP project for ``vadgs train``.

    Writes ``OUT/images`` (the photos under their own names: unchanged, but those with an EXIF
    rotation written upright, as a viewer shows them), ``OUT/sparse/0`` (the largest model),
    ``OUT/database.db`` and ``OUT/sfm.json``; prints the photos registered and the mean reprojection
    error. Refuses an ``OUT`` inside PHOTOS, a photo that does not decode, and an ``OUT`` another
    process is writing; leaves out photos identical to an earlier one. ``--threads N`` sets
    pycolmap's threads too (0: all cores). Then: ``vadgs train OUT --out RUN``.
    """

    photos: Annotated[str, Positional, tyro.conf.arg(metavar="PHOTOS")]
    """folder of photos (.jpg, .jpeg, .png, .tif, .tiff, .bmp; subfolders included; any sizes)"""
    out: str
    """the COLMAP project folder to write"""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """pairs matched: every pair, or each photo with its 10 successors by name (video frames);
    auto: exhaustive up to 100 photos"""
    camera_mode: Literal["auto", "single", "per-image"] = "auto"
    """cameras: one per photo size and EXIF camera (auto), one for all, or one per photo"""
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE"] = "SIMPLE_RADIAL"
    """COLMAP camera model fitted (vadgs train undistorts the distorted ones)"""
    max_image_size: int = checked(1600, int_field(0))
    """longest side in pixels at which features are detected (the photos are not scaled); 0: full size"""
    link: Flag = False
    """symlink the photos into OUT/images instead of copying them (rotated ones are written upright)"""
    overwrite: Flag = False
    """replace the images/, sparse/, database.db and sfm.json of an existing project in OUT"""
    seed: int = 0
    """random seed of COLMAP's RANSAC and mapping"""
    no_progress: Flag = False
    """no progress bars"""

    def main(self) -> int:
        """Run SfM, print the summary; 0."""
        from vadgs.data.sfm import run_sfm

        res = run_sfm(
            self.photos,
            self.out,
            matcher=self.matcher,
            camera_mode=self.camera_mode,
            camera_model=self.camera_model,
            max_image_size=self.max_image_size,
            link=self.link,
            overwrite=self.overwrite,
            threads=self.threads,
            seed=self.seed,
            progress=not self.no_progress,
        )
        s = res.seconds
        print(
            f"{res.summary()} (features {s['features']} s, matching {s['matching']} s, "
            f"mapping {s['mapping']} s)"
        )
        if res.unregistered:
            shown = ", ".join(res.unregistered[:5]) + (", ..." if len(res.unregistered) > 5 else "")
            print(f"not registered: {shown} (they stay in {res.images} and out of training)")
        print(f"wrote {res.project} (sparse/0, images/); next: vadgs train {res.project} --out RUN")
        return 0
