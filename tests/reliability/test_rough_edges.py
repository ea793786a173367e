"""Rough edges of issue 49: each a one-line answer instead of silence, a raw warning or a deep failure."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vadgs.cli import main
from vadgs.data.images import exif_orientation, upright_image
from vadgs.data.photos import find_photos, read_photo_header, unsupported_photos


def _photo(path: Path, seed: int, exif: Image.Exif | None = None) -> None:
    rng = np.random.default_rng(seed)
    img = Image.fromarray(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8))
    img.save(path, quality=95, **({"exif": exif} if exif is not None else {}))


class TestPhotos:
    def test_unsupported_formats_named_in_one_line(self, tmp_path, capsys):
        pytest.importorskip("pycolmap")
        photos = tmp_path / "photos"
        (photos / "sub").mkdir(parents=True)
        _photo(photos / "a.jpg", 0)
        (photos / "b.jpg").write_bytes((photos / "a.jpg").read_bytes())  # one distinct photo: stops early
        Image.new("RGB", (40, 30)).save(photos / "c.webp")
        (photos / "sub" / "d.HEIC").write_bytes(b"\0" * 10)
        (photos / "notes.txt").write_text("not a photo")
        assert find_photos(photos) == ["a.jpg", "b.jpg"]
        assert unsupported_photos(photos) == ["c.webp", "sub/d.HEIC"]
        assert main(["sfm", str(photos), "--out", str(tmp_path / "p"), "--no-progress"]) == 2
        out = capsys.readouterr().out
        line = [ln for ln in out.splitlines() if "formats vadgs sfm does not take" in ln]
        assert line == [
            f"PHOTOS {photos}: left out 2 photo(s) in formats vadgs sfm does not take (.heic, .webp): "
            "c.webp, sub/d.HEIC; convert them to JPEG or PNG to use them"
        ]
        only = tmp_path / "only"
        only.mkdir()
        Image.new("RGB", (40, 30)).save(only / "x.webp")
        with pytest.raises(
            ValueError, match=r"got none \(1 other file\(s\)\); left out 1 photo\(s\) .*\(\.webp\): x\.webp"
        ):
            find_photos(only)

    @pytest.mark.parametrize("tag", [0, 9, 200])
    def test_out_of_range_orientation_is_upright_and_said(self, tmp_path, tag):
        exif = Image.Exif()
        exif[0x0112] = tag
        path = tmp_path / "a.jpg"
        _photo(path, 1, exif)
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            header = read_photo_header(path)  # what vadgs sfm reads: not "turned"
            assert header.orientation == 1 and header.size == (40, 30)
            assert exif_orientation(path) == 1  # what loading a COLMAP project reads
            assert upright_image(path, tmp_path / "b.jpg") == 1  # what vadgs sfm copies: as stored
        assert not (tmp_path / "b.jpg").exists()
        msgs = {str(x.message) for x in w}
        assert msgs == {
            f"{path}: EXIF orientation {tag} is not one of 1-8: taken as 1 (upright, the pixels as stored)"
        }
        exif[0x0112] = 6  # a real rotation still turns
        _photo(path, 1, exif)
        assert read_photo_header(path).orientation == 6 and upright_image(path, tmp_path / "b.jpg") == 6
        assert Image.open(tmp_path / "b.jpg").size == (30, 40)

    def test_corrupt_exif_warning_names_the_photo(self, tmp_path):
        exif = Image.Exif()
        exif[0x010F] = "Canon"
        path = tmp_path / "a.jpg"
        _photo(path, 2, exif)
        data = bytearray(path.read_bytes())
        at = data.find(b"Exif\0\0")
        data[at + 14 : at + 34] = bytes(range(200, 220))  # the IFD entries, inside the 38-byte block
        path.write_bytes(bytes(data))
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            header = read_photo_header(path)
        assert header.size == (40, 30) and header.orientation == 1
        assert w, "PIL warns about the damaged EXIF block"
        for x in w:
            assert str(x.message).startswith(f"{path}: "), str(x.message)
        assert any("Corrupt EXIF data" in str(x.message) for x in w)
        from vadgs.data.images import read_image

        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            assert read_image(path).shape == (30, 40, 3)  # what sfm decodes for its duplicate check
        assert w and all(str(x.message).startswith(f"{path}: ") for x in w)


class TestStrategyAttributes:
    def test_unknown_attribute_refused(self):
        from vadgs.train.strategy import DefaultStrategy
        from vadgs.train.vad import VisibilityAwareDensification

        s = VisibilityAwareDensification()
        with pytest.raises(
            AttributeError, match=r"VisibilityAwareDensification: no setting or attribute 'typo_setting'"
        ):
            s.typo_setting = 3
        with pytest.raises(AttributeError, match=r"'every_cycle'; did you mean 'every_cycles'\?"):
            s.every_cycle = 3
        assert (
            not hasattr(s, "typo_setting") and s.every_cycles == VisibilityAwareDensification().every_cycles
        )
        s.every_cycles = 7  # a setting: checked, into the config
        s.on_progress = print  # its own attributes
        s.index = None
        assert s.config.every_cycles == 7 and s.on_progress is print
        d = DefaultStrategy()
        with pytest.raises(AttributeError, match=r"'refine_evrey'; did you mean 'refine_every'\?"):
            d.refine_evrey = 50

    def test_subclass_init_adds_attributes(self):
        from vadgs.train.strategy import DefaultStrategy

        class Traced(DefaultStrategy):
            def __init__(self, *args, **kwargs):
                super().__init__(*args, **kwargs)
                self.trace, self.model = [], None

        t = Traced(refine_every=50)
        t.model = "set later"  # an attribute its __init__ made
        assert t.refine_every == 50 and t.trace == [] and t.model == "set later"
        with pytest.raises(AttributeError, match="no setting or attribute 'tracee'"):
            t.tracee = []


class TestTrainConfigFields:
    @pytest.mark.parametrize(
        ("changes", "message"),
        [
            ({"iterations": 2.5}, "iterations: expected an integer >= 1, got 2.5"),
            ({"iterations": True}, "iterations: expected an integer >= 1, got True"),
            ({"seed": -1}, r"seed: expected an integer in \[0, 9223372036854775807\], got -1"),
            (
                {"seed": 2**64},
                r"seed: expected an integer in \[0, "
                r"9223372036854775807\], got 18446744073709551616",
            ),
            ({"cache_gb": "2"}, r"cache_gb: expected a finite number > 0 \(GB\), got str '2'"),
            (
                {"max_minutes": None},
                r"max_minutes: expected a finite number >= 0 \(0 = "
                r"no limit\), got NoneType None",
            ),
            ({"vad": {}}, r"vad: expected None or a VisibilityDensifyConfig, got dict \{\}"),
            ({"strategy": None}, "strategy: expected a DefaultStrategyConfig, got NoneType None"),
            ({"device": 0}, "device: expected a torch device such as 'cpu' or 'cuda', got 0"),
        ],
    )
    def test_refused_at_construction(self, changes, message):
        from vadgs.train.config import TrainConfig

        with pytest.raises(ValueError, match=f"^{message}"):
            TrainConfig(**changes)

    def test_accepted(self):
        from vadgs.train.config import TrainConfig
        from vadgs.train.vad import VisibilityDensifyConfig

        c = TrainConfig(iterations=np.int64(10), seed=2**63 - 1, cache_gb=1, vad=VisibilityDensifyConfig())
        assert c.iterations == 10 and c.cache_gb == 1 and TrainConfig.from_dict(c.to_dict()) == c


class TestSegmentConfigFields:
    @pytest.mark.parametrize(
        ("changes", "message"),
        [
            (
                {"width": 200_000, "height": 200_000},
                r"width: expected an integer in \[1, 65536\], got 200000",
            ),
            (
                {"width": 10_000, "height": 10_000},
                r"width, height: 10000x10000 is 100000000 pixels per image",
            ),
            ({"width": 10_000, "side_height": 9_000}, r"width, side_height: 10000x9000 is 90000000 pixels"),
            ({"lidar_points": 10**9}, r"lidar_points: expected an integer in \[1, 4000000\], got 1000000000"),
            ({"jpeg_quality": 0}, r"jpeg_quality: expected an integer in \[1, 100\], got 0"),
            ({"jpeg_quality": 101}, r"jpeg_quality: expected an integer in \[1, 100\], got 101"),
            (
                {"lidar_vfov": (5.0, -5.0)},
                r"lidar_vfov: expected \(min, max\) degrees with min < max, got \(5.0, -5.0\)",
            ),
            (
                {"lidar_vfov": (-95.0, 5.0)},
                r"lidar_vfov: expected \(min, max\) degrees with -90 <= min < max <= 90",
            ),
            ({"lidar_vfov": 5.0}, r"lidar_vfov: expected \(min, max\) degrees"),
            ({"seed": -1}, r"seed: expected an integer in \[0, 9223372036854775807\], got -1"),
            ({"seed": 1.5}, r"seed: expected an integer"),
            ({"moving_cars": 10**6}, r"moving_cars: expected an integer in \[0, 1000\]"),
            ({"lidar_beams": 10**6}, r"lidar_beams: expected an integer in \[1, 4096\]"),
        ],
    )
    def test_refused(self, changes, message):
        from vadgs.data import SegmentConfig

        with pytest.raises(ValueError, match=f"^{message}"):
            SegmentConfig(**changes)

    def test_accepted(self):
        from vadgs.data import SegmentConfig

        c = SegmentConfig(width=1920, height=1280, side_height=886, lidar_vfov=[-30, 10], jpeg_quality=100)
        assert c.lidar_vfov == (-30.0, 10.0) and c.image_size("side_left") == (886, 1920)


class TestInterruptedVideo:
    def test_sigterm_exits_130_and_leaves_no_temporary_file(self, tmp_path):
        """``render --video`` stopped by SIGTERM (a job scheduler's stop): exit 130, as Ctrl+C, and
        the temporary video removed (was exit 143 and a ``.v.*.tmp.mp4`` left beside the output)."""
        pytest.importorskip("imageio_ffmpeg")
        import os
        import signal
        import subprocess
        import sys
        import time

        run = tmp_path / "run"
        tiny = ["--scale", "0.25", "--no-progress", "--init.max-points", "300", "--init.voxel-size", "1.0"]
        assert (
            main(["--threads", "1", "train", "--sample", "--out", str(run), "--iterations", "1", *tiny]) == 0
        )
        out = tmp_path / "videos"
        out.mkdir()
        argv = ["render", str(run), "--video", str(out / "v.mp4"), "--trajectory", "orbit:20000"]
        argv += ["--max-frames", "20000", "--no-progress"]
        root = Path(__file__).resolve().parents[2]
        env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
        proc = subprocess.Popen(
            [sys.executable, "-m", "vadgs.cli", "--threads", "1", *argv],
            env=env,
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        deadline = time.monotonic() + 240
        while not list(out.iterdir()) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)  # until the temporary video exists: frames are being written
        assert proc.poll() is None, proc.communicate()
        assert [p.name.endswith(".tmp.mp4") for p in out.iterdir()] == [True]
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 130, err
        assert err.strip().splitlines()[-1] == "vadgs render: interrupted"
        assert list(out.iterdir()) == []
