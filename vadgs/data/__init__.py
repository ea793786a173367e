"""Scene loaders: the benchmark format, COLMAP, TRI's DGP, nuScenes, Waymo, PandaSet, Argoverse 2.

A folder of photos becomes a COLMAP project with :func:`run_sfm` (``vadgs sfm``);
:func:`make_segment` writes a procedural driving segment in the benchmark format at any size, and
:func:`write_waymo_segment` a benchmark scene as the Waymo v2 parquet components that
:func:`load_waymo` reads.

Every loader returns a :class:`~vadgs.data.scene.Scene`; per-view images, depth and instance
maps are read lazily.
"""

from pathlib import Path

from vadgs.data.argoverse2 import load_argoverse2
from vadgs.data.checks import ValidationReport, ValidationRow
from vadgs.data.colmap import ColmapScene, load_colmap
from vadgs.data.colmap_model import find_colmap_model, match_colmap_views
from vadgs.data.colmap_project import open_colmap_project, reopen_colmap_project
from vadgs.data.dgp import load_dgp
from vadgs.data.export import export_scene
from vadgs.data.nuscenes import load_nuscenes
from vadgs.data.pandaset import load_pandaset
from vadgs.data.scene import (
    CameraInfo,
    ColmapPoints,
    FrameInfo,
    InstanceInfo,
    LidarFrame,
    Scene,
    Track,
    ViewInfo,
)
from vadgs.data.scene_json import load_scene
from vadgs.data.sfm import SfmResult, run_sfm
from vadgs.data.synthetic import SegmentConfig, make_segment
from vadgs.data.validate import validate_scene
from vadgs.data.waymo import load_waymo
from vadgs.data.waymo_writer import write_waymo_segment

__all__ = [
    "CameraInfo",
    "ColmapPoints",
    "ColmapScene",
    "FrameInfo",
    "InstanceInfo",
    "LidarFrame",
    "Scene",
    "SegmentConfig",
    "SfmResult",
    "Track",
    "ValidationReport",
    "ValidationRow",
    "ViewInfo",
    "export_scene",
    "find_colmap_model",
    "load_argoverse2",
    "load_colmap",
    "load_dgp",
    "load_nuscenes",
    "load_pandaset",
    "load_scene",
    "load_waymo",
    "make_segment",
    "match_colmap_views",
    "open_colmap_project",
    "reopen_colmap_project",
    "run_sfm",
    "sample_scene_path",
    "validate_scene",
    "write_waymo_segment",
]


def sample_scene_path() -> Path:
    """Path of the small sample scene bundled with vadgs (a cut of street_a at 240×144).

    Frames 16–23 of street_a, three cameras, LiDAR subsampled to 12k points per frame, made by
    ``tools/make_sample_scene.py``. Ground-truth depth is nearest-subsampled from full resolution.
    """
    return Path(__file__).resolve().parent / "sample_scene"
