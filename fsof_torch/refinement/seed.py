"""The road detection's seed (:mod:`fsof_torch.refinement.auto_road`, step 1): the road in front of
the vehicle from the camera's geometry alone, straight ahead or along a curved path.

The vehicle drives along its path: straight ahead, or, turning, an arc of curvature κ (1/m, > 0
turning right), whose heading turns by κ per metre driven. A road point (X, Z) on the road plane
(metres: lateral, forward; the vehicle frame of :mod:`fsof_torch.geometry.road_models`) lies at
a lateral offset from the path and a distance along it: X and Z straight ahead; on the arc, whose
centre lies at (1 / κ, 0), its distance from the arc and the arc's length up to its foot. The
seed is the road within ``width / 2`` of the path and nearer than ``depth`` along it.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from .._check import check_float_tensor, check_size, is_number, option_error, scalar
from ..geometry.camera import Camera
from ..geometry.road_models import plane_from_homography, road_homography, road_motion

__all__ = ["road_seed", "path_curvature"]


def ground(camera: Camera, size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """Lateral X and forward Z (metres, vehicle frame) of the road point seen by every pixel, and
    whether the pixel sees the road in front of the camera (below the horizon): (B, 1, H, W) each."""
    H, W = size
    cam = camera.to(torch.float64)
    A = cam.mounting().transpose(-1, -2) @ cam.K_inv()  # pixel -> vehicle-frame ray
    u = torch.arange(W, dtype=torch.float64, device=cam.device)
    v = torch.arange(H, dtype=torch.float64, device=cam.device)
    ray = A[:, :, 0:1, None] * u + A[:, :, 1:2, None] * v[:, None] + A[:, :, 2:3, None]  # (B, 3, H, W)
    below = ray[:, 1] > 1e-9
    s = cam.height.reshape(-1, 1, 1) / torch.where(below, ray[:, 1], 1.0)
    return (s * ray[:, 0]).unsqueeze(1), (s * ray[:, 2]).unsqueeze(1), below.unsqueeze(1)


def along_path(X: Tensor, Z: Tensor, curvature: Tensor | None) -> tuple[Tensor, Tensor]:
    """The lateral offset from the path (its magnitude) and the distance along it (metres) of road
    points X, Z (B, 1, H, W) for paths of ``curvature`` (B,) 1/m (None, or 0 for a sample: straight
    ahead, |X| and Z themselves). A point behind the arc's start is infinitely far along it."""
    if curvature is None:
        return X.abs(), Z
    k = curvature.to(X).reshape(-1, 1, 1, 1)
    straight = k == 0
    R = 1.0 / torch.where(straight, 1.0, k)  # (the arc's centre: (R, 0))
    # the angle the heading turns through from the camera to the point's foot on the arc
    turned = torch.atan2(Z, torch.sign(R) * (R - X))
    lateral = (torch.hypot(X - R, Z) - R.abs()).abs()
    along = torch.where(turned >= 0, R.abs() * turned, math.inf)
    return torch.where(straight, X.abs(), lateral), torch.where(straight, Z, along)


def seed_mask(X: Tensor, Z: Tensor, below: Tensor, width_m: float, depth_m: float,
              curvature: Tensor | None = None) -> Tensor:
    """The seed (B, 1, H, W) bool from :func:`ground`'s outputs (:func:`road_seed`)."""
    lateral, along = along_path(X, Z, curvature)
    return below & (lateral <= width_m / 2) & (along <= depth_m)


def path_curvature(yaw: Tensor, x_d: Tensor, z_d: Tensor, width_m: float, depth_m: float) -> Tensor:
    """The curvature (B,) 1/m of the path a motion of ``yaw`` (rad), ``x_d`` and ``z_d`` (m) a frame
    drives, where it takes the path out of the straight seed (``width_m`` wide, ``depth_m`` deep)
    within the seed's depth: where the arc's offset at that depth, about κ depth² / 2, exceeds
    the seed's half width, |κ| > width / depth², κ = yaw / z_d. Elsewhere 0 (the straight seed
    holds the path), and so where the motion does not drive forwards, or does not move sideways
    as a vehicle turning on its path does: without side slip its rear axle moves towards the turn
    by z_d tan(yaw / 2) ≈ z_d yaw / 2 (the chord of its arc), a camera ahead of the axle by more;
    a motion that moves less than half that towards the turn (a camera turned in place, an image
    rotated; the half allows for the fit's error) yaws across its path, not along it."""
    # (numbers on the host, tensors where they are: not on a default device set by the caller)
    yaw, x_d, z_d = (torch.as_tensor(t, dtype=torch.float64, device=t.device if isinstance(t, Tensor) else "cpu")
                     .reshape(-1) for t in (yaw, x_d, z_d))
    k = yaw / torch.where(z_d > 0, z_d, 1.0)
    along = x_d * torch.sign(yaw) >= 0.25 * z_d * yaw.abs()
    return torch.where((z_d > 0) & along & (k.abs() > width_m / depth_m ** 2), k, 0.0)


def plane_motion(motion: Any, camera: Camera) -> tuple[str, dict[str, Tensor]]:
    """The motion as a model with metric translation (``"paper"`` or ``"plane"``): a
    ``"homography"`` is decomposed with the camera's attitude, and with the fit's own camera where
    it has one (its homography is in the pixels of the images it was fitted to), else ``camera``;
    one given by its parameters (calibrated: no resolution) is built with ``camera``. (Its plane
    gives the parallax of raised surfaces; the road is judged with the homography's own flow.)"""
    model, params = road_motion(motion, "motion")
    if model.name in ("paper", "plane"):
        return model.name, params
    if model.name == "homography":
        H, own = getattr(motion, "homography", None), getattr(motion, "camera", None)
        cam = (own if isinstance(own, Camera) and H is not None else camera).to(torch.float64)
        if H is None:
            H = road_homography(cam, {k: torch.as_tensor(v, dtype=torch.float64, device=cam.device) for k, v in params.items()},
                                model="homography")
        return "plane", plane_from_homography(H.to(torch.float64), cam)
    raise ValueError(f"motion: expected a displacement model ('paper', 'plane' or 'homography'), got {model.name!r}")


def road_seed(camera: Camera, size: tuple[int, int], *, width_m: float = 4.0, depth_m: float = 20.0,
              curvature: float | Tensor = 0.0) -> Tensor:
    """The conservative road in front of the vehicle, from the camera's geometry alone.

    The pixels whose viewing ray meets the road plane (the camera's height, roll and pitch) in
    front of the camera, within ``width_m / 2`` of the vehicle's path and nearer than ``depth_m``
    metres along it: a lane-wide band from the bottom of the image towards the horizon. The path
    runs straight ahead of the vehicle (``curvature`` 0), or turns along an arc of ``curvature``
    1/m (> 0 turning right; a number, or a tensor of one value per sample of the camera's batch).

    Returns (B, 1, H, W) bool, B the camera's batch.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    width_m, depth_m = scalar(width_m, "width_m"), scalar(depth_m, "depth_m")
    for name, value in (("width_m", width_m), ("depth_m", depth_m)):
        if not is_number(value) or not (0 < value < math.inf):
            raise option_error(value, f"{name}: expected a finite number of metres > 0, got {value!r}")
    if isinstance(curvature, Tensor) and curvature.dim() > 0:
        check_float_tensor(curvature, "curvature")
        if curvature.dim() != 1 or curvature.numel() not in (1, camera.batch_size):
            raise ValueError(f"curvature: expected a number or a 1-D tensor of 1 or {camera.batch_size} values "
                             f"(the camera's batch), got shape {tuple(curvature.shape)}")
        if not bool(torch.isfinite(curvature).all()):
            raise ValueError(f"curvature: expected finite values (1/m), got {curvature.tolist()}")
        bend = curvature.detach().to(torch.float64).expand(camera.batch_size)
    else:
        curvature = scalar(curvature, "curvature")
        if not is_number(curvature) or not math.isfinite(curvature):
            raise option_error(curvature, f"curvature: expected a finite number (1/m), got {curvature!r}")
        bend = None if curvature == 0 else torch.full((camera.batch_size,), float(curvature), dtype=torch.float64,
                                                      device=camera.device)
    X, Z, below = ground(camera, check_size(size))
    return seed_mask(X, Z, below, float(width_m), float(depth_m), None if bend is None else bend.to(X.device))
