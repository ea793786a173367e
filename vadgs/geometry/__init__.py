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
    observing_views,
    pixel_grid,
    project_points,
    relative_pose,
    scale_intrinsics,
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
from vadgs.geometry.ground import ground_frame, points_in_frame, sample_rows
from vadgs.geometry.homography import (
    apply_homography,
    homography_warp,
    plane_distance,
    plane_homography,
    warp_patches,
)
from vadgs.geometry.octahedral import octahedral_decode, octahedral_encode
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
    "ground_frame",
    "homography_warp",
    "interpolate_rigid",
    "invert_rigid",
    "keyframe_path",
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
    "project_points",
    "quat_multiply",
    "quaternion_to_rotation",
    "rasterize_voxels",
    "relative_pose",
    "rotation_to_quat",
    "sample_rows",
    "scale_intrinsics",
    "spline_path",
    "unique_cells",
    "voxel_labels",
    "voxelize",
    "voxelize_chunks",
    "warp_patches",
]
