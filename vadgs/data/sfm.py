"""Structure from motion with pycolmap: a folder of photos → a COLMAP project that ``vadgs train`` reads.

:func:`run_sfm` is what ``vadgs sfm PHOTOS --out PROJECT`` runs (nerfstudio's ``ns-process-data
images``, COLMAP's automatic reconstructor), in four pycolmap steps:

1. **Features.** SIFT (:func:`pycolmap.extract_features`), at most ``max_image_size`` pixels on the
   longest side *for the detection only* (keypoints are in the photo's own pixels). Cameras
   (``camera_mode``): ``"auto"`` makes one camera per group of photos with the same pixel size
   and EXIF camera (make, model, focal length), so that photos of one camera share their
   intrinsics; ``"single"``: one for all (one size needed); ``"per-image"``: one each.
2. **Matching** (``matcher``): ``"exhaustive"`` matches every pair, ``"sequential"`` each photo
   with its :data:`SEQUENTIAL_OVERLAP` successors in name order (video frames); ``"auto"`` is
   exhaustive up to :data:`EXHAUSTIVE_MAX` photos, sequential beyond.
3. **Incremental mapping** (:func:`pycolmap.incremental_mapping`); the largest model is kept.
4. **The project**: ``PROJECT/sparse/0`` (the model), ``PROJECT/images`` (the photos under their
   own names: byte for byte, copied or symlinked with ``link=True``, but for the rotated ones, see
   below), ``PROJECT/database.db`` (COLMAP's features and matches, e.g. for COLMAP's GUI) and
   ``PROJECT/sfm.json`` (the summary).

**Orientation.** COLMAP and vadgs both read a photo's stored pixel grid and ignore its EXIF
orientation tag; a phone photo is often stored sideways with a tag (6 or 8) that a viewer applies.
So :func:`run_sfm` first writes each rotated photo *upright* into ``PROJECT/images``
(:func:`vadgs.data.images.upright_image`: the pixels transposed, the tag removed, the other EXIF
fields kept; JPEGs re-encoded at quality 95, other formats lossless), **under its original name**
(so the model's image names are the user's file names), and runs SfM on those copies. The cameras,
the up direction vadgs finds (:func:`vadgs.geometry.level_up`), videos and exports then agree with
what a viewer shows. ``sfm.json``'s ``exif_rotated`` maps each turned photo to its tag; the
originals are never changed (a rotated photo is a real file even with ``link=True``, and a run whose
``images/`` is ``PHOTOS`` itself is refused when a photo is rotated). :func:`run_sfm` checks that
every registered camera has its photo's upright size.

**Checks before the work** (one line each): ``PHOTOS`` must be a folder; ``--out`` must not be
``PHOTOS`` or inside it (its copies would be taken as photos by the next run); every photo is
decoded (:func:`vadgs.data.images.read_image`), so a truncated or corrupt one is named and the run
refused; photos with identical pixels are named and all but the first left out (identical photos
have no baseline: COLMAP cannot place them). One process writes a project at a time: the run holds
the project's lock (:class:`vadgs.runlock.RunLock`, ``PROJECT/.vadgs.lock``).

``vadgs train PROJECT`` keeps the undistorted copy of a distorted model in
``PROJECT/.vadgs-undistorted`` (:func:`vadgs.data.colmap_project.open_colmap_project`), so later
runs link to it instead of undistorting again; a new model (``overwrite``) removes it.

Nothing is written next to the photos; the work happens in a temporary folder inside ``PROJECT``
(``.vadgs-sfm-*``, with a marker file naming its process: the next run into the project removes
the folder of a killed one) and moves into place only when a model was made, so a failed run
leaves ``PROJECT`` as it was. An existing project is replaced only with ``overwrite=True``, and
only when ``vadgs sfm`` wrote it (its ``sfm.json`` says so, :func:`vadgs.runfolder.is_sfm_project`): a COLMAP
project made elsewhere is never written to, and in one of its own only what it wrote is
replaced (``sparse/0``, ``database.db``, ``sfm.json``, the photos it put into ``images/``, listed
in ``sfm.json``'s ``images_written``); the project's other files stay.

The photos (which files, their headers and camera groups): :mod:`vadgs.data.photos`; the
project's files (what a run may replace, how they move into place): :mod:`vadgs.data.sfm_project`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from vadgs.data.photos import (
    CAMERA_MODES,
    PhotoHeader,
    distinct_photos,
    find_photos,
    group_photos,
    left_out_line,
    read_photo_header,
    unsupported_photos,
)
from vadgs.data.sfm_project import (
    check_out_outside,
    check_sfm_project,
    move_into,
    place_photos,
    remove_path,
)
from vadgs.runfolder import SFM_FORMAT

if TYPE_CHECKING:  # imported where used: pycolmap is slow to import
    import pycolmap

__all__ = [
    "CAMERA_MODELS",
    "EXHAUSTIVE_MAX",
    "MATCHERS",
    "SEQUENTIAL_OVERLAP",
    "SfmResult",
    "run_sfm",
    "sequential_pairs",
]

#: ``matcher="auto"`` matches every pair up to this many photos, else sequentially.
EXHAUSTIVE_MAX = 100

#: ``matcher="sequential"``: each photo is matched with this many successors in name order.
SEQUENTIAL_OVERLAP = 10

#: The matchers (see the module docstring).
MATCHERS = ("auto", "exhaustive", "sequential")

#: The camera models COLMAP may fit that vadgs reads (``vadgs train`` undistorts the distorted ones).
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")


class SfmResult(NamedTuple):
    """What :func:`run_sfm` made.

    Attributes:
        project: the project folder (``vadgs train PROJECT`` reads it).
        model: its model folder, ``project/sparse/0``.
        images: its photos, ``project/images``.
        num_photos: photos found.
        registered: photos with a pose in the model.
        num_points: 3D points of the model.
        mean_reprojection_error: in pixels.
        num_cameras: cameras of the model.
        unregistered: the names of the photos left out.
        matcher: the matcher used (``"exhaustive"`` or ``"sequential"``).
        seconds: ``{"features", "matching", "mapping"}`` wall-clock times.
    """

    project: Path
    model: Path
    images: Path
    num_photos: int
    registered: int
    num_points: int
    mean_reprojection_error: float
    num_cameras: int
    unregistered: tuple[str, ...]
    matcher: str
    seconds: dict[str, float]

    def summary(self) -> str:
        """One line: registered/total photos, points, the mean reprojection error."""
        return (
            f"registered {self.registered} of {self.num_photos} photos, {self.num_points} points, "
            f"{self.num_cameras} camera(s), mean reprojection error {self.mean_reprojection_error:.3f} px"
        )


_WORK_PREFIX = ".vadgs-sfm-"
_WORK_MARKER = "vadgs-sfm-work.json"


def _remove_dead_work(project: Path, say: Callable[[str], None]) -> None:
    """Remove the work folders (``.vadgs-sfm-*``) of killed runs into ``project``.

    Only those it can prove are its own: their marker file names a process of this host that is
    no longer running. Called with the project's lock held (no live run of this host writes there).
    """
    import socket

    from vadgs.process import pid_alive

    for work in sorted(project.glob(_WORK_PREFIX + "*")):
        marker = work / _WORK_MARKER
        if work.is_symlink() or not work.is_dir() or not marker.is_file():
            continue
        try:
            owner = json.loads(marker.read_text())
            pid, host = int(owner["pid"]), owner["host"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if host != socket.gethostname() or pid_alive(pid):
            continue
        shutil.rmtree(work, ignore_errors=True)
        say(f"removed {work}: the work folder of a killed vadgs sfm (pid {pid}, not running)")


def sequential_pairs(names: Sequence[str], overlap: int) -> list[tuple[str, str]]:
    """The pairs matched in sequence: each photo with the ``overlap`` photos after it.

    Example:
        >>> sequential_pairs("abc", 1)
        [('a', 'b'), ('b', 'c')]
    """
    return [
        (a, names[j]) for i, a in enumerate(names) for j in range(i + 1, min(i + 1 + overlap, len(names)))
    ]


def run_sfm(
    photos: str | Path,
    out: str | Path,
    *,
    matcher: str = "auto",
    camera_mode: str = "auto",
    camera_model: str = "SIMPLE_RADIAL",
    max_image_size: int = 1600,
    link: bool = False,
    overwrite: bool = False,
    threads: int = 0,
    seed: int = 0,
    log: Callable[[str], None] | None = print,
    progress: bool = True,
) -> SfmResult:
    """Reconstruct the cameras of a folder of photos with pycolmap; write a COLMAP project.

    See the module docstring for the steps and what is written.

    Args:
        photos: the folder of photos (subfolders included; other files skipped).
        out: the project folder to write (created; an existing project needs ``overwrite``).
        matcher: ``"auto"``, ``"exhaustive"`` or ``"sequential"``.
        camera_mode: ``"auto"`` (one camera per size and EXIF camera), ``"single"``, ``"per-image"``.
        camera_model: the COLMAP model fitted: ``SIMPLE_RADIAL`` (default), ``RADIAL``, ``OPENCV``,
            ``SIMPLE_PINHOLE``, ``PINHOLE``.
        max_image_size: longest side (pixels) at which features are detected (the photos are not
            scaled); ``0``: the photos' own size.
        link: symlink the photos into ``out/images`` instead of copying them (but the rotated ones,
            written upright).
        overwrite: replace the ``images``, ``sparse``, ``database.db``, ``sfm.json`` of an
            existing project.
        threads: CPU threads of pycolmap (0: all).
        seed: pycolmap's random seed (RANSAC, mapping).
        log: where the step lines go (``print``-like; None: nowhere).
        progress: tqdm bars for the features, the matching and the registration.

    Returns:
        :class:`SfmResult`.

    Raises:
        FileNotFoundError: if ``photos`` does not exist.
        ValueError: ``photos`` a file, no or fewer than two (distinct) photos, an unreadable photo,
            a bad option, ``out`` equal to or inside ``photos``, an existing project without
            ``overwrite``, or no photo registered (one line each, naming it).
        vadgs.runlock.RunInUseError: another process is writing ``out``.
    """
    say = log or (lambda _s: None)
    photos, out = Path(photos), Path(out)
    if matcher not in MATCHERS:
        raise ValueError(f"matcher: expected one of {list(MATCHERS)}, got {matcher!r}")
    if camera_mode not in CAMERA_MODES:
        raise ValueError(f"camera_mode: expected one of {list(CAMERA_MODES)}, got {camera_mode!r}")
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model: expected one of {list(CAMERA_MODELS)}, got {camera_model!r}")
    if not isinstance(max_image_size, int) or max_image_size < 0:
        raise ValueError(f"max_image_size: expected >= 0 (0: the photos' size), got {max_image_size}")
    if int(threads) < 0:
        raise ValueError(f"threads: expected >= 0 (0: all cores), got {threads}")
    names = find_photos(photos)
    left = unsupported_photos(photos)
    if left:
        say(f"PHOTOS {photos}: {left_out_line(left)}")
    check_out_outside(photos, out)
    if len(names) < 2:
        raise ValueError(f"PHOTOS {photos}: expected at least 2 photos, got {len(names)} ({names[0]})")
    from vadgs.runlock import RunLock

    created = not out.exists()
    with RunLock(out, "vadgs sfm", log=log):
        return _run_sfm_locked(
            photos, out, names, created, matcher, camera_mode, camera_model, max_image_size, link,
            overwrite, threads, seed, say, progress,
        )  # fmt: skip


def _run_sfm_locked(
    photos, out, names, created, matcher, camera_mode, camera_model, max_image_size, link, overwrite,
    threads, seed, say, progress,
) -> SfmResult:  # fmt: skip
    import pycolmap
    from tqdm import tqdm

    from vadgs.data.colmap_project import colmap_logging

    replaced = check_sfm_project(out, photos, overwrite, names)
    _remove_dead_work(out, say)
    in_place = (out / "images").resolve() == photos.resolve()
    turned = {n: o for n in names if (o := read_photo_header(photos / n).orientation) != 1}
    if in_place and turned:
        first = next(iter(turned))
        raise ValueError(
            f"PHOTOS {photos}: {len(turned)} photo(s) carry an EXIF rotation (e.g. {first}: orientation "
            f"{turned[first]}) and PHOTOS is the project's images/, where vadgs sfm would write them "
            "upright over the originals; give --out another folder"
        )
    names, duplicates = distinct_photos(photos, names)
    for dup, first in duplicates.items():
        say(f"{dup} is identical to {first} (same pixels): left out")
    if len(names) < 2:
        dup = next(iter(duplicates))
        raise ValueError(
            f"PHOTOS {photos}: expected at least 2 distinct photos, got 1 ({names[0]}; {dup} is "
            "identical to it: same pixels, no baseline between them)"
        )
    turned = {n: o for n, o in turned.items() if n in names}
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= EXHAUSTIVE_MAX else "sequential"
    nthreads = int(threads) or -1

    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=_WORK_PREFIX, dir=out))
    try:
        import socket

        owner = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        (work / _WORK_MARKER).write_text(json.dumps(owner))  # a killed run's folder: removed next time
        # -- 0. the photos in place, the rotated ones upright: SfM runs on what the project holds
        if not in_place:
            place_photos(photos, names, work / "images", link)
        images_dir = photos if in_place else work / "images"
        headers = {name: read_photo_header(images_dir / name) for name in names}
        groups = group_photos(headers, camera_mode)
        if turned:
            first = next(iter(turned))
            say(
                f"turned {len(turned)} photo(s) upright by their EXIF orientation (e.g. {first}: "
                f"{turned[first]}) into {out / 'images'}, under their own names; the originals are unchanged"
            )
        db = work / "database.db"
        seconds = {}
        t0 = time.perf_counter()
        # -- 1. features, one camera per group (a new camera per call; chunks reuse the group's)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = nthreads
        extraction.max_image_size = int(max_image_size) or -1
        chunk = max(2, os.cpu_count() or 1) if nthreads < 0 else max(2, nthreads)
        size = f"longest side {max_image_size} px" if max_image_size else "full size"
        say(
            f"features: SIFT on {len(names)} photos ({size}), {len(groups)} camera(s) "
            f"({camera_mode}: {', '.join(headers[g[0]].label for g in groups[:4])}"
            f"{', ...' if len(groups) > 4 else ''})"
        )
        bar = tqdm(total=len(names), desc="features", unit="photo", disable=not progress)
        with colmap_logging(fatal_only=True), bar:
            for group in groups:
                camera_id = -1
                for i in range(0, len(group), chunk):
                    reader = pycolmap.ImageReaderOptions()
                    reader.camera_model = camera_model
                    reader.existing_camera_id = camera_id
                    pycolmap.extract_features(
                        db,
                        images_dir,
                        image_names=group[i : i + chunk],
                        camera_mode=pycolmap.CameraMode.SINGLE,
                        reader_options=reader,
                        extraction_options=extraction,
                        device=pycolmap.Device.cpu,
                    )
                    if camera_id < 0:
                        camera_id = _camera_of(db, group[0])
                    bar.update(len(group[i : i + chunk]))
        t1 = time.perf_counter()
        seconds["features"] = round(t1 - t0, 1)
        # -- 2. matching: the pairs in chunks (a progress bar) through pycolmap's imported pairs,
        # whose list file separates names by spaces: names with spaces go to pycolmap's own matchers
        if matcher == "exhaustive":
            pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
        else:
            pairs = sequential_pairs(names, SEQUENTIAL_OVERLAP)
        say(f"matching: {len(pairs)} pairs ({matcher})")
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = nthreads
        listable = not any(any(c.isspace() for c in name) for name in names)
        step = max(1, -(-len(pairs) // 20)) if listable else len(pairs)
        bar = tqdm(total=len(pairs), desc="matching", unit="pair", disable=not progress)
        with colmap_logging(fatal_only=True), bar:
            for i in range(0, len(pairs), step):
                if not listable and matcher == "exhaustive":
                    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
                elif not listable:
                    pairing = pycolmap.SequentialPairingOptions()
                    pairing.overlap, pairing.quadratic_overlap = SEQUENTIAL_OVERLAP, False
                    pycolmap.match_sequential(
                        db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
                    )
                else:
                    listing = work / "pairs.txt"
                    listing.write_text("".join(f"{a} {b}\n" for a, b in pairs[i : i + step]))
                    imported = pycolmap.ImportedPairingOptions()
                    imported.match_list_path = str(listing)
                    pycolmap.match_image_pairs(
                        db, matching_options=matching, pairing_options=imported, device=pycolmap.Device.cpu
                    )
                bar.update(len(pairs[i : i + step]))
        t2 = time.perf_counter()
        seconds["matching"] = round(t2 - t1, 1)
        # -- 3. incremental mapping
        say(f"mapping: incremental, {len(names)} photos")
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = nthreads
        options.random_seed = int(seed)
        (work / "models").mkdir()
        bar = tqdm(total=len(names), desc="registering", unit="photo", disable=not progress)
        with colmap_logging(fatal_only=True), bar:
            models = pycolmap.incremental_mapping(
                db, images_dir, work / "models", options, next_image_callback=lambda: bar.update(1)
            )
            bar.n = max((r.num_reg_images() for r in models.values()), default=0)  # + the initial pair
            bar.refresh()
        seconds["mapping"] = round(time.perf_counter() - t2, 1)
        if not models or max(r.num_reg_images() for r in models.values()) == 0:
            raise ValueError(
                f"PHOTOS {photos}: COLMAP registered none of the {len(names)} photos (too little "
                "overlap or texture between them?); photos from nearby viewpoints of a textured "
                "scene register best" + ("; try --matcher exhaustive" if matcher == "sequential" else "")
            )
        best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
        registered = {im.name for im in best.images.values() if im.has_pose}
        _check_sizes(best, photos, headers)
        if len(models) > 1:
            say(
                f"COLMAP made {len(models)} separate models; kept the largest "
                f"({len(registered)} photos), the others did not connect to it"
            )
        (work / "sparse" / "0").mkdir(parents=True)
        best.write(work / "sparse" / "0")
        result = SfmResult(
            project=out,
            model=out / "sparse" / "0",
            images=out / "images",
            num_photos=len(names),
            registered=len(registered),
            num_points=best.num_points3D(),
            mean_reprojection_error=float(best.compute_mean_reprojection_error()),
            num_cameras=len({best.images[i].camera_id for i in best.reg_image_ids()}),
            unregistered=tuple(n for n in names if n not in registered),
            matcher=matcher,
            seconds=seconds,
        )
        summary = {
            "format": SFM_FORMAT,
            "photos": str(photos.resolve()),
            **{k: v for k, v in result._asdict().items() if k not in ("project", "model", "images")},
            "camera_mode": camera_mode,
            "camera_model": camera_model,
            "max_image_size": int(max_image_size),
            "seed": int(seed),
            "exif_rotated": turned,
            "duplicates": duplicates,
            "images_written": [] if in_place else list(names),
        }
        summary["unregistered"] = list(result.unregistered)
        (work / "sfm.json").write_text(json.dumps(summary, indent=2) + "\n")
        # -- 4. the project: sfm.json first (a run killed from here on leaves a project of its own),
        # then what the old run wrote removed, the new files moved in; the project's other files stay
        os.replace(work / "sfm.json", out / "sfm.json")
        for entry in replaced.entries:
            remove_path(entry)
        for photo in replaced.images:
            photo.unlink(missing_ok=True)
        for folder in sorted({q for p in replaced.images for q in p.parents if out / "images" in q.parents},
                             key=lambda q: len(q.parts), reverse=True):  # fmt: skip
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty
        from vadgs.data.colmap_project import UNDISTORT_CACHE

        remove_path(out / UNDISTORT_CACHE)  # the undistorted copy of the model replaced, if any
        if (work / "database.db").exists():
            os.replace(work / "database.db", out / "database.db")
        for name in ("sparse", "images"):
            if (work / name).exists():
                move_into(work / name, out / name)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    shutil.rmtree(work, ignore_errors=True)
    return result


def _camera_of(db: Path, name: str) -> int:
    """The camera id the database gave photo ``name``."""
    import pycolmap

    database = pycolmap.Database.open(str(db))
    try:
        image = database.read_image_with_name(name)
        if image is None:
            raise ValueError(f"{db}: expected photo {name!r} in the database, found none")
        return int(image.camera_id)
    finally:
        database.close()


def _check_sizes(rec: pycolmap.Reconstruction, photos: Path, headers: dict[str, PhotoHeader]) -> None:
    """Every registered camera has its photo's stored size (what vadgs reads), else a ValueError."""
    for im in rec.images.values():
        if not im.has_pose:
            continue
        cam = rec.cameras[im.camera_id]
        if (cam.width, cam.height) != headers[im.name].size:
            w, h = headers[im.name].size
            raise ValueError(
                f"PHOTOS: {photos / im.name}: COLMAP's camera is {cam.width}x{cam.height}, the photo "
                f"vadgs reads {w}x{h}"
            )
