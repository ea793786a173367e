"""gsplat v1.5.3's own ``examples/simple_trainer.py`` with ``examples/gsplat_simple_trainer.diff``,
run for real on the CPU: ``default`` and ``vad`` on the COLMAP sample (24 images at half
resolution, 120×72, every 8th held out: 21 training views per cycle).

The script is gsplat's file, copied from ``../shared/third_party/gsplat-v1.5.3/examples`` and
patched with the shipped diff; the GPU-only parts get the stand-ins of
:mod:`tests.train.gsplat_simple_trainer` (gsplat's pure-torch rasterization path, pycolmap 4.x
under the forked ``SceneManager``, ...). ``--vad.every-cycles 1`` puts a VAD-GS event after each
pass over the training views (steps 20 and 41 of 50); everything else is the diff's ``vad``
entry as a user runs it. Skipped only when ``../shared`` is absent.
"""

from __future__ import annotations

import json
import math

import pytest

from vadgs.train.vad import VisibilityInputs, build_visibility_index

from ..data.colmap_sample import write_sample_colmap
from .gsplat_parser import sample_parser
from .gsplat_simple_trainer import GSPLAT_EXAMPLES, prepare_data, prepare_examples, run_trainer

pytestmark = [
    pytest.mark.shared,
    pytest.mark.skipif(not GSPLAT_EXAMPLES.is_dir(), reason="needs ../shared/third_party/gsplat-v1.5.3"),
]
for _mod in ("gsplat", "torchmetrics", "sklearn", "tensorboard", "kornia"):
    pytest.importorskip(_mod)

STEPS, FACTOR, CYCLE = 50, 2, 21


def _argv(name: str, root, out) -> list[str]:
    return [
        name, "--data_dir", str(root), "--data_factor", str(FACTOR), "--result_dir", str(out),
        "--max_steps", str(STEPS), "--eval_steps", str(STEPS), "--save_steps", str(STEPS),
        "--disable_viewer", "--disable_video",
    ]  # fmt: skip


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("simple_trainer")
    root = tmp / "colmap"
    write_sample_colmap(root, n_points=1500)
    prepare_data(root, FACTOR)
    examples = prepare_examples(tmp)
    out = {
        "metric_voxels": len(
            build_visibility_index(VisibilityInputs.from_gsplat_parser(sample_parser(root, 2))).grid
        )
    }
    for name, extra in (("default", []), ("vad", ["--vad.every-cycles", "1"])):
        res = tmp / f"results_{name}"
        out[name] = run_trainer(examples, _argv(name, root, res) + extra, tmp / f"{name}.json")
        out[name]["val"] = json.loads((res / "stats" / f"val_step{STEPS - 1:04d}.json").read_text())
    return out


def test_default_trains_through_the_harness(runs):
    rec = runs["default"]
    assert [s for s, *_ in rec["steps"]] == list(range(STEPS))
    assert rec["events"] == []
    assert rec["val"]["num_GS"] == rec["steps"][-1][1] == 1500  # SfM init, no ADC before step 500
    assert math.isfinite(rec["val"]["psnr"]) and rec["val"]["psnr"] > 10


def test_vad_events_flag_add_and_keep_every_row(runs):
    rec = runs["vad"]
    # VAD-GS's lengths follow gsplat's normalised world (median view depth 0.8, not 11.3 m): as
    # many voxels as in the sample's own metres
    assert rec["config"]["lengths"]["scene_depth"] == pytest.approx(0.80, abs=0.01)
    assert abs(rec["config"]["voxels"] - runs["metric_voxels"]) <= 0.02 * runs["metric_voxels"]
    assert [s for s, *_ in rec["steps"]] == list(range(STEPS))
    events = rec["events"]
    assert [e["step"] for e in events] == [CYCLE - 1, 2 * CYCLE - 1]
    n_before = {s: n for s, n, *_ in rec["steps"]}
    for e in events:
        assert e["flagged_instances"] >= 1 and e["attempted"] >= 1
        assert e["added"] > 0 and e["repaired"] >= 1, e
        assert e["n_after"] == n_before[e["step"]]  # what the loop sees after the event
        rows = e["rows"]
        assert set(rows["moments"]) == {f"{k}.{m}" for k in rows["params"] for m in ("exp_avg", "exp_avg_sq")}
        assert set(rows["params"].values()) | set(rows["moments"].values()) == {e["n_after"]}
        assert {"grad2d", "count"} <= set(rows["state"]) and set(rows["state"].values()) == {e["n_after"]}
    for e in events:  # the diff passes the step's render: the event tests the trained views on it
        assert e["tests_reused"] >= 0.8 * CYCLE and e["views_rendered"] <= 0.2 * CYCLE, e
    # it trains on: the steps after the events run, with the Gaussians the events added
    first = rec["steps"][0][1]
    assert rec["steps"][-1][1] == first + sum(e["added"] for e in events) == rec["val"]["num_GS"]
    assert math.isfinite(rec["val"]["psnr"]) and rec["val"]["psnr"] > 10


def test_text_scene_manager_reads_what_pycolmap_reads(tmp_path):
    """:class:`TextSceneManager` (no pycolmap) against the pycolmap-based stand-in, on one model."""
    import numpy as np

    from .gsplat_simple_trainer import SceneManager, TextSceneManager

    write_sample_colmap(tmp_path, n_points=1500, text=True)  # what a machine without pycolmap is given
    sparse = tmp_path / "sparse" / "0"
    assert {"cameras.txt", "images.txt", "points3D.txt"} <= {f.name for f in sparse.iterdir()}
    assert not list(sparse.glob("*.bin"))
    a, b = SceneManager(str(sparse)), TextSceneManager(str(sparse))
    for m in (a, b):
        m.load_cameras(), m.load_images(), m.load_points3D()
    assert a.cameras.keys() == b.cameras.keys()
    for cid in a.cameras:
        assert vars(a.cameras[cid]) == pytest.approx(vars(b.cameras[cid]), rel=1e-12), cid
    assert a.name_to_image_id == b.name_to_image_id and len(a.images) == 24
    for iid, ia in a.images.items():
        ib = b.images[iid]
        assert (ia.camera_id, ia.name) == (ib.camera_id, ib.name)
        np.testing.assert_allclose(ib.R(), ia.R(), atol=1e-12)
        np.testing.assert_allclose(ib.tvec, ia.tvec, atol=1e-12)
    np.testing.assert_array_equal(b.points3D, a.points3D)
    np.testing.assert_array_equal(b.point3D_colors, a.point3D_colors)
    np.testing.assert_allclose(b.point3D_errors, a.point3D_errors)
    assert b.point3D_id_to_point3D_idx == a.point3D_id_to_point3D_idx
    assert a.point3D_id_to_images.keys() == b.point3D_id_to_images.keys()
    for pid, track in a.point3D_id_to_images.items():
        np.testing.assert_array_equal(b.point3D_id_to_images[pid], track.reshape(-1, 2))  # (0,) when empty
