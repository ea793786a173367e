"""``vadgs export --inria`` of a normalised COLMAP run: every camera and a source model in the PLY's frame."""

from __future__ import annotations

import ast
import json
import re

import numpy as np
import pytest

from vadgs.cli import main
from vadgs.data import load_colmap

from ..data.colmap_sample import write_sample_colmap

pycolmap = pytest.importorskip("pycolmap")


def test_inria_export_of_a_colmap_run_is_in_one_frame(tmp_path, capsys):
    root, run, out = tmp_path / "proj", tmp_path / "run", tmp_path / "inria"
    write_sample_colmap(root, n_points=400)
    fast = ["--scale", "0.25", "--no-progress", "--init.sh-degree", "0", "--init.max-points", "400"]
    assert main(["--threads", "1", "train", str(root), "--out", str(run), "--iterations", "2", *fast]) == 0
    ref = json.loads((run / "config.json").read_text())["scene"]
    assert ref["transform"] is not None  # normalised: the PLY is not in COLMAP's frame
    assert main(["export", str(run), "--out", str(out), "--inria"]) == 0
    cams = json.loads((out / "cameras.json").read_text())
    args = (out / "cfg_args").read_text()
    fields = dict(re.findall(r"(\w+)=('[^']*')", args))
    source, images = ast.literal_eval(fields["source_path"]), ast.literal_eval(fields["images"])
    assert source == str(out.resolve()) and images == ref["images"]
    # the source model, read as 3DGS reads it, has every camera where cameras.json puts it
    scene, _ = load_colmap(f"{source}/sparse/0", images)
    assert len(cams) == scene.num_views == 24
    for cam, view in zip(cams, scene.views):  # one image per frame: frame 0's first, then in order
        assert cam["img_name"] == view.image.stem  # 3DGS's image_name (the file name, no extension)
        c2w = view.cam_to_world.double().numpy()
        np.testing.assert_allclose(cam["position"], c2w[:3, 3], atol=1e-4)
        np.testing.assert_allclose(cam["rotation"], c2w[:3, :3], atol=1e-5)
    # and differs from the COLMAP-frame model the run was trained from
    original, _ = load_colmap(ref["path"], images)
    moved = [float(np.linalg.norm(a.cam_to_world[:3, 3] - b.cam_to_world[:3, 3]))
             for a, b in zip(original.views, scene.views)]  # fmt: skip
    assert max(moved) > 1e-2
