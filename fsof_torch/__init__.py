"""fsof-torch: freespace optical flow (Feng et al., T-MECH 2023) for PyTorch.

The road's optical flow in closed form from the camera (intrinsics, height, roll, pitch) and the
ego-motion, as differentiable batched modules; fitting it to flow or images; refining a flow
network's prediction with it; photometric and ground-truth evaluation; a training loss term.
Subpackages: ``geometry``, ``estimation``, ``refinement``, ``evaluation``, ``training``, ``data``,
``io``. Short module paths are aliases of their modules: ``camera``, ``flow_model``, ``egomotion``,
``fit``, ``vflow``, ``warp``, ``photometric``, ``metrics``, ``fusion``, ``losses``, ``testnet``,
``scene``, ``datasets``, ``visualize``.
"""

import sys as _sys

from . import io
from .estimation import flow_fit as _flow_fit, image_fit as _image_fit
from .geometry import road_flow as _road_flow
from .data import datasets, scene
from .estimation import vflow
from .evaluation import metrics, photometric, visualize, warp
from .geometry import camera, egomotion
from .refinement import fusion
from .training import losses, testnet
from .geometry.camera import Camera, mounting_matrix, pitch_matrix, read_kitti_calibration, roll_matrix
from .geometry.egomotion import EgoMotion, ego_motion_from_ackermann, ego_motion_from_pose, relative_pose
from .refinement.estimators import FlowMotionEstimator, ImageMotionEstimator
from .refinement.gate import ImageGate
from .estimation.flow_fit import (
    FitResult,
    RoadFit,
    VelocityFitResult,
    fit_displacement,
    fit_road,
    fit_velocity,
)
from .estimation.decompose import decompose_homography
from .estimation.image_fit import fit_image, fit_photometric
from .estimation.sequence import SequenceFit, fit_sequence
from .geometry.road_flow import (
    DisplacementFlow,
    VelocityFlow,
    displacement_flow,
    displacement_flow_straight,
    displacement_flow_straight_level,
    RoadFlow,
    pixel_grid,
    road_flow,
    road_velocity_matrix,
    velocity_flow,
    velocity_flow_straight,
    velocity_flow_straight_level,
    vflow_curve,
)
from .geometry.road_models import ROAD_MODELS, RoadModel, plane_from_pose, road_homography, road_motion
from .refinement.fusion import FreespaceRefiner, RefineOutput, fuse_flow, refine_flow
from .refinement.wrapped import FreespaceRefined
from .refinement.contracts import InputPadder
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
from .training.losses import CompositeLoss, FreespaceFlowLoss, UnsupervisedFlowLoss
from .evaluation.metrics import (
    FlowMetricAccumulator,
    angular_error,
    endpoint_error,
    flow_metrics,
    flow_metrics_per_sample,
    outlier_rate,
    u_error,
    v_error,
)
from .evaluation.photometric import (
    PhotometricError,
    photometric_error,
    photometric_error_map,
    photometric_error_maps,
    photometric_errors,
)
from .data.scene import PRESETS, collate, render_pair, render_sequence
from .training.testnet import TinyRAFT
from .estimation.freespace import detect_freespace
from .refinement.auto_road import RoadDetection, detect_road, road_seed
from .estimation.vflow import fit_vflow_curve, vflow_map
from .evaluation.visualize import flow_to_color, save_error_png, save_flow_png, save_overlay_png
from .evaluation.warp import WarpBackward, warp_backward

from ._check import trust_image_range
from .warn import FreespaceWarning

from . import version as _version

__version__ = _version.__version__

# The short module paths (``fsof_torch.metrics``, ``fsof_torch.camera``, ...) are importable:
# each is an alias of the module that holds it, in sys.modules and as an
# attribute (``import fsof_torch.fit`` finds the module in sys.modules and sets no attribute).
# ``fsof_torch.fit_photometric`` is the function; its module path stays in sys.modules only
# (``from fsof_torch.fit_photometric import fit_image`` works; the attribute is the function).
for _name, _module in {"camera": camera, "egomotion": egomotion, "flow_model": _road_flow,
                       "fit": _flow_fit, "vflow": vflow,
                       "fusion": fusion, "warp": warp, "photometric": photometric, "metrics": metrics,
                       "visualize": visualize, "losses": losses, "testnet": testnet,
                       "datasets": datasets, "scene": scene}.items():
    _sys.modules.setdefault(f"{__name__}.{_name}", _module)
    globals().setdefault(_name, _module)
_sys.modules.setdefault(f"{__name__}.fit_photometric", _image_fit)
del _name, _module

__all__ = [
    "Camera",
    "CompositeLoss",
    "DisplacementFlow",
    "EgoMotion",
    "FitResult",
    "FlowMetricAccumulator",
    "FreespaceFlowLoss",
    "FreespaceRefined",
    "FreespaceRefiner",
    "FreespaceWarning",
    "InputPadder",
    "PRESETS",
    "PhotometricError",
    "RefineOutput",
    "RoadDetection",
    "TinyRAFT",
    "UnsupervisedFlowLoss",
    "VelocityFitResult",
    "VelocityFlow",
    "WarpBackward",
    "angular_error",
    "collate",
    "datasets",
    "detect_freespace",
    "detect_road",
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
    "trust_image_range",
    "io",
    "metrics",
    "mounting_matrix",
    "outlier_rate",
    "photometric_error",
    "photometric_error_map",
    "photometric_error_maps",
    "photometric_errors",
    "pitch_matrix",
    "pixel_grid",
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
    "road_flow",
    "road_seed",
    "RoadFlow",
    "RoadFit",
    "RoadModel",
    "ROAD_MODELS",
    "fit_road",
    "fit_image",
    "fit_sequence",
    "SequenceFit",
    "FlowMotionEstimator",
    "ImageMotionEstimator",
    "ImageGate",
    "decompose_homography",
    "plane_from_pose",
    "road_motion",
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
