"""Geometry: cameras, poses, rotations, plane homographies, voxel grids, the voxel z-buffer, normal codes.

Knows nothing about Gaussians or scenes: every function takes tensors and small dataclasses.
"""

from vadgs.geometry.camera import (
    Cameras,
    backproject_depth,
    camera_centers,
    cameras_in_object_frame,
    invert_rigid,
    level_up,
    pixel_grid,
    project_points,
    relative_pose,
    scale_intrinsics,
)
from vadgs.geometry.homography import (
    apply_homography,
    homography_warp,
    plane_distance,
    plane_homography,
    warp_patches,
)
from vadgs.geometry.octahedral import octahedral_decode, octahedral_encode
from vadgs.geometry.rotation import quat_multiply, quaternion_to_rotation, rotation_to_quat
from vadgs.geometry.voxel import (
    ChunkedVoxels,
    PointChunk,
    VoxelGrid,
    observing_views,
    unique_cells,
    voxel_labels,
    voxelize,
    voxelize_chunks,
)
from vadgs.geometry.zbuffer import VoxelRaster, VoxelRasterizer, ZBufferConfig, rasterize_voxels

__all__ = [
    "Cameras",
    "ChunkedVoxels",
    "PointChunk",
    "VoxelGrid",
    "VoxelRaster",
    "VoxelRasterizer",
    "ZBufferConfig",
    "apply_homography",
    "backproject_depth",
    "camera_centers",
    "cameras_in_object_frame",
    "homography_warp",
    "invert_rigid",
    "level_up",
    "observing_views",
    "octahedral_decode",
    "octahedral_encode",
    "pixel_grid",
    "plane_distance",
    "plane_homography",
    "project_points",
    "quat_multiply",
    "quaternion_to_rotation",
    "rasterize_voxels",
    "relative_pose",
    "rotation_to_quat",
    "scale_intrinsics",
    "unique_cells",
    "voxel_labels",
    "voxelize",
    "voxelize_chunks",
    "warp_patches",
]
