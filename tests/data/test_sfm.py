"""``vadgs sfm`` (:func:`vadgs.data.sfm.run_sfm`): photos → a COLMAP project, against the true cameras."""

from __future__ import annotations

import filecmp
import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from vadgs.cli import main
from vadgs.data import open_colmap_project
from vadgs.data.colmap_model import colmap_world_to_cam
from vadgs.data.photos import find_photos, photo_groups
from vadgs.data.sfm import run_sfm, sequential_pairs
from vadgs.train.scenes import scene_ref

from .photo_sample import SIDEWAYS, photo_cameras, write_photo_set

pycolmap = pytest.importorskip("pycolmap")

SCEAUX = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "sceaux_castle" / "images"


LAYOUT = ["database.db", "images", "sfm.json", "sparse"]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The 10-photo room (three sizes, one stored sideways) reconstructed once (about 10 s of CPU)."""
    root = tmp_path_factory.mktemp("sfm")
    truth = write_photo_set(root / "photos")
    upright = photo_cameras()  # the sideways photo is turned upright into the project: its upright camera
    for key in ("cam_to_world", "K", "sizes"):
        truth[key][SIDEWAYS] = upright[key][SIDEWAYS]
    (root / "photos" / "notes.txt").write_text("not a photo")  # skipped
    res = run_sfm(root / "photos", root / "proj", threads=1, log=None, progress=False)
    return root, truth, res


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``s, R, t`` with ``dst ≈ s R src + t`` (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.eye(3)
    e[2, 2] = np.sign(np.linalg.det(u @ vt))
    R = u @ e @ vt
    s = float((d * np.diag(e)).sum() / (a**2).sum(1).mean())
    return s, R, md - s * R @ ms


class TestRunSfm:
    def test_every_photo_registers_with_its_true_camera(self, made):
        _, truth, res = made
        assert (res.num_photos, res.registered, res.unregistered) == (10, 10, ())
        assert res.matcher == "exhaustive" and res.num_cameras == 2  # one per size (photo 5 upright)
        assert res.mean_reprojection_error < 0.5
        rec = pycolmap.Reconstruction(str(res.model))
        images = {im.name: im for im in rec.images.values()}
        # intrinsics: every camera has its photo's stored size and its true focal length (within 1 %)
        for i, name in enumerate(truth["names"]):
            cam = rec.cameras[images[name].camera_id]
            h, w = truth["sizes"][i]
            assert (cam.height, cam.width) == (h, w), name
            assert cam.focal_length == pytest.approx(truth["K"][i][0, 0], rel=0.01), name
        # poses: the camera centres match the truth up to a similarity within 0.5 % of the arc's radius
        c2w = [np.linalg.inv(colmap_world_to_cam(images[n])) for n in truth["names"]]
        centres = np.stack([m[:3, 3] for m in c2w])
        s, R, t = _similarity(centres, truth["cam_to_world"][:, :3, 3])
        err = np.linalg.norm(s * centres @ R.T + t - truth["cam_to_world"][:, :3, 3], axis=1)
        assert err.max() < 0.015, err
        # orientations, the sideways photo's included: rotation error below 0.5 degree
        for i, m in enumerate(c2w):
            rel = truth["cam_to_world"][i, :3, :3].T @ R @ m[:3, :3]
            angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
            assert angle < 0.5, (truth["names"][i], angle)

    def test_project_layout_and_photos_unchanged(self, made):
        root, truth, res = made
        assert sorted(p.name for p in res.project.iterdir() if not p.name.startswith(".")) == [
            "database.db",
            "images",
            "sfm.json",
            "sparse",
        ]
        assert sorted(p.name for p in res.images.iterdir()) == truth["names"]  # notes.txt left out
        for name in truth["names"]:
            if name != "photo_05.jpg":
                assert filecmp.cmp(root / "photos" / name, res.images / name, shallow=False)
        # the sideways photo: upright under its own name, its tag gone, the pixels within JPEG error
        assert Image.open(root / "photos" / "photo_05.jpg").getexif()[0x0112] == 6  # the original kept
        turned = Image.open(res.images / "photo_05.jpg")
        assert turned.format == "JPEG" and 0x0112 not in turned.getexif()
        stored = np.asarray(Image.open(root / "photos" / "photo_05.jpg"), dtype=np.float64)
        assert np.abs(np.asarray(turned, dtype=np.float64) - np.rot90(stored, -1)).mean() < 2.0
        summary = json.loads((res.project / "sfm.json").read_text())
        assert summary["registered"] == 10 and summary["exif_rotated"] == {"photo_05.jpg": 6}
        assert summary["duplicates"] == {}
        assert not list((root / "photos").glob("*.db"))  # nothing written next to the photos

    def test_vadgs_reads_the_project(self, made):
        root, truth, res = made
        assert scene_ref(res.project).kind == "colmap"
        colmap, recipe = open_colmap_project(res.project, undistort_dir=root / "undistorted")
        scene = colmap.scene
        assert scene.num_views == 10 and scene.name == "proj"
        assert sorted(v.image.name for v in scene.views) == truth["names"]
        assert len(recipe["undistorted"]) == 2  # SIMPLE_RADIAL: undistorted for training

    def test_undistorted_once_per_project(self, made, tmp_path, monkeypatch):
        """The second run of a project links to the undistorted copy the first one left in it."""
        import os

        _, truth, res = made
        first, _ = open_colmap_project(res.project, undistort_dir=tmp_path / "a")
        cache = res.project / ".vadgs-undistorted"
        (entry,) = list(cache.iterdir())

        def again(*_a, **_k):
            raise AssertionError("undistorted again")

        monkeypatch.setattr(pycolmap, "undistort_images", again)
        second, recipe = open_colmap_project(res.project, undistort_dir=tmp_path / "b")
        assert recipe["images"] == str((tmp_path / "b" / "images").resolve())  # the run's own copy
        for name in truth["names"]:
            assert os.path.samefile(tmp_path / "b" / "images" / name, entry / "images" / name)
        for v1, v2 in zip(first.scene.views, second.scene.views):
            assert torch.equal(v1.cam_to_world, v2.cam_to_world)
        assert torch.equal(first.scene.load_images([3]), second.scene.load_images([3]))
        monkeypatch.undo()
        # a photo changed: undistorted again, the old copy replaced by the new one
        photo = res.images / truth["names"][0]
        st = photo.stat()
        os.utime(photo, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        try:
            open_colmap_project(res.project, undistort_dir=tmp_path / "c")
            assert [p.name for p in cache.iterdir()] not in ([], [entry.name])
            assert len(list(cache.iterdir())) == 1
        finally:
            os.utime(photo, ns=(st.st_atime_ns, st.st_mtime_ns))

    def test_overwrite(self, made, tmp_path, capsys):
        root, truth, res = made

        def sfm(photos, out, *flags):
            return main(["--threads", "1", "sfm", str(photos), "--out", str(out), "--no-progress", *flags])

        before = (res.model / "points3D.bin").read_bytes()
        argv = ["--threads", "1", "sfm", str(root / "photos"), "--out", str(res.project), "--no-progress"]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "already holds images, sparse, database.db, sfm.json; --overwrite replaces them" in err
        assert err.count("\n") == 1
        # a failing --overwrite (nothing registers) leaves the old project as it was
        noise = tmp_path / "noise"
        noise.mkdir()
        rng = np.random.default_rng(0)
        for i in range(3):
            Image.fromarray(rng.integers(0, 255, (90, 120, 3), dtype=np.uint8)).save(noise / f"n{i}.png")
        assert (
            main(
                [
                    "--threads",
                    "1",
                    "sfm",
                    str(noise),
                    "--out",
                    str(res.project),
                    "--overwrite",
                    "--no-progress",
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert "COLMAP registered none of the 3 photos" in err and err.count("\n") == 1
        assert (res.model / "points3D.bin").read_bytes() == before
        assert sorted(p.name for p in res.project.iterdir() if not p.name.startswith(".")) == [
            "database.db",
            "images",
            "sfm.json",
            "sparse",
        ]
        # a new project from nothing that registers: no folder left behind
        assert sfm(noise, tmp_path / "new") == 2
        assert not (tmp_path / "new").exists()
        capsys.readouterr()
        # a successful --overwrite with four photos, in place (PHOTOS is the project's images/), linked;
        # a name with a space goes to pycolmap's own matchers (the pair list separates by spaces)
        proj = tmp_path / "small"
        (proj / "images").mkdir(parents=True)
        names = ["photo 00.png", *truth["names"][1:4]]
        for name, src in zip(names, truth["names"]):
            (proj / "images" / name).write_bytes((root / "photos" / src).read_bytes())
        assert sfm(proj / "images", proj) == 0
        out = capsys.readouterr().out
        # the larger photo 3, its own camera, does not connect to the three others: left out, said so
        assert "registered 3 of 4 photos" in out and "mean reprojection error" in out
        assert "not registered: photo_03.png" in out
        assert sfm(proj / "images", proj) == 2
        assert "--overwrite" in capsys.readouterr().err
        t0 = time.process_time()  # CPU seconds (threads included), not wall-clock under load
        assert sfm(proj / "images", proj, "--overwrite") == 0
        assert time.process_time() - t0 < 120
        assert sorted(p.name for p in (proj / "images").iterdir()) == names  # never removed
        link = tmp_path / "linked"
        assert sfm(proj / "images", link, "--link", "--matcher", "sequential") == 0
        out = capsys.readouterr().out
        assert "matching: 6 pairs (sequential)" in out and "registered 3 of 4 photos" in out
        assert (link / "images" / names[0]).resolve() == (proj / "images" / names[0]).resolve()


class TestBadInput:
    def test_messages(self, tmp_path, capsys):
        (tmp_path / "empty").mkdir()
        (tmp_path / "empty" / "K.txt").write_text("1 0 0")
        (tmp_path / "one").mkdir()
        Image.new("RGB", (40, 30)).save(tmp_path / "one" / "a.jpg")
        cases = [
            ([str(tmp_path / "nope")], "PHOTOS " + str(tmp_path / "nope") + ": no such folder"),
            (
                [str(tmp_path / "empty")],
                "expected photos (.jpg, .jpeg, .png, .tif, .tiff, .bmp), got none (1 other file(s))",
            ),
            ([str(tmp_path / "one")], "expected at least 2 photos, got 1 (a.jpg)"),
            ([str(tmp_path / "one"), "--matcher", "vocab"], "--matcher"),
            (
                [str(tmp_path / "one"), "--max-image-size", "-1"],
                "--max-image-size: expected an integer >= 0, got -1",
            ),
        ]
        for argv, message in cases:
            assert main(["sfm", *argv, "--out", str(tmp_path / "p")]) == 2, argv
            err = capsys.readouterr().err
            assert message in err and err.count("\n") == 1, (argv, err)
            assert not (tmp_path / "p").exists()
        # a project inside the photos folder, or the photos folder itself: refused (F12b, F13)
        (tmp_path / "one" / "proj" / "images").mkdir(parents=True)
        for name in ("b.jpg", "c.jpg"):
            Image.new("RGB", (40, 30)).save(tmp_path / "one" / "proj" / "images" / name)
        argv = ["sfm", str(tmp_path / "one"), "--out", str(tmp_path / "one" / "proj"), "--overwrite"]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "is inside PHOTOS" in err and "give a folder outside PHOTOS" in err and err.count("\n") == 1
        assert main(["sfm", str(tmp_path / "one"), "--out", str(tmp_path / "one")]) == 2
        err = capsys.readouterr().err
        assert "is PHOTOS itself" in err and err.count("\n") == 1
        # PHOTOS a file (F21)
        assert main(["sfm", str(tmp_path / "one" / "a.jpg"), "--out", str(tmp_path / "p")]) == 2
        err = capsys.readouterr().err
        assert "expected a folder of photos, got a file" in err and err.count("\n") == 1
        assert not (tmp_path / "p").exists()
        with pytest.raises(ValueError, match="camera_mode: expected one of"):
            run_sfm(tmp_path / "one", tmp_path / "p", camera_mode="exif")

    def test_corrupt_duplicate_locked(self, tmp_path, capsys):
        """F5b: a truncated JPEG is named and the run refused; F3: identical photos are said to be
        identical; two runs into one project: the second is refused by the project's lock."""
        rng = np.random.default_rng(0)
        photos = tmp_path / "photos"
        photos.mkdir()
        for name in ("a.jpg", "b.jpg", "c.jpg"):
            Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)).save(photos / name, quality=95)
        data = (photos / "b.jpg").read_bytes()
        (photos / "b.jpg").write_bytes(data[: len(data) // 2])

        def sfm(out):
            return main(["--threads", "1", "sfm", str(photos), "--out", str(out), "--no-progress"])

        assert sfm(tmp_path / "p") == 2
        err = capsys.readouterr().err
        assert f"{photos / 'b.jpg'}: not a decodable image" in err and "remove or replace" in err
        assert err.count("\n") == 1 and not (tmp_path / "p").exists()
        # b.jpg an exact copy of a.jpg (and c.jpg gone): two photos, one distinct
        (photos / "b.jpg").write_bytes((photos / "a.jpg").read_bytes())
        (photos / "c.jpg").unlink()
        assert sfm(tmp_path / "p") == 2
        out, err = capsys.readouterr()
        assert "b.jpg is identical to a.jpg (same pixels): left out" in out
        assert "expected at least 2 distinct photos, got 1 (a.jpg; b.jpg is identical to it" in err
        assert not (tmp_path / "p").exists()
        # a project another process is writing
        from vadgs.runlock import RunLock

        with RunLock(tmp_path / "busy", "vadgs sfm"):
            assert sfm(tmp_path / "busy") != 0
        err = capsys.readouterr().err
        assert "in use by vadgs sfm" in err and err.count("\n") == 1
        assert not (tmp_path / "busy").exists()

    def test_groups(self, tmp_path):
        for name, size in (("b.png", (40, 30)), ("a.png", (40, 30)), ("sub/c.jpg", (30, 40))):
            (tmp_path / name).parent.mkdir(exist_ok=True)
            Image.new("RGB", size).save(tmp_path / name)
        (tmp_path / ".hidden.png").write_bytes(b"")
        assert sequential_pairs("abcd", 2) == [("a", "b"), ("a", "c"), ("b", "c"), ("b", "d"), ("c", "d")]
        names = find_photos(tmp_path)
        assert names == ["a.png", "b.png", "sub/c.jpg"]
        assert photo_groups(tmp_path, names) == [["a.png", "b.png"], ["sub/c.jpg"]]
        assert photo_groups(tmp_path, names, "per-image") == [["a.png"], ["b.png"], ["sub/c.jpg"]]
        with pytest.raises(ValueError, match="camera_mode: 'single' needs photos of one size, got 2 sizes"):
            photo_groups(tmp_path, names, "single")


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.skipif(not SCEAUX.is_dir(), reason="needs ../shared/data/real/sceaux_castle")
def test_sceaux_castle(tmp_path):
    """The 11 castle photos (2832x2128) at features of 800 px: all register, focal within 4 % of K.txt."""
    res = run_sfm(SCEAUX, tmp_path / "castle", max_image_size=800, threads=1, log=None, progress=False)
    assert res.num_photos == 11 and res.registered == 11 and res.mean_reprojection_error < 1.0
    focal = float(SCEAUX.joinpath("K.txt").read_text().split()[0])
    rec = pycolmap.Reconstruction(str(res.model))
    assert [c.focal_length for c in rec.cameras.values()] == [pytest.approx(focal, rel=0.04)]


@pytest.mark.shared
@pytest.mark.skipif(not SCEAUX.is_dir(), reason="needs ../shared/data/real/sceaux_castle")
def test_phone_photos_stored_sideways(tmp_path):
    """Real photos stored as a phone stores them: pixels turned 90° with EXIF orientation 6 (a viewer
    shows them upright), four of six, as in the trial (19 of 23). ``vadgs sfm`` writes them upright
    into the project, and the up direction it recovers is the one of the same photos stored upright.

    Six castle photos at 1/4 size (708x532), about 5 s of CPU per run.
    """
    import torch

    from vadgs.geometry import level_up

    names = sorted(p.name for p in SCEAUX.glob("*.JPG"))[:6]
    (tmp_path / "upright").mkdir()
    (tmp_path / "phone").mkdir()
    for i, name in enumerate(names):
        with Image.open(SCEAUX / name) as im:
            small = im.reduce(4)
        small.save(tmp_path / "upright" / name, quality=95)
        if i in (0, 5):  # two stored upright
            small.save(tmp_path / "phone" / name, quality=95)
            continue
        exif = Image.Exif()
        exif[0x0112] = 6  # "rotate 90° clockwise to show": the stored grid is the upright one turned back
        stored = np.ascontiguousarray(np.rot90(np.asarray(small)))
        Image.fromarray(stored).save(tmp_path / "phone" / name, quality=95, exif=exif)

    def up_in_cameras(photos, out):
        res = run_sfm(photos, out, max_image_size=0, threads=1, log=None, progress=False)
        assert res.registered == 6, res.summary()
        rec = pycolmap.Reconstruction(str(res.model))
        ims = sorted(rec.images.values(), key=lambda im: im.name)
        c2w = torch.tensor(np.stack([np.linalg.inv(colmap_world_to_cam(im)) for im in ims]))
        up = level_up(c2w)
        # the up in each camera's own axes: free of the reconstructions' arbitrary world frames
        return res, {im.name: (c2w[i, :3, :3].T @ up).numpy() for i, im in enumerate(ims)}

    _, want = up_in_cameras(tmp_path / "upright", tmp_path / "p_upright")
    res, got = up_in_cameras(tmp_path / "phone", tmp_path / "p_phone")
    summary = json.loads((res.project / "sfm.json").read_text())
    assert summary["exif_rotated"] == {name: 6 for name in names[1:5]}
    for name in names:
        # the project's image is upright: the upright photo within JPEG error, no orientation tag
        with Image.open(res.images / name) as im:
            assert im.size == (708, 532) and im.getexif().get(0x0112, 1) == 1, name
            image = np.asarray(im, dtype=np.float64)
        with Image.open(tmp_path / "upright" / name) as im:
            assert np.abs(image - np.asarray(im, dtype=np.float64)).mean() < 3.0, name
        # the up agrees with the upright run's (within 1°), and points up in the photo (-y, level)
        angle = np.degrees(np.arccos(np.clip(want[name] @ got[name], -1.0, 1.0)))
        assert angle < 1.0, (name, angle)
        assert got[name][1] < -0.95, (name, got[name])
