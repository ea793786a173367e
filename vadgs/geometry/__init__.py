"""Geometry: cameras, poses, rotations, homographies, voxel grids and z-buffer, point clouds, resampling.

Knows nothing about Gaussians or scenes: every function takes tensors and small dataclasses.
"""

from vadgs.geometry.camera import (
    Cameras,
    backproject_depth,
    camera_centers,
    cameras_in_object_frame,
    invert_rigid,
    level_up,
    observing_views,
    pixel_grid,
    project_points,
    relative_pose,
    scale_intrinsics,
    shift_K,
)
from vadgs.geometry.camera_path import (
    CameraPath,
    catmull_rom,
    focus_point,
    interpolate_rigid,
    keyframe_path,
    look_at,
    orbit_path,
    spline_path,
)
from vadgs.geometry.ground import ground_cells, ground_frame, points_in_frame, sample_rows
from vadgs.geometry.homography import (
    apply_homography,
    homography_warp,
    plane_distance,
    plane_homography,
    warp_patches,
)
from vadgs.geometry.octahedral import octahedral_decode, octahedral_encode
from vadgs.geometry.points import VoxelAccumulator, knn_scales, thin_points, voxel_downsample
from vadgs.geometry.resample import pool_mask, pool_valid, repeat
from vadgs.geometry.rotation import normals_to_quats, quat_multiply, quaternion_to_rotation, rotation_to_quat
from vadgs.geometry.voxel import (
    ChunkedVoxels,
    PointChunk,
    VoxelGrid,
    unique_cells,
    voxel_labels,
    voxelize,
    voxelize_chunks,
)
from vadgs.geometry.zbuffer import VoxelRaster, VoxelRasterizer, ZBufferConfig, rasterize_voxels

__all__ = [
    "CameraPath",
    "Cameras",
    "ChunkedVoxels",
    "PointChunk",
    "VoxelAccumulator",
    "VoxelGrid",
    "VoxelRaster",
    "VoxelRasterizer",
    "ZBufferConfig",
    "apply_homography",
    "backproject_depth",
    "camera_centers",
    "cameras_in_object_frame",
    "catmull_rom",
    "focus_point",
    "ground_cells",
    "ground_frame",
    "homography_warp",
    "interpolate_rigid",
    "invert_rigid",
    "keyframe_path",
    "knn_scales",
    "level_up",
    "look_at",
    "normals_to_quats",
    "observing_views",
    "octahedral_decode",
    "octahedral_encode",
    "orbit_path",
    "pixel_grid",
    "plane_distance",
    "plane_homography",
    "points_in_frame",
    "pool_mask",
    "pool_valid",
    "project_points",
    "quat_multiply",
    "quaternion_to_rotation",
    "rasterize_voxels",
    "relative_pose",
    "repeat",
    "rotation_to_quat",
    "sample_rows",
    "scale_intrinsics",
    "shift_K",
    "spline_path",
    "thin_points",
    "unique_cells",
    "voxel_downsample",
    "voxel_labels",
    "voxelize",
    "voxelize_chunks",
    "warp_patches",
]
