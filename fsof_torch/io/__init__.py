"""Data formats: flow files (KITTI PNG, Middlebury .flo, .npy, Virtual KITTI 2, CARLA), images,
road masks, KITTI poses and calibration, the synthetic KITTI-like layout; atomic writing; what
produced a result file (:func:`environment`, the ``environment`` block of the jobs' JSON outputs).

Every reader checks what it reads and raises a ValueError naming the path (truncated PNG, wrong
bit depth or channel count, wrong ``.flo`` magic or size); every writer writes a temporary file
in the target folder and renames it (:func:`atomic_path`), so a crash leaves no half file.
Conventions: flow (2, H, W) float32 in pixels, channel 0 = u; valid and road masks (1, H, W)
bool; images (3, H, W) float32 RGB 0..255.
"""

from ..geometry.camera import read_kitti_calibration
from .atomic import atomic_path, remove_stale_temporaries, to_jsonable, write_bytes, write_json, write_text
from .carla import (
    CARLA_CAMERA_HEIGHT,
    CARLA_ROAD_COLORS,
    CARLA_WHEELBASE,
    CarlaRun,
    carla_camera,
    parse_carla_run_name,
    read_carla_flow,
    read_carla_road,
    write_carla_flow,
)
from .flo import FLO_MAGIC, read_flo, write_flo
from .flow import read_flow, write_flow
from .images import read_image, read_image_array, write_image, write_image_array
from .kitti import (
    KITTI_FLOW_MAX,
    KITTI_FLOW_MIN,
    KITTI_FLOW_SCALE,
    read_kitti_flow,
    read_kitti_poses,
    write_kitti_calibration,
    write_kitti_flow,
    write_kitti_poses,
)
from .layout import (
    SYNTHETIC_FORMAT,
    camera_from_params,
    pair_name,
    read_depth_png,
    read_synthetic_pair,
    read_synthetic_params,
    relative_pose_from_odometry,
    synthetic_pair_indices,
    write_depth_png,
    write_synthetic_pair,
    write_synthetic_sequence,
)
from .masks import (
    mask_from_colors,
    rasterize_polygons,
    read_label_map,
    read_road_mask,
    write_label_map,
    write_road_mask,
)
from .provenance import code_digest, cpu_name, dependency_versions, environment
from .vkitti import (
    read_vkitti2_classes,
    read_vkitti2_colors,
    read_vkitti2_extrinsics,
    read_vkitti2_flow,
    read_vkitti2_intrinsics,
    vkitti2_camera_poses,
    write_vkitti2_flow,
)

__all__ = [
    "CARLA_CAMERA_HEIGHT",
    "CARLA_ROAD_COLORS",
    "CARLA_WHEELBASE",
    "CarlaRun",
    "FLO_MAGIC",
    "KITTI_FLOW_MAX",
    "KITTI_FLOW_MIN",
    "KITTI_FLOW_SCALE",
    "SYNTHETIC_FORMAT",
    "atomic_path",
    "camera_from_params",
    "carla_camera",
    "code_digest",
    "cpu_name",
    "dependency_versions",
    "environment",
    "mask_from_colors",
    "pair_name",
    "parse_carla_run_name",
    "rasterize_polygons",
    "read_carla_flow",
    "read_carla_road",
    "read_depth_png",
    "read_flo",
    "read_flow",
    "read_image",
    "read_image_array",
    "read_kitti_calibration",
    "read_kitti_flow",
    "read_kitti_poses",
    "read_label_map",
    "read_road_mask",
    "read_synthetic_pair",
    "read_synthetic_params",
    "read_vkitti2_classes",
    "read_vkitti2_colors",
    "read_vkitti2_extrinsics",
    "read_vkitti2_flow",
    "read_vkitti2_intrinsics",
    "relative_pose_from_odometry",
    "remove_stale_temporaries",
    "synthetic_pair_indices",
    "to_jsonable",
    "vkitti2_camera_poses",
    "write_bytes",
    "write_carla_flow",
    "write_depth_png",
    "write_flo",
    "write_flow",
    "write_image",
    "write_image_array",
    "write_json",
    "write_kitti_calibration",
    "write_kitti_flow",
    "write_kitti_poses",
    "write_label_map",
    "write_road_mask",
    "write_synthetic_pair",
    "write_synthetic_sequence",
    "write_text",
    "write_vkitti2_flow",
]
