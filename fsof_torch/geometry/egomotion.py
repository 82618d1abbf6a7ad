"""Ego-motion in the paper's terms (x_d, z_d, yaw) from poses and from Ackermann kinematics.

Convention (DESIGN.md §2): the vehicle frame of time t has x right, y down, z forward; the
displacement model moves road points as ``p_v(t+1) = R_φ (p_v(t) - d)``, ``d = (x_d, 0, z_d)``.
Camera poses follow KITTI: camera-to-world 4×4 matrices, camera x right, y down, z forward.
The camera frame is the vehicle frame rotated by the mounting ``R_c = R_θ R_β`` (roll, pitch).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .._check import (as_batch_param, autocast_off, check_finite, check_positive, check_same_device, resolve_batch,
                      result_dtype, skip_values, summary_repr, tracing)
from .camera import Camera

__all__ = ["EgoMotion", "ego_motion_from_pose", "ego_motion_from_ackermann", "relative_pose", "as_pose_4x4",
           "check_pose_steps", "check_motion_step", "MAX_ROAD_SPEED", "MAX_FRAME_INTERVAL"]

#: the fastest a road vehicle moves, m/s (360 km/h: beyond any road car's top speed)
MAX_ROAD_SPEED = 100.0
#: the longest time between two consecutive frames of a video, s (one frame a second)
MAX_FRAME_INTERVAL = 1.0


class EgoMotion(NamedTuple):
    """Planar ego-motion of the displacement model, each (B,), and what the plane drops.

    ``x_d``, ``z_d`` in metres, ``yaw`` in radians. ``y_d`` (metres, positive down) and
    ``rotation_residual`` ((B, 3) axis-angle in radians, in the vehicle frame) are the
    out-of-plane part of the pose that the model cannot represent: a bump, a pitch or roll of
    the car body. Small values mean the model fits the pose. The residual is the axis-angle
    vector of the matrix R_v R_φᵀ that maps vehicle coordinates (the pose's rotation in the
    vehicle frame, its yaw taken out), so the body's pitch and roll changes α and γ of the
    ``"plane"`` model (positive α: pitching up) give about (−α, 0, −γ).
    """

    x_d: Tensor
    z_d: Tensor
    yaw: Tensor
    y_d: Tensor | None = None
    rotation_residual: Tensor | None = None

    __repr__ = summary_repr  # (one line: a batch of many frames as its shapes)


def relative_pose(pose0: Tensor, pose1: Tensor) -> Tensor:
    """``cam1_T_cam0 = inverse(pose1) @ pose0`` for camera-to-world poses (B, 4, 4) or (B, 3, 4),
    rigid (:func:`as_pose_4x4`: a ValueError names a pose that is not, and a singular one)."""
    P0, P1 = as_pose_4x4(pose0, "pose0"), as_pose_4x4(pose1, "pose1")
    check_same_device({"pose0": P0, "pose1": P1})
    resolve_batch({"pose0": P0.shape[0], "pose1": P1.shape[0]})
    dtype = result_dtype(P0, P1)
    with autocast_off(P0):
        # (rigid poses are invertible: inv_ex only spares the error handling while tracing)
        return torch.linalg.inv_ex(P1.to(dtype))[0] @ P0.to(dtype)


def _rigid_tolerance(dtype: torch.dtype) -> float:
    """How far the 3×3 block of a pose of ``dtype`` may be from a rotation for :func:`as_pose_4x4`:
    the largest entry of |RᵀR − I|.

    5e-3, or 4 eps of a coarser dtype (bfloat16: 3.1e-2, its own rounding). The check is for gross
    mistakes (a scaled or sheared block, an all-zero one), not rounding: KITTI's poses, printed
    to 7 digits, are orthonormal to 2e-7 (the relative poses of the shared odometry excerpt to
    5e-7, in float32 too), :func:`fsof_torch.io.read_kitti_poses` accepts 1e-3, and a relative
    pose of two such poses (what :func:`relative_pose` makes of them) adds their errors."""
    return max(5e-3, 4 * torch.finfo(dtype).eps)


def as_pose_4x4(T: Tensor, name: str) -> Tensor:
    """A rigid transform (B, 4, 4) or (B, 3, 4) (or unbatched) as float (B, 4, 4), validated.

    Finite, its 3×3 block R a rotation (|RᵀR − I| within :func:`_rigid_tolerance` of the input's
    dtype, det R > 0) and, for (B, 4, 4), its bottom row 0 0 0 1 (as
    :func:`fsof_torch.io.read_kitti_poses` checks it: to 1e-9, 1e-5 relative; a transposed pose
    has its translation there), else a ValueError naming ``name`` and the first sample that is
    not. So the pose is invertible. The values are not checked while tracing or on the meta
    device."""
    if not isinstance(T, Tensor) or not T.is_floating_point():
        raise TypeError(f"{name}: expected a float tensor of shape (B, 4, 4) or (B, 3, 4), got "
                        f"{type(T).__name__ if not isinstance(T, Tensor) else T.dtype}")
    if T.dim() not in (2, 3) or T.shape[-1] != 4 or T.shape[-2] not in (3, 4):
        raise ValueError(f"{name}: expected shape (B, 4, 4) or (B, 3, 4), got {tuple(T.shape)}")
    if T.dim() == 2:
        T = T.unsqueeze(0)
    tol = _rigid_tolerance(T.dtype)
    T = T.to(result_dtype(T))  # linear algebra in at least float32 (torch has no half inverse)
    check_finite(T, name)
    _check_rigid(T, name, tol)
    if T.shape[-2] == 3:
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device).expand(T.shape[0], 1, 4)
        T = torch.cat([T, bottom], dim=-2)
    return T


def _check_rigid(T: Tensor, name: str, tol: float) -> None:
    """Poses T (B, 3 or 4, 4), finite, are rigid within ``tol`` (one host read when they are)."""
    if skip_values(T) or T.numel() == 0:
        return
    with autocast_off(T):
        T = T.detach()
        R = T[:, :3, :3]
        error = (R.transpose(-1, -2) @ R - torch.eye(3, dtype=T.dtype, device=T.device)).abs().flatten(1).amax(1)
        det = torch.linalg.det(R)
        ok = (error <= tol) & (det > 0)
        if T.shape[-2] == 4:
            e4 = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device).expand(T.shape[0], 4)
            ok &= torch.isclose(T[:, 3], e4, rtol=1e-5, atol=1e-9).all(1)
        if bool(ok.all()):
            return
        i = int((~ok).nonzero()[0])
    if float(error[i]) <= tol and float(det[i]) > 0:
        what = f"its bottom row is {T[i, 3].tolist()}, not 0 0 0 1 (a transposed pose has its translation there)"
    else:
        what = f"its 3×3 block is not a rotation: |RᵀR − I| up to {float(error[i]):.3g}, det R = {float(det[i]):.3g}"
    raise ValueError(f"{name}: expected rigid transforms (a rotation block, |RᵀR − I| <= {tol:g}, det R > 0, "
                     f"and a bottom row 0 0 0 1), got sample {i}: {what}; {T[i].tolist()}")


def check_invertible(M: Tensor, name: str) -> None:
    """A ValueError naming ``name`` and the samples of the finite (B, n, n) matrices ``M`` that are
    singular: a determinant of exactly 0, in float64 with each column scaled to a largest entry of
    1 (so that no scale, as pixels against unitless entries, underflows or overflows it). Skipped
    where values cannot be read (:func:`~fsof_torch._check.skip_values`)."""
    if skip_values(M):
        return
    M64 = M.detach().to(torch.float64)
    scaled = M64 / M64.abs().amax(dim=-2, keepdim=True).clamp_min(torch.finfo(torch.float64).tiny)
    singular = torch.linalg.det(scaled) == 0
    if bool(singular.any()):
        bad = singular.nonzero().flatten().tolist()
        raise ValueError(f"{name}: expected invertible matrices, got samples {bad} that are singular, "
                         f"e.g. {M64[bad[0]].tolist()}")


def scalable_map(G: Tensor) -> Tensor:
    """(B,) whether the maps G (B, 3, 3) scale to a last entry of 1: that entry is not 0 up to the
    rounding of a product of such maps (16 ulps of G's largest entry), and G scaled by it is
    finite (False for a map holding NaN). The ``"homography"`` road model expresses K⁻¹ H K so."""
    zero = G[:, 2, 2].abs() <= 16 * torch.finfo(G.dtype).eps * G.abs().flatten(1).amax(1)
    return ~zero & torch.isfinite(G / G[:, 2:3, 2:3]).flatten(1).all(1)


def _axis_angle(R: Tensor) -> Tensor:
    """Axis-angle vectors (B, 3) of rotation matrices (B, 3, 3) (angles below π)."""
    w = torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], dim=-1)
    s = 0.5 * w.norm(dim=-1)
    c = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    angle = torch.atan2(s, c)
    # angle / (2 sin angle), written to stay finite at angle -> 0
    factor = torch.where(s > 1e-12, angle / (2 * s.clamp_min(1e-12)), torch.full_like(s, 0.5))
    return w * factor.unsqueeze(-1)


def ego_motion_from_pose(cam1_T_cam0: Tensor, camera: Camera | None = None,
                         pose1: Tensor | None = None) -> EgoMotion:
    """Project a relative camera pose onto the model's planar motion (x_d, z_d, yaw).

    Args:
        cam1_T_cam0: (B, 4, 4) or (B, 3, 4) transform of camera-t coordinates into camera-(t+1)
            coordinates; or, with ``pose1`` given, the camera-to-world pose of frame t.
        camera: supplies the mounting (roll, pitch) relating the camera to the vehicle frame;
            without it the two frames coincide.
        pose1: camera-to-world pose of frame t+1 (then ``cam1_T_cam0 = inverse(pose1) @ pose0``).

    Returns:
        :class:`EgoMotion` with x_d, z_d, yaw and the dropped remainder (y_d, rotation_residual).
    """
    if camera is not None and not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera or None, got {type(camera).__name__}")
    T = relative_pose(cam1_T_cam0, pose1) if pose1 is not None else as_pose_4x4(cam1_T_cam0, "cam1_T_cam0")
    with autocast_off(T):  # (geometry in the inputs' precision, also under autocast)
        return _planar_projection(T, camera)


def _planar_projection(T: Tensor, camera: Camera | None) -> EgoMotion:
    R, t = T[:, :3, :3], T[:, :3, 3]
    # (an empty batch too, with or without a camera: relative_pose and plane_from_pose refuse it)
    resolve_batch({"cam1_T_cam0": T.shape[0], **({} if camera is None else {"camera": camera.batch_size})})
    if camera is not None:
        Rc = camera.to(device=T.device, dtype=T.dtype).mounting()  # (the camera follows the pose)
    else:
        Rc = torch.eye(3, dtype=T.dtype, device=T.device).expand(1, 3, 3)
    # p_c1 = R p_c0 + t and p_c1 = R_c R_φ R_cᵀ p_c0 - R_c R_φ d  =>  R_v = R_cᵀ R R_c ≈ R_φ, t_v = R_cᵀ t = -R_φ d
    Rv = Rc.transpose(-1, -2) @ R @ Rc
    tv = (Rc.transpose(-1, -2) @ t.unsqueeze(-1)).squeeze(-1)
    yaw = torch.atan2(Rv[:, 2, 0] - Rv[:, 0, 2], Rv[:, 0, 0] + Rv[:, 2, 2])
    c, s = torch.cos(yaw), torch.sin(yaw)
    # d = -R_φᵀ t_v
    x_d = -(c * tv[:, 0] + s * tv[:, 2])
    y_d = -tv[:, 1]
    z_d = -(-s * tv[:, 0] + c * tv[:, 2])
    z, o = torch.zeros_like(c), torch.ones_like(c)
    R_phi = torch.stack([c, z, -s, z, o, z, s, z, c], dim=-1).reshape(-1, 3, 3)
    residual = _axis_angle(Rv @ R_phi.transpose(-1, -2))
    return EgoMotion(x_d, z_d, yaw, y_d, residual)


def ego_motion_from_ackermann(speed: Tensor | float, steering: Tensor | float,
                              wheelbase: Tensor | float, dt: Tensor | float, *,
                              camera_offset: Tensor | float = 0.0) -> EgoMotion:
    """Exact integration of the Ackermann model (no side slip) over ``dt`` seconds.

    With curvature κ = tan δ_f / l and arc length s = v_r Δt the vehicle turns by φ = κ s and
    its rear axle moves along the arc by ``(1 - cos φ) / κ`` to the side and ``sin φ / κ``
    forward, written with ``sinc`` so that straight motion (κ = 0) is exact and gradients stay
    finite. The displacement model's d is the camera's (the vehicle frame's origin is the camera
    centre, DESIGN.md §2): a camera ``camera_offset`` metres ahead of the rear axle (negative:
    behind) swings out of a turn, ``x_d = (1 - cos φ) / κ + a sin φ``, ``z_d = sin φ / κ -
    a (1 - cos φ)``. The default 0 is the paper's velocity model (lateral rate 0), exact for a
    camera above the rear axle; a windscreen camera 1.5 m ahead turning by 3° a frame moves
    8 cm further to the side than the axle.
    """
    named = {"speed": speed, "steering": steering, "wheelbase": wheelbase, "dt": dt, "camera_offset": camera_offset}
    given = [as_batch_param(v, n) for n, v in named.items() if isinstance(v, Tensor)]
    dtype = result_dtype(*given) if given else torch.get_default_dtype()
    device = given[0].device if given else None  # Python numbers follow the tensors' device
    p = {n: as_batch_param(v, n, dtype, device) for n, v in named.items()}
    resolve_batch({n: t.shape[0] for n, t in p.items()})
    check_positive(p["wheelbase"], "wheelbase")
    # (as velocity_flow: at ±π/2 the wheels stand across the car and tan δ_f has no meaning)
    if not tracing() and p["steering"].device.type != "meta" and not bool((p["steering"].abs() < torch.pi / 2).all()):
        raise ValueError(f"steering: expected |δ_f| < π/2 rad, got {p['steering'].tolist()}")
    arc = p["speed"] * p["dt"]
    yaw = arc * torch.tan(p["steering"]) / p["wheelbase"]
    # (1 - cos φ) / φ = (φ / 2) sinc²(φ / 2π); sin φ / φ = sinc(φ / π) (torch.sinc is normalised)
    versine, sine = (yaw / 2) * torch.sinc(yaw / (2 * torch.pi)) ** 2, torch.sinc(yaw / torch.pi)
    # the rear axle's arc (s times those), and the camera's offset a turned by φ: (a sin φ, -a (1 - cos φ))
    a = p["camera_offset"]
    x_d = arc * versine + a * yaw * sine
    z_d = arc * sine - a * yaw * versine
    zero = torch.zeros_like(yaw)
    return EgoMotion(x_d, z_d, yaw, zero, torch.zeros(*yaw.shape, 3, dtype=yaw.dtype, device=yaw.device))


def check_pose_steps(poses: Tensor, name: str = "poses", *, labels: list[str] | None = None,
                     frames_apart: list[int] | None = None) -> None:
    """Raise a ValueError naming ``name`` where two consecutive camera-to-world poses (N, 4, 4)
    lie farther apart than a road vehicle travels between two frames of a video
    (:data:`MAX_ROAD_SPEED` for :data:`MAX_FRAME_INTERVAL`: 100 m; ``frames_apart[i]`` times that
    between poses i and i + 1 where frames are missing between them).

    Such poses are in other units than metres, most likely millimetres (a car at 10 m/s and 10 Hz
    then moves 1000 "metres" a frame), or hold a jump; such a motion leaves the road's flow
    undefined in most of the image, so the refiner would leave the pairs unchanged with no word of why.
    ``labels[i]`` names pose i in the message (default ``"pose i"``)."""
    if poses.shape[0] < 2:
        return
    t = poses.detach().to("cpu", torch.float64)[:, :3, 3]
    steps = (t[1:] - t[:-1]).norm(dim=-1)
    apart = torch.ones_like(steps) if frames_apart is None else torch.tensor(frames_apart, dtype=torch.float64, device="cpu")
    far = (steps > MAX_ROAD_SPEED * MAX_FRAME_INTERVAL * apart.clamp_min(1)).nonzero().flatten()
    if far.numel():
        i = int(far[0])
        a, b = (labels[k] if labels is not None else f"pose {k}" for k in (i, i + 1))
        seconds = MAX_FRAME_INTERVAL * max(float(apart[i]), 1.0)
        raise ValueError(f"{name}: {a} and {b} lie {float(steps[i]):.4g} m apart, farther than a road vehicle "
                         f"travels between them ({MAX_ROAD_SPEED * seconds:g} m: {MAX_ROAD_SPEED:g} m/s for "
                         f"{seconds:g} s, video at one frame a second or more); are the poses in millimetres? "
                         f"Poses are in metres (as KITTI's)")


def check_motion_step(params: dict[str, Tensor], name: str = "odometry") -> None:
    """Raise a ValueError naming ``name`` and the sample where a motion of one frame is no road
    vehicle's: a translation (the norm of its ``x_d``, ``y_d``, ``z_d`` among ``params``, (B,)
    tensors, metres) longer than a road vehicle travels between two frames of a video (100 m, as
    :func:`check_pose_steps`: odometry in millimetres), or a ``yaw`` of half a turn or more
    (|yaw| >= π: no turn between two frames, which the yaw of a pose, an angle in (−π, π], cannot
    tell apart from a smaller one; most likely degrees). Either would leave the road's flow
    undefined in most of the image, or wrong, with at most a generic warning. Not read while
    tracing or on the meta device; a motion without a translation or yaw (a homography) passes."""
    steps = [params[k] for k in ("x_d", "y_d", "z_d") if k in params]
    yaw = params.get("yaw")
    if not (steps or yaw is not None) or skip_values(*steps, yaw):
        return
    with torch.no_grad():
        # (float64 before the stack: autocast's stack refuses a half dtype other than its own)
        norm = torch.stack([s.to(torch.float64) for s in torch.broadcast_tensors(*steps)]).norm(dim=0).reshape(-1) \
            if steps else torch.zeros(1, dtype=torch.float64, device=yaw.device)
        turn = torch.zeros(1, dtype=torch.float64, device=steps[0].device) if yaw is None else yaw.detach().to(torch.float64).abs().reshape(-1)
        far, wraps = norm > MAX_ROAD_SPEED * MAX_FRAME_INTERVAL, ~(turn < torch.pi)  # (NaN: checked before)
        if not bool(far.any() | wraps.any()):
            return
    if not bool(far.any()):
        i = int(wraps.nonzero()[0])
        raise ValueError(f"{name}: sample {i} turns by {float(yaw.reshape(-1)[i if yaw.numel() > 1 else 0]):.4g} rad "
                         f"in a frame, half a turn or more (|yaw| >= π); in degrees? The yaw is in radians")
    i = int(far.nonzero()[0])
    given = ", ".join(f"{k} {float(params[k].reshape(-1)[i if params[k].numel() > 1 else 0]):.4g}"
                      for k in ("x_d", "y_d", "z_d") if k in params)
    raise ValueError(f"{name}: sample {i} moves {float(norm[i]):.4g} m in a frame ({given}), farther than a road "
                     f"vehicle travels between two frames ({MAX_ROAD_SPEED * MAX_FRAME_INTERVAL:g} m: "
                     f"{MAX_ROAD_SPEED:g} m/s for {MAX_FRAME_INTERVAL:g} s); in millimetres? {name} is the motion "
                     f"over the frame interval in metres")
