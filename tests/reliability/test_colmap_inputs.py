"""Issue 33, COLMAP inputs: every fault that pycolmap aborted on (exit 134), passed through as raw
``Check failed`` text, or trained on silently is found before pycolmap's C++ code sees it, with one
line naming the file; a failed undistortion leaves no ``RUN/undistorted`` behind."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from tests.data.colmap_sample import write_sample_colmap
from vadgs.data.colmap import load_colmap
from vadgs.data.colmap_files import check_image_name, diagnose_model_files
from vadgs.data.colmap_project import open_colmap_project


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A distorted (SIMPLE_RADIAL) project whose images are copies, as binary and as text."""
    import pycolmap

    root = tmp_path_factory.mktemp("colmap") / "proj"
    write_sample_colmap(root, model="SIMPLE_RADIAL", k=0.05, n_points=120, crop={"front": (144, 240)})
    text = root.parent / "text"
    text.mkdir()
    pycolmap.Reconstruction(str(root / "sparse" / "0")).write_text(str(text))
    return root, text


def _variant(base, tmp_path, text: bool = False) -> Path:
    root, text_model = base
    out = tmp_path / "p"
    shutil.copytree(root / "images", out / "images")
    shutil.copytree(text_model if text else root / "sparse" / "0", out / "sparse" / "0")
    return out


def _edit(project: Path, name: str, fn) -> None:
    path = project / "sparse" / "0" / name
    path.write_text(fn(path.read_text()))


def _open(project: Path, run: Path):
    return open_colmap_project(project, undistort_dir=run / "undistorted")


def _fault(base, tmp_path, kind):
    """The faulty project of ``kind`` and the message (regex) expected."""
    p = _variant(base, tmp_path, text=kind in ("dotdot", "absolute", "duplicate", "zero_quat", "nan_pose"))
    img = p / "images" / "front" / "016.png"
    if kind == "wrong_size":
        Image.new("RGB", (200, 100)).save(img)
        return (
            p,
            rf"{re.escape(str(img))}: expected size 240x144 \(W x H\), got 200x100 \(camera 1, SIMPLE_RADIAL",
        )
    if kind == "truncated_image":
        img.write_bytes(img.read_bytes()[:2000])
        return p, rf"{re.escape(str(img))}: not a decodable image \(OSError: image file is truncated"
    if kind == "empty_image":
        img.write_bytes(b"")
        return p, rf"{re.escape(str(img))}: not a decodable image \(an empty file \(0 bytes\)\)"
    if kind == "dotdot":
        _edit(p, "images.txt", lambda t: t.replace(" 1 front/016.png", " 1 ../../victim.png"))
        return (
            p,
            r"image 1 name: expected a relative image path inside the images folder, got '../../victim.png'",
        )
    if kind == "absolute":
        _edit(p, "images.txt", lambda t: t.replace(" 1 front/016.png", " 1 /tmp/victim.png"))
        return p, r"image 1 name: expected a relative image path .* got '/tmp/victim.png'"
    if kind == "duplicate":
        _edit(p, "images.txt", lambda t: t.replace(" 2 front_left/016.png", " 2 front/016.png"))
        return p, r"images 1 and 2: expected unique names, both are 'front/016.png'"
    if kind == "zero_quat":
        _edit(p, "frames.txt", lambda t: re.sub(r"^1 1 \S+ \S+ \S+ \S+ ", "1 1 0 0 0 0 ", t, flags=re.M))
        return (
            p,
            r"image 1 'front/016.png': cam_from_world: expected a unit quaternion, got \[0.0, 0.0, 0.0, 0.0",
        )
    if kind == "nan_pose":
        _edit(
            p, "frames.txt", lambda t: re.sub(r"^1 1 (\S+ \S+ \S+ \S+) \S+ ", r"1 1 \1 nan ", t, flags=re.M)
        )
        return p, r"frames.txt: field 7 is not finite"
    if kind in ("truncated_points3D", "truncated_images", "truncated_cameras"):
        f = p / "sparse" / "0" / (kind.split("_")[1] + ".bin")
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
        return p, rf"cannot read the COLMAP model: {re.escape(str(f))}: truncated"
    raise AssertionError(kind)


KINDS = [
    "wrong_size",
    "truncated_image",
    "empty_image",
    "dotdot",
    "absolute",
    "duplicate",
    "zero_quat",
    "nan_pose",
    "truncated_points3D",
    "truncated_images",
    "truncated_cameras",
]


@pytest.mark.parametrize("kind", KINDS)
def test_fault_is_one_line_naming_the_file_and_nothing_is_left(base, tmp_path, kind):
    project, message = _fault(base, tmp_path, kind)
    before = {p: p.stat().st_mtime_ns for p in project.rglob("*")}
    run = tmp_path / "run"
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        _open(project, run)
    assert not (run / "undistorted").exists()  # nothing half-written in the run folder
    assert {p: p.stat().st_mtime_ns for p in project.rglob("*")} == before  # the dataset untouched
    assert not (tmp_path / "victim.png").exists()


def test_truncated_points3D_names_the_record(base, tmp_path):
    project, _ = _fault(base, tmp_path, "truncated_points3D")
    found = diagnose_model_files(project / "sparse" / "0")
    assert re.fullmatch(
        r".*points3D.bin: truncated: the header announces 120 records, the file ends in record \d+", found
    )
    assert diagnose_model_files(base[0] / "sparse" / "0") is None and diagnose_model_files(base[1]) is None


def test_pinhole_model_with_a_dotdot_name_is_refused_at_load(base, tmp_path):
    project = _variant(base, tmp_path, text=True)
    _edit(
        project,
        "cameras.txt",
        lambda t: re.sub(r"SIMPLE_RADIAL (\d+) (\d+) (\S+) (\S+) (\S+) \S+", r"PINHOLE \1 \2 \3 \3 \4 \5", t),
    )
    _edit(project, "images.txt", lambda t: t.replace(" 1 front/016.png", " 1 ../front/016.png"))
    with pytest.raises(ValueError, match="image 1 name: expected a relative image path"):
        load_colmap(project / "sparse" / "0")


def test_wrong_size_under_a_distorted_camera_is_no_native_abort(base, tmp_path):
    """The trial's case 5: exit 134 with a C++ stack; now exit 2 and one line, in a fresh process."""
    project, _ = _fault(base, tmp_path, "wrong_size")
    code = (
        "import sys; from vadgs.cli import main; "
        f"sys.exit(main(['train', {str(project)!r}, '--out', {str(tmp_path / 'run')!r}, '--iterations', '1', "
        "'--no-progress', '--threads', '1']))"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "expected size 240x144 (W x H), got 200x100" in lines[0], res.stderr
    assert not (tmp_path / "run" / "undistorted").exists()


@pytest.mark.parametrize("name", ["a.png", "front/016.png", "x/y/z.jpg"])
def test_image_names_accepted(name):
    assert check_image_name(name, "image") == name


@pytest.mark.parametrize("name", ["", "../a.png", "a/../../b.png", "/etc/passwd", "C:\\x.png", "a\\..\\b"])
def test_image_names_refused(name):
    with pytest.raises(ValueError, match="image: expected a relative image path"):
        check_image_name(name, "image")


def test_interrupted_undistortion_leaves_nothing_and_a_stale_partial_is_cleared(base, tmp_path, monkeypatch):
    import pycolmap

    project = _variant(base, tmp_path)
    run = tmp_path / "run"
    real = pycolmap.undistort_images

    def killed(out, *args, **kwargs):  # some images written, then Ctrl+C
        (Path(out) / "images").mkdir(parents=True)
        (Path(out) / "images" / "half.png").write_bytes(b"x")
        raise KeyboardInterrupt

    monkeypatch.setattr(pycolmap, "undistort_images", killed)
    with pytest.raises(KeyboardInterrupt):
        _open(project, run)
    assert sorted(p.name for p in run.iterdir()) == []
    (run / ".undistorted.partial" / "images").mkdir(parents=True)  # what a kill -9 leaves
    monkeypatch.setattr(pycolmap, "undistort_images", real)
    colmap, _ = _open(project, run)
    assert sorted(p.name for p in run.iterdir()) == ["undistorted"] and colmap.scene.num_views == 24


@pytest.mark.parametrize("binary", [False, True])
def test_a_track_observing_a_missing_image_names_the_point(base, tmp_path, binary):
    """pycolmap said only "Image with ID 9999 does not exist"."""
    import pycolmap

    project = _variant(base, tmp_path, text=True)
    _edit(
        project,
        "points3D.txt",
        lambda t: re.sub(r"^(\d+ (?:\S+ ){7})\d+ ", r"\g<1>9999 ", t, count=1, flags=re.M),
    )
    model = project / "sparse" / "0"
    first = next(ln for ln in (model / "points3D.txt").read_text().splitlines() if not ln.startswith("#"))
    if binary:  # the same model as .bin files, written without pycolmap's checks
        out = tmp_path / "bin"
        out.mkdir()
        rec_ok = pycolmap.Reconstruction(str(base[0] / "sparse" / "0"))
        rec_ok.write_binary(str(out))
        data = bytearray((out / "points3D.bin").read_bytes())
        data[8 + 51 : 8 + 55] = (9999).to_bytes(4, "little")  # the first track element's image id
        (out / "points3D.bin").write_bytes(bytes(data))
        model = out
        pid = int.from_bytes(data[8:16], "little")
    else:
        pid = int(first.split()[0])
    with pytest.raises(
        ValueError,
        match=rf"points3D.(txt|bin): point {pid} observes image 9999, which images.(txt|bin) does not have",
    ):
        load_colmap(model)
