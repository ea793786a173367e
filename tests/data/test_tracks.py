"""vadgs.data._tracks: the helpers the DGP, nuScenes and Waymo readers share."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vadgs.data._tracks import (
    BoxObservation,
    check_min_motion,
    held_out_frames,
    labelled_lidar,
    quat_wxyz_to_matrix,
    recentred,
    select_cameras,
    select_positions,
)


def _naive_quat_to_matrix(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


class TestQuatWxyzToMatrix:
    def test_feature(self):
        rng = np.random.default_rng(0)
        for q in rng.normal(size=(50, 4)) * 3:
            np.testing.assert_allclose(quat_wxyz_to_matrix(q), _naive_quat_to_matrix(q), rtol=0, atol=1e-14)
            np.testing.assert_allclose(quat_wxyz_to_matrix(q), quat_wxyz_to_matrix(-q), rtol=0, atol=1e-15)

    @pytest.mark.parametrize("q", [[0, 0, 0, 0], [1, 0, 0], [float("nan"), 0, 0, 1], "abcd"])
    def test_exception(self, q):
        with pytest.raises(ValueError, match="quaternion"):
            quat_wxyz_to_matrix(q)


class TestSelection:
    def test_cameras(self):
        assert select_cameras(None, ("A", "B"), "none") == ["A", "B"]
        assert select_cameras(["B"], ("A", "B"), "none") == ["B"]
        with pytest.raises(ValueError, match=r"^cameras: unknown camera 'C', have \['A', 'B'\]$"):
            select_cameras(["C"], ("A", "B"), "none")
        with pytest.raises(ValueError, match=r"^scene x: no camera$"):
            select_cameras(None, (), "scene x: no camera")

    def test_positions(self):
        assert select_positions(None, 4) == [0, 1, 2, 3]
        assert select_positions([3, 1], 4) == [3, 1]
        with pytest.raises(ValueError, match=r"frames: expected keyframe positions in \[0, 4\), got \[4\]"):
            select_positions([4], 4, "keyframe")
        with pytest.raises(ValueError, match=r"got \[\]"):
            select_positions([], 4)

    def test_held_out_frames(self):
        assert (
            held_out_frames(None, 7) == [2, 6]
            and held_out_frames((), 7) == []
            and held_out_frames([5, 0], 7) == [0, 5]
        )
        with pytest.raises(ValueError, match=r"test_frames: unknown frame\(s\) \[7\], have 0\.\.6"):
            held_out_frames([7], 7)

    def test_min_motion(self):
        check_min_motion(None)
        check_min_motion(0.0)
        with pytest.raises(ValueError, match="min_motion_m"):
            check_min_motion(-1)


def test_recentred_copies_and_broadcasts():
    m = np.stack([np.eye(4)] * 2)
    out = recentred(m, np.array([1.0, 2.0, 3.0]))
    assert out[:, :3, 3].tolist() == [[-1.0, -2.0, -3.0]] * 2 and m[:, :3, 3].tolist() == [[0.0] * 3] * 2


def test_labelled_lidar():
    box = np.eye(4)
    box[:3, 3] = [10.0, 0.0, 0.0]
    boxes = {7: {0: BoxObservation(box, np.array([4.0, 2.0, 2.0]), "car")}}
    world = np.array([[10.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    lf = labelled_lidar(world, np.array([1.0, 2.0, 3.0]), boxes, 0)
    assert lf.points.dtype == torch.float32 and lf.instance.tolist() == [7, 0]
    assert lf.origin.tolist() == [1.0, 2.0, 3.0]
    assert labelled_lidar(world, np.zeros(3), boxes, 1).instance.tolist() == [0, 0]  # no box at frame 1
