"""fsof-torch: freespace optical flow (Feng et al., T-MECH 2023) for PyTorch."""

from .camera import Camera, mounting_matrix, pitch_matrix, read_kitti_calibration, roll_matrix
from .egomotion import EgoMotion, ego_motion_from_ackermann, ego_motion_from_pose, relative_pose
from .flow_model import (
    DisplacementFlow,
    VelocityFlow,
    displacement_flow,
    displacement_flow_straight,
    displacement_flow_straight_level,
    pixel_grid,
    road_homography,
    road_velocity_matrix,
    velocity_flow,
    velocity_flow_straight,
    velocity_flow_straight_level,
    vflow_curve,
)

__version__ = "0.1.0"

__all__ = [
    "Camera",
    "DisplacementFlow",
    "EgoMotion",
    "VelocityFlow",
    "displacement_flow",
    "displacement_flow_straight",
    "displacement_flow_straight_level",
    "ego_motion_from_ackermann",
    "ego_motion_from_pose",
    "mounting_matrix",
    "pitch_matrix",
    "pixel_grid",
    "read_kitti_calibration",
    "relative_pose",
    "road_homography",
    "road_velocity_matrix",
    "roll_matrix",
    "velocity_flow",
    "velocity_flow_straight",
    "velocity_flow_straight_level",
    "vflow_curve",
]
