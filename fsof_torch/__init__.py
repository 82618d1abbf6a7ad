"""fsof-torch: freespace optical flow (Feng et al., T-MECH 2023) for PyTorch.

The road's optical flow in closed form from the camera (intrinsics, height, roll, pitch) and the
ego-motion, as differentiable batched modules; fitting it to flow or images; refining a flow
network's prediction with it; photometric and ground-truth evaluation; a training loss term.
Submodules: ``camera``, ``flow_model``, ``egomotion``, ``fit``, ``vflow``, ``pose``, ``warp``,
``photometric``, ``metrics``, ``fusion``, ``losses``, ``testnet``, ``scene``, ``io``,
``datasets``, ``visualize``.
"""

from . import datasets, io, metrics
from .camera import Camera, mounting_matrix, pitch_matrix, read_kitti_calibration, roll_matrix
from .egomotion import EgoMotion, ego_motion_from_ackermann, ego_motion_from_pose, relative_pose
from .fit import FitResult, VelocityFitResult, fit_displacement, fit_photometric, fit_velocity
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
from .fusion import FreespaceRefined, FreespaceRefiner, RefineOutput, fuse_flow, refine_flow
from .io import (
    read_flo,
    read_flow,
    read_image,
    read_kitti_flow,
    read_kitti_poses,
    read_road_mask,
    write_flo,
    write_flow,
    write_image,
    write_kitti_flow,
    write_kitti_poses,
)
from .losses import CompositeLoss, FreespaceFlowLoss, UnsupervisedFlowLoss
from .metrics import (
    angular_error,
    endpoint_error,
    flow_metrics,
    flow_metrics_per_sample,
    outlier_rate,
    u_error,
    v_error,
)
from .photometric import PhotometricError, photometric_error, photometric_error_map
from .pose import pose_estimation_experiment
from .scene import PRESETS, collate, render_pair, render_sequence
from .testnet import TinyRAFT
from .vflow import detect_freespace, fit_vflow_curve, vflow_map
from .visualize import flow_to_color, save_error_png, save_flow_png, save_overlay_png
from .warp import WarpBackward, warp_backward

__version__ = "0.1.0"

__all__ = [
    "Camera",
    "CompositeLoss",
    "DisplacementFlow",
    "EgoMotion",
    "FitResult",
    "FreespaceFlowLoss",
    "FreespaceRefined",
    "FreespaceRefiner",
    "PRESETS",
    "PhotometricError",
    "RefineOutput",
    "TinyRAFT",
    "UnsupervisedFlowLoss",
    "VelocityFitResult",
    "VelocityFlow",
    "WarpBackward",
    "angular_error",
    "collate",
    "datasets",
    "detect_freespace",
    "displacement_flow",
    "displacement_flow_straight",
    "displacement_flow_straight_level",
    "ego_motion_from_ackermann",
    "ego_motion_from_pose",
    "endpoint_error",
    "fit_displacement",
    "fit_photometric",
    "fit_velocity",
    "fit_vflow_curve",
    "flow_metrics",
    "flow_metrics_per_sample",
    "flow_to_color",
    "fuse_flow",
    "io",
    "metrics",
    "mounting_matrix",
    "outlier_rate",
    "photometric_error",
    "photometric_error_map",
    "pitch_matrix",
    "pixel_grid",
    "pose_estimation_experiment",
    "read_flo",
    "read_flow",
    "read_image",
    "read_kitti_calibration",
    "read_kitti_flow",
    "read_kitti_poses",
    "read_road_mask",
    "refine_flow",
    "relative_pose",
    "render_pair",
    "render_sequence",
    "road_homography",
    "road_velocity_matrix",
    "roll_matrix",
    "save_error_png",
    "save_flow_png",
    "save_overlay_png",
    "u_error",
    "v_error",
    "velocity_flow",
    "velocity_flow_straight",
    "velocity_flow_straight_level",
    "vflow_curve",
    "vflow_map",
    "warp_backward",
    "write_flo",
    "write_flow",
    "write_image",
    "write_kitti_flow",
    "write_kitti_poses",
]
