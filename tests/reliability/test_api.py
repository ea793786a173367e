"""Issue 33, the Python API: bad values give one ValueError naming the argument (value checks obey
``vadgs.checking(False)``), and the combinatorial / allocation-heavy entry points are bounded."""

from __future__ import annotations

import math
import time

import pytest
import torch

from tests.mvs.mvs_scenes import plane_scene
from vadgs.checks import checking
from vadgs.geometry import normals_to_quats
from vadgs.geometry.camera import backproject_depth, invert_rigid, project_points
from vadgs.geometry.points import voxel_downsample
from vadgs.geometry.rotation import quaternion_to_rotation
from vadgs.geometry.voxel import voxelize
from vadgs.mvs import PatchMatchConfig, patchmatch
from vadgs.mvs.planar import fit_plane_ransac
from vadgs.select import ViewSelectionConfig, max_weight_clique, top_k_views
from vadgs.select.clique import MAX_CLIQUES

K_OK = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]]])
NAN = float("nan")


def _pm(dtype_of_image):
    sc = plane_scene()
    args = [sc.image.to(dtype_of_image), sc.src_images, sc.K, sc.src_K, sc.world_to_cam, sc.src_world_to_cam]
    return patchmatch(*args, (1.0, 10.0), PatchMatchConfig(iterations=1))


CASES = [
    (
        "invert_rigid(zeros)",
        lambda: invert_rigid(torch.zeros(4, 4)),
        r"transform: expected a transform with last row \(0, 0, 0, 1\)",
    ),
    (
        "invert_rigid(nan)",
        lambda: invert_rigid(torch.full((2, 4, 4), NAN)),
        "transform: expected finite values",
    ),
    (
        "project_points(K=0)",
        lambda: project_points(torch.ones(1, 2, 3), torch.zeros(1, 3, 3)),
        "K: expected positive focal lengths .* got fx=0, fy=0",
    ),
    (
        "project_points(K=nan)",
        lambda: project_points(torch.ones(1, 2, 3), K_OK * NAN),
        "K: expected finite values",
    ),
    (
        "project_points(pose)",
        lambda: project_points(torch.ones(1, 2, 3), K_OK, torch.zeros(1, 4, 4)),
        "world_to_cam: expected a transform with last row",
    ),
    (
        "backproject_depth(K=0)",
        lambda: backproject_depth(torch.ones(1, 1, 2, 2), torch.zeros(1, 3, 3)),
        "K: expected positive focal lengths",
    ),
    (
        "quaternion_to_rotation(0)",
        lambda: quaternion_to_rotation(torch.zeros(3, 4)),
        r"quats: expected non-zero quaternions, got 3 of norm 0 \(first: row 0\)",
    ),
    (
        "patchmatch(float64 image)",
        lambda: _pm(torch.float64),
        "expected one floating dtype for the images, cameras and initial values, got .*'image': torch.fl",
    ),
    (
        "max_weight_clique(nan)",
        lambda: max_weight_clique(torch.tensor([1.0, NAN]), torch.zeros(2, 2), 1),
        "node_weight: expected finite values, got 1 non-finite of 2",
    ),
    (
        "max_weight_clique(nan edge)",
        lambda: max_weight_clique(torch.ones(2), torch.full((2, 2), NAN), 1),
        "edge_weight: expected finite values",
    ),
    (
        "top_k_views(nan)",
        lambda: top_k_views(torch.tensor([1.0, NAN, 2.0]), 0, 2),
        "scores: expected finite values, got 1 non-finite of 3",
    ),
    (
        "top_k_views(k=-1)",
        lambda: top_k_views(torch.rand(3), 0, -1),
        "k: expected a number of views >= 0, got -1",
    ),
    (
        "fit_plane_ransac(threshold=-1)",
        lambda: fit_plane_ransac(torch.rand(10, 3), -1),
        "threshold: expected positive inlier distances, got min -1",
    ),
    (
        "fit_plane_ransac(threshold=nan)",
        lambda: fit_plane_ransac(torch.rand(10, 3), NAN),
        "threshold: expected finite values",
    ),
    (
        "fit_plane_ransac(iterations=0)",
        lambda: fit_plane_ransac(torch.rand(10, 3), 0.1, iterations=0),
        "iterations: expected >= 1, got 0",
    ),
    (
        "normals_to_quats((5, 2))",
        lambda: normals_to_quats(torch.rand(5, 2)),
        r"normals: expected shape \(N, 3\), got \(5, 2\)",
    ),
    (
        "voxelize(1e-30)",
        lambda: voxelize(torch.rand(10, 3) * 50, 1e-30),
        "voxel_size: 1e-30 makes .* cells along an axis",
    ),
    (
        "voxel_downsample(1e-30)",
        lambda: voxel_downsample(torch.rand(10, 3) * 50, torch.rand(10, 3), 1e-30),
        "voxel_size: 1e-30 makes",
    ),
]


@pytest.mark.parametrize(("name", "call", "message"), CASES, ids=[c[0] for c in CASES])
def test_bad_value_is_a_value_error_naming_the_argument(name, call, message):
    with pytest.raises(ValueError, match=message) as e:
        call()
    assert "\n" not in str(e.value)


def test_value_checks_obey_the_switch():
    with checking(False):  # the caller vouches for the values: no check, no host synchronisation
        assert invert_rigid(torch.full((4, 4), NAN))[:3].isnan().all()
        assert quaternion_to_rotation(torch.zeros(1, 4)).isnan().all()
    with pytest.raises(ValueError, match=r"normals: expected shape"):  # shape checks always run
        with checking(False):
            normals_to_quats(torch.rand(5, 2))


def test_checking_holds_for_its_thread_only():
    """Blocks in two threads that overlap (A in, B in, A out, B out) leave checks on in both, and
    a thread that does not ask keeps them on meanwhile (a viewer rendering beside an event)."""
    import threading

    from vadgs import checks_enabled

    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen: dict[str, bool] = {}

    def a():
        with checking(False):
            seen["a_inside"] = checks_enabled()
            a_in.set()
            b_in.wait(10)
        seen["a_after"] = checks_enabled()
        a_out.set()

    def b():
        a_in.wait(10)
        with checking(False):
            b_in.set()
            a_out.wait(10)
        seen["b_after"] = checks_enabled()

    threads = [threading.Thread(target=f) for f in (a, b)]
    for t in threads:
        t.start()
    a_in.wait(10)
    seen["main_meanwhile"] = checks_enabled()
    for t in threads:
        t.join(10)
    assert seen == {"a_inside": False, "main_meanwhile": True, "a_after": True, "b_after": True}
    assert checks_enabled()


def test_valid_inputs_still_give_the_reference_values():
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    assert invert_rigid(T)[:3, 3].tolist() == [-1.0, -2.0, -3.0]
    uv, z = project_points(torch.tensor([[[0.0, 0.0, 2.0]]]), K_OK)
    assert uv.tolist() == [[[50.0, 40.0]]] and z.tolist() == [[2.0]]
    assert top_k_views(torch.tensor([9.0, 0.0, 3.0, 5.0]), ref=0, k=3).tolist() == [3, 2]
    assert top_k_views(torch.tensor([9.0, 1.0]), ref=0, k=0).tolist() == []
    res = _pm(torch.float32)
    assert res.depth.dtype == torch.float32


class TestCliqueIsBounded:
    @pytest.mark.parametrize(("n", "k"), [(40, 10), (30, 8), (60, 30)])
    def test_refused_within_a_second(self, n, k):
        """n = 40, k = 10 used ~21 GB in 71 s until the kernel killed it.

        CPU seconds of this process (``time.process_time``), not wall-clock: other processes on a
        loaded machine do not count against the bound."""
        t0 = time.process_time()
        with pytest.raises(
            ValueError, match=rf"k = {k} over {n} nodes .* means ([\d.e+]+) subsets to score"
        ) as e:
            max_weight_clique(torch.rand(n), torch.rand(n, n), k)
        assert time.process_time() - t0 < 1.0
        assert f"{math.comb(n, k):.3g} subsets" in str(e.value)

    def test_many_maximal_cliques_refused_within_a_second(self):
        n = 60  # the complement of 20 disjoint triangles: 3^20 maximal cliques (Moon-Moser)
        adj = torch.ones(n, n, dtype=torch.bool)
        for i in range(0, n, 3):
            adj[i : i + 3, i : i + 3] = False
        t0 = time.process_time()  # CPU seconds (see above)
        with pytest.raises(ValueError, match=f"more than MAX_CLIQUES = {MAX_CLIQUES} maximal cliques"):
            max_weight_clique(torch.rand(n), torch.rand(n, n), 4, adj)
        assert time.process_time() - t0 < 2.0  # 0.85 s measured on the shared 2-core machine

    def test_within_the_bound_it_is_exact(self):
        gen = torch.Generator().manual_seed(0)
        n, k = 12, 4
        w, W = torch.rand(n, generator=gen), torch.rand(n, n, generator=gen)
        W = (W + W.T) / 2
        best = max_weight_clique(w, W, k)
        import itertools

        def value(s):
            return float(w[list(s)].sum() + sum(W[i, j] for i, j in itertools.combinations(s, 2)))

        ref = max(itertools.combinations(range(n), k), key=value)
        assert best.nodes.tolist() == list(ref) and best.weight == pytest.approx(value(ref))
        # a raised bound lets a larger search through, a lowered one refuses a small one
        assert len(max_weight_clique(torch.rand(24), torch.rand(24, 24), 8, max_subsets=10**6).nodes) == 8
        with pytest.raises(ValueError, match="max_subsets = 100"):
            max_weight_clique(w, W, k, max_subsets=100)

    def test_selection_config_checks_the_bound(self):
        with pytest.raises(ValueError, match=r"max_candidates, k: .* got C\(40, 10\) = 8.48e\+08"):
            ViewSelectionConfig(k=10, max_candidates=40)
        ViewSelectionConfig(k=4, max_candidates=24)
