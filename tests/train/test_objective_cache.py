"""Issue 40, memory bounded by design: the training views' images and LiDAR depth are kept on the host
in a byte-bounded cache (uint8, sparse), not every view in float32 on the device."""

from __future__ import annotations

import pytest
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.data.cache import ByteCache, SparseDepth, from_uint8, to_uint8
from vadgs.data.lidar import lidar_depth_map
from vadgs.train.config import TrainConfig
from vadgs.train.objective import Objective


class TestByteCache:
    def test_bounded_and_least_recently_used_first(self):
        cache = ByteCache(max_bytes=1000)
        made = []

        def make(i):
            made.append(i)
            return torch.zeros(100, dtype=torch.uint8) + i  # 100 bytes

        for i in range(25):
            cache.get(i, lambda i=i: make(i))
            assert cache.nbytes <= 1000
        assert cache.keys() == list(range(15, 25)) and cache.nbytes == 1000
        cache.get(15, lambda: make(-1))  # a hit: 15 becomes the most recent
        cache.get(99, lambda: make(99))  # drops 16, the least recent
        assert 15 in cache and 16 not in cache and made[-1] == 99
        assert (cache.hits, cache.misses) == (1, 26)

    def test_one_value_over_the_budget_is_kept_alone(self):
        cache = ByteCache(max_bytes=10)
        cache.get("a", lambda: torch.zeros(2))
        big = cache.get("b", lambda: torch.zeros(100))
        assert cache.keys() == ["b"] and big.numel() == 100

    @pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "1GB", True])
    def test_bad_budget(self, bad):
        with pytest.raises(ValueError, match="max_bytes: expected a"):
            ByteCache(bad)

    def test_uint8_round_trip(self):
        k = torch.arange(256, dtype=torch.float32)
        exact = k / 255.0  # an 8-bit image read at its own size
        assert torch.equal(from_uint8(to_uint8(exact)), exact)
        x = torch.rand(1000, generator=torch.Generator().manual_seed(0))  # a resampled image
        assert (from_uint8(to_uint8(x)) - x).abs().max() <= 0.5 / 255 + 1e-7

    def test_sparse_depth_is_the_dense_map(self):
        dense = torch.zeros(1, 1, 7, 9)
        dense[0, 0, [0, 3, 6], [8, 2, 0]] = torch.tensor([1.5, 20.25, 3.0])
        s = SparseDepth.from_dense(dense)
        assert s.points == 3 and torch.equal(s.to_dense(), dense)
        assert ByteCache.size_of(s) == 3 * 8 + 3 * 4


@pytest.fixture(scope="module")
def scene():
    return load_scene(sample_scene_path(), scale=0.5)


class TestObjectiveCache:
    def test_images_and_lidar_as_read(self, scene):
        obj = Objective(scene, TrainConfig(), torch.device("cpu"))
        for v in scene.train_views[:4]:
            img = obj.image(v)
            ref = scene.load_images([v])
            assert img.dtype == torch.float32 and img.shape == ref.shape
            assert (img - ref).abs().max() <= 0.5 / 255 + 1e-7
            assert torch.equal(obj.lidar_depth(v), lidar_depth_map(scene, v))

    def test_images_at_their_own_size_are_exact(self):
        full = load_scene(sample_scene_path())
        obj = Objective(full, TrainConfig(), torch.device("cpu"))
        v = full.train_views[0]
        assert torch.equal(obj.image(v), full.load_images([v]))

    def test_memory_is_bounded_by_cache_gb_not_by_the_views(self, scene):
        one_view = 3 * 72 * 120  # a uint8 image at half size
        budget = 4.5 * one_view
        obj = Objective(scene, TrainConfig(cache_gb=budget / 2**30), torch.device("cpu"))
        first = obj.image(scene.train_views[0])
        for v in scene.train_views:
            obj.image(v)
            assert obj.cache.nbytes <= budget
        assert len(obj.cache) == 4  # of 18 training views
        # a view dropped from the cache is read again, to the same values
        assert scene.train_views[0] not in {k[1] for k in obj.cache.keys()}
        assert torch.equal(obj.image(scene.train_views[0]), first)

    def test_uint8_host_cache_is_a_quarter_of_float32(self, scene):
        obj = Objective(scene, TrainConfig(lambda_lidar=0.0), torch.device("cpu"))
        for v in scene.train_views:
            obj.image(v)
        assert obj.cache.nbytes == len(scene.train_views) * 3 * 72 * 120  # 4 x less than float32

    def test_cache_gb_is_checked(self):
        with pytest.raises(ValueError, match=r"cache_gb: expected a finite number > 0 \(GB\), got 0"):
            TrainConfig(cache_gb=0)
