"""The one image decoder (:mod:`vadgs.data.images`): each mode against hand-computed values, and
through the scene loader, a COLMAP project (PINHOLE: no undistortion) and ``vadgs check --full``.

The trial's fault: a 16-bit PNG was read as all white (the 8-bit conversion clipped every value
above 255) while ``check --full`` said it decoded.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vadgs.cli import main
from vadgs.data import load_colmap, load_scene, validate_scene
from vadgs.data.images import SUPPORTED_MODES, decode_image, exif_orientation, read_image, upright_image

from .sample_copy import copy_sample_scene

RNG = np.random.default_rng(0)
U16 = RNG.integers(0, 65536, (6, 5), dtype=np.uint16)  # grey, 16 bits
U8 = RNG.integers(0, 256, (6, 5, 3), dtype=np.uint8)  # RGB, 8 bits


def _png16_rgb(path: Path, rgb: np.ndarray) -> None:
    """A 48-bit RGB PNG written by hand (PIL cannot write one): IHDR bit depth 16, colour type 2."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    h, w, _ = rgb.shape
    rows = b"".join(b"\x00" + rgb[r].astype(">u2").tobytes() for r in range(h))
    ihdr = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def _grey(a: np.ndarray) -> np.ndarray:
    return np.repeat(a[..., None], 3, axis=-1)


class TestModes:
    """Every mode read to float32 RGB in [0, 1], each against its conversion computed by hand."""

    def test_16bit_grey_png_and_tiff(self, tmp_path):
        want = _grey(U16 / 65535.0)
        Image.fromarray(U16).save(tmp_path / "a.png")  # I;16
        assert Image.open(tmp_path / "a.png").mode == "I;16"
        got = read_image(tmp_path / "a.png")
        assert got.dtype == np.float32 and got.shape == (6, 5, 3)
        np.testing.assert_allclose(got, want, atol=1e-7)
        assert got.max() < 1.0 or U16.max() == 65535  # not all white (the trial's fault)
        Image.frombytes("I;16B", (5, 6), U16.astype(">u2").tobytes()).save(tmp_path / "b.tif")
        assert Image.open(tmp_path / "b.tif").mode == "I;16B"
        np.testing.assert_allclose(read_image(tmp_path / "b.tif"), want, atol=1e-7)

    def test_dark_16bit_is_not_white(self, tmp_path):
        # every value above 255 became 255 in the 8-bit conversion: white; here 1000/65535 ≈ 0.015
        Image.fromarray(np.full((4, 4), 1000, np.uint16)).save(tmp_path / "dark.png")
        np.testing.assert_allclose(read_image(tmp_path / "dark.png"), 1000 / 65535, atol=1e-7)

    def test_48bit_rgb_png_high_byte(self, tmp_path):
        rgb = RNG.integers(0, 65536, (6, 5, 3), dtype=np.uint16)
        _png16_rgb(tmp_path / "c.png", rgb)
        got = read_image(tmp_path / "c.png")
        # PIL decodes 16 bits per sample to their high byte: 8-bit precision, never clipped
        np.testing.assert_allclose(got, (rgb >> 8) / 255.0, atol=1e-7)
        assert np.abs(got - rgb / 65535.0).max() < 1 / 255

    def test_8bit_L_RGB_and_1(self, tmp_path):
        Image.fromarray(U8).save(tmp_path / "rgb.png")
        np.testing.assert_allclose(read_image(tmp_path / "rgb.png"), U8 / 255.0, atol=1e-7)
        Image.fromarray(U8[..., 0]).save(tmp_path / "l.png")
        np.testing.assert_allclose(read_image(tmp_path / "l.png"), _grey(U8[..., 0] / 255.0), atol=1e-7)
        bits = U8[..., 0] > 127
        Image.fromarray(bits).save(tmp_path / "one.png")
        assert Image.open(tmp_path / "one.png").mode == "1"
        np.testing.assert_array_equal(read_image(tmp_path / "one.png"), _grey(bits.astype(np.float32)))

    def test_palette_with_transparency(self, tmp_path):
        im = Image.new("P", (3, 1))
        im.putpalette([255, 0, 0, 0, 128, 0, 10, 20, 30] + [0] * (256 * 3 - 9))
        im.putdata([0, 1, 2])
        im.info["transparency"] = 1
        im.save(tmp_path / "p.png", transparency=1)
        assert Image.open(tmp_path / "p.png").mode == "P"
        want = np.array([[[255, 0, 0], [0, 128, 0], [10, 20, 30]]]) / 255.0  # the transparent one: its colour
        np.testing.assert_allclose(read_image(tmp_path / "p.png"), want, atol=1e-7)

    def test_alpha_dropped(self, tmp_path):
        alpha = RNG.integers(0, 256, (6, 5), dtype=np.uint8)
        Image.fromarray(np.dstack([U8, alpha])).save(tmp_path / "rgba.png")
        np.testing.assert_allclose(read_image(tmp_path / "rgba.png"), U8 / 255.0, atol=1e-7)
        Image.fromarray(np.dstack([U8[..., 1], alpha]), mode="LA").save(tmp_path / "la.png")
        assert Image.open(tmp_path / "la.png").mode == "LA"
        np.testing.assert_allclose(read_image(tmp_path / "la.png"), _grey(U8[..., 1] / 255.0), atol=1e-7)

    def test_cmyk(self, tmp_path):
        # K = 0: R = 255 - C, G = 255 - M, B = 255 - Y
        Image.new("CMYK", (4, 3), (55, 100, 0, 0)).save(tmp_path / "c.tif")
        np.testing.assert_allclose(
            read_image(tmp_path / "c.tif"), np.array([200, 155, 255]) / 255.0 + np.zeros((3, 4, 3)), atol=1e-7
        )
        Image.new("CMYK", (16, 16), (55, 100, 0, 0)).save(tmp_path / "c.jpg", quality=95)
        assert Image.open(tmp_path / "c.jpg").mode == "CMYK"
        np.testing.assert_allclose(
            read_image(tmp_path / "c.jpg"),
            np.array([200, 155, 255]) / 255.0 + np.zeros((16, 16, 3)),
            atol=3 / 255,
        )

    def test_I_and_F(self, tmp_path):
        Image.fromarray(U16.astype(np.int32), mode="I").save(tmp_path / "i.tif")
        assert Image.open(tmp_path / "i.tif").mode == "I"
        np.testing.assert_allclose(read_image(tmp_path / "i.tif"), _grey(U16 / 65535.0), atol=1e-7)
        Image.fromarray(np.array([[70000, 0]], np.int32), mode="I").save(tmp_path / "big.tif")
        with pytest.raises(
            ValueError, match=r"big\.tif: mode I .*values in \[0, 70000\]; expected \[0, 65535\]"
        ):
            read_image(tmp_path / "big.tif")
        f = np.array([[0.0, 0.25, 1.0]], np.float32)
        Image.fromarray(f, mode="F").save(tmp_path / "f.tif")
        np.testing.assert_array_equal(read_image(tmp_path / "f.tif"), _grey(f))
        Image.fromarray(f * 2, mode="F").save(tmp_path / "f2.tif")
        with pytest.raises(ValueError, match=r"f2\.tif: mode F .*expected finite values in \[0, 1\]"):
            read_image(tmp_path / "f2.tif")

    def test_exif_rotated_read_as_stored(self, tmp_path):
        exif = Image.Exif()
        exif[0x0112] = 6
        y, x = np.mgrid[0:24, 0:40]
        smooth = np.stack([x * 6, y * 10, (x + y) * 4], -1).astype(np.uint8)  # JPEG-friendly
        Image.fromarray(smooth).save(tmp_path / "r.jpg", exif=exif, quality=95)
        assert exif_orientation(tmp_path / "r.jpg") == 6
        assert read_image(tmp_path / "r.jpg").shape == (24, 40, 3)  # the stored grid, as COLMAP reads it
        # upright_image: the pixels turned (90° clockwise for 6), the tag gone, the name's format kept
        assert upright_image(tmp_path / "r.jpg", tmp_path / "u.jpg") == 6
        assert exif_orientation(tmp_path / "u.jpg") == 1 and Image.open(tmp_path / "u.jpg").format == "JPEG"
        stored = read_image(tmp_path / "r.jpg")
        assert read_image(tmp_path / "u.jpg").shape == (40, 24, 3)
        assert np.abs(read_image(tmp_path / "u.jpg") - np.rot90(stored, -1)).mean() < 2 / 255
        # a phone's MPO (a JPEG with a second picture): written as a JPEG of its first picture
        second = Image.fromarray(smooth[::-1].copy())
        Image.fromarray(smooth).save(
            tmp_path / "m.jpg", "MPO", save_all=True, append_images=[second], exif=exif
        )
        assert Image.open(tmp_path / "m.jpg").format == "MPO"
        assert upright_image(tmp_path / "m.jpg", tmp_path / "n.jpg") == 6
        assert Image.open(tmp_path / "n.jpg").format == "JPEG" and exif_orientation(tmp_path / "n.jpg") == 1
        assert np.abs(read_image(tmp_path / "n.jpg") - np.rot90(smooth / 255.0, -1)).mean() < 2 / 255
        Image.fromarray(U8).save(tmp_path / "p.png", exif=exif)
        assert upright_image(tmp_path / "p.png", tmp_path / "q.png") == 6  # lossless
        np.testing.assert_array_equal(
            read_image(tmp_path / "q.png"), np.rot90(U8 / 255.0, -1).astype(np.float32)
        )
        assert (
            upright_image(tmp_path / "q.png", tmp_path / "z.png") == 1 and not (tmp_path / "z.png").exists()
        )

    def test_refused_naming_the_file(self, tmp_path):
        Image.fromarray(U8).save(tmp_path / "t.png")
        data = (tmp_path / "t.png").read_bytes()
        (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match=r"t\.png: not a decodable image"):
            read_image(tmp_path / "t.png")
        (tmp_path / "e.png").write_bytes(b"")
        with pytest.raises(ValueError, match=r"e\.png: not a decodable image \(an empty file \(0 bytes\)\)"):
            read_image(tmp_path / "e.png")
        with pytest.raises(FileNotFoundError, match="missing file"):
            read_image(tmp_path / "none.png")
        with pytest.raises(ValueError, match=r"waymo x: not a decodable image"):
            decode_image(data[:100], "waymo x")
        im = Image.new("RGB", (2, 2))
        im._mode = "I;16S"  # a mode PIL opens but vadgs does not read
        from vadgs.data.images import as_rgb

        with pytest.raises(
            ValueError, match=r"x\.png: image mode 'I;16S' is not read; expected one of 1, L, P"
        ):
            as_rgb(im, "x.png")
        assert "I;16" in SUPPORTED_MODES and "CMYK" in SUPPORTED_MODES


def _pinhole_project(tmp_path):
    """The tests' COLMAP sample as a PINHOLE project with its own copy of the images (to change)."""
    pytest.importorskip("pycolmap")
    import shutil

    from .colmap_sample import write_sample_colmap

    root = tmp_path / "proj"
    made = write_sample_colmap(root, model="PINHOLE")
    target = (root / "images").resolve()
    (root / "images").unlink()
    shutil.copytree(target, root / "images")
    return root, made


class TestThroughLoaders:
    def test_scene_loader_and_check_full(self, tmp_path, capsys):
        root = copy_sample_scene(tmp_path)
        p = root / "images/front/019.png"
        rgb8 = np.asarray(Image.open(p).convert("RGB"))
        # the same image as a 16-bit grey PNG: the loader reads it / 65535, check --full passes
        grey16 = (rgb8[..., 1].astype(np.uint16) * 257).astype(np.uint16)
        Image.fromarray(grey16).save(p)
        scene = load_scene(root)
        img = scene.load_images([scene.view_id(19, "front")])[0]
        np.testing.assert_allclose(img.permute(1, 2, 0).numpy(), _grey(rgb8[..., 1] / 255.0), atol=1e-6)
        assert validate_scene(root, full=True).ok
        assert main(["check", str(root), "--full"]) == 0
        capsys.readouterr()
        # a 32-bit integer image beyond 16 bits (a TIFF under the .png name): check --full names it
        Image.fromarray(np.full(grey16.shape, 70000, np.int32), mode="I").save(p, format="TIFF")
        assert validate_scene(root).ok  # headers: a mode read, the right size
        report = validate_scene(root, full=True)
        assert [r.file for r in report.errors] == [str(p)]
        assert "mode I (32-bit integer) with values in [70000, 70000]" in report.errors[0].message
        assert main(["check", str(root), "--full"]) == 1
        assert "019.png" in capsys.readouterr().out
        with pytest.raises(ValueError, match=r"019\.png: mode I"):
            load_scene(root).load_images([scene.view_id(19, "front")])

    def test_colmap_pinhole_project(self, tmp_path):
        root, made = _pinhole_project(tmp_path)
        name = made["names"][0]
        rgb8 = np.asarray(Image.open(root / "images" / name).convert("RGB"))
        _png16_rgb(root / "images" / name, rgb8.astype(np.uint16) * 257)  # 48-bit, same colours
        Image.fromarray(rgb8[..., 2].astype(np.uint16) * 257).save(root / "images" / made["names"][1])
        scene = load_colmap(root / "sparse" / "0").scene
        by_name = {v.image.relative_to(root / "images").as_posix(): v.index for v in scene.views}
        imgs = scene.load_images([by_name[made["names"][0]], by_name[made["names"][1]]])
        np.testing.assert_allclose(imgs[0].permute(1, 2, 0).numpy(), rgb8 / 255.0, atol=1e-6)
        np.testing.assert_allclose(imgs[1].permute(1, 2, 0).numpy(), _grey(rgb8[..., 2] / 255.0), atol=1e-6)

    def test_colmap_project_with_rotated_images_warns(self, tmp_path):
        root, made = _pinhole_project(tmp_path)
        exif = Image.Exif()
        exif[0x0112] = 6
        for name in made["names"][:2]:  # tagged, pixels as stored: as COLMAP made elsewhere sees them
            with Image.open(root / "images" / name) as im:
                im.load()
            im.save(root / "images" / name, exif=exif)
        with pytest.warns(
            UserWarning,
            match=r"2 of 24 image\(s\) carry an EXIF orientation tag that COLMAP ignores.*rerun `vadgs sfm`",
        ):
            load_colmap(root / "sparse" / "0")
