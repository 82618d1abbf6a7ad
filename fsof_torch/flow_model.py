"""The freespace flow models of the paper: displacement (eq. 13) and velocity (eq. 21).

Both are evaluated through the plane-induced homography of the road (DESIGN.md §3), not
per-pixel trigonometry: for the displacement model every road pixel moves by

    H = K R_c R_φ (I - d nᵀ / h) R_cᵀ K⁻¹,   n = (0, 1, 0)ᵀ,  d = (x_d, 0, z_d)ᵀ,
    f_d(p) = π(H p̃) - p,

and the velocity model is the time derivative of that map at Δt = 0 (with ḋ = (0, 0, v_r),
φ̇ = v_r tan δ_f / l):

    G = K R_c (Ω - ḋ nᵀ / h) R_cᵀ K⁻¹,   g = G p̃,   f_v(p) = (g_x - u g_z, g_y - v g_z).

R_c = R_θ R_β is the camera mounting (roll θ, pitch β; β = 0 is the paper).

Convention: pixel (u, v) with origin at the centre of the top-left pixel; flow channel 0 is u,
channel 1 is v; forward flow from frame t to t+1; displacement flow in pixels, velocity flow in
pixels per second. ``valid`` is True where the model is defined: the pixel's viewing ray meets
the road in front of the camera (below the horizon) and, for the displacement model, the road
point is in front of the camera at t+1. Elsewhere the flow is 0 (never NaN or inf) and gradients
are finite.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ._check import as_batch_param, check_positive, check_size, resolve_batch, result_dtype, tracing
from .camera import Camera

__all__ = [
    "road_homography",
    "road_velocity_matrix",
    "displacement_flow",
    "velocity_flow",
    "DisplacementFlow",
    "VelocityFlow",
    "displacement_flow_straight",
    "displacement_flow_straight_level",
    "velocity_flow_straight",
    "velocity_flow_straight_level",
    "vflow_curve",
    "pixel_grid",
]


def pixel_grid(size: tuple[int, int], dtype: torch.dtype, device: torch.device | None = None) -> Tensor:
    """Homogeneous pixel coordinates (3, H*W): rows u, v, 1, row-major over the image."""
    H, W = size
    u = torch.arange(W, dtype=dtype, device=device).expand(H, W)
    v = torch.arange(H, dtype=dtype, device=device).unsqueeze(1).expand(H, W)
    return torch.stack([u, v, torch.ones_like(u)]).reshape(3, H * W)


def _params(camera: Camera, named: dict[str, object]) -> tuple[Camera, dict[str, Tensor], int]:
    """Validate per-frame parameters, resolve the batch size and the common dtype."""
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    given = [as_batch_param(v, n) for n, v in named.items() if isinstance(v, Tensor)]
    dtype = result_dtype(camera.K, *given)
    # Python floats are converted straight to the common dtype (no float32 round trip).
    tensors = {n: as_batch_param(v, n, dtype, camera.device) for n, v in named.items()}
    B = resolve_batch({"camera": camera.batch_size, **{n: t.shape[0] for n, t in tensors.items()}})
    if camera.dtype != dtype:
        camera = camera.to(dtype)
    return camera, tensors, B


def _vehicle_ray_row(camera: Camera, Rc: Tensor) -> Tensor:
    """The row a (B, 1, 3) with ``a · p̃`` = y component of the pixel's vehicle-frame ray.

    The ray meets the road in front of the camera iff this is > 0 (λ1 > 0 of the paper).
    """
    return (Rc.transpose(-1, -2) @ camera.K_inv())[:, 1:2, :]


def road_homography(camera: Camera, x_d: Tensor | float, z_d: Tensor | float,
                    yaw: Tensor | float) -> Tensor:
    """The road-plane homography H (B, 3, 3) mapping pixels of frame t to frame t+1.

    Args:
        camera: intrinsics and mounting, batch 1 or B.
        x_d, z_d: ego translation in metres in the vehicle frame of time t (right, forward).
        yaw: rotation φ about the vehicle's y axis in radians (positive turns toward +x).
    """
    camera, p, B = _params(camera, {"x_d": x_d, "z_d": z_d, "yaw": yaw})
    return _homography(camera, camera.mounting(), p["x_d"], p["z_d"], p["yaw"])


def _homography(camera: Camera, Rc: Tensor, x_d: Tensor, z_d: Tensor, yaw: Tensor) -> Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    h = camera.height
    z, o = torch.zeros_like(c), torch.ones_like(c)
    # R_φ (I - d nᵀ / h): only the middle column changes, by -R_φ d / h.
    a = x_d / h
    b = z_d / h
    inner = torch.stack([c, -(c * a - s * b), -s,
                         z, o, z,
                         s, -(s * a + c * b), c], dim=-1).reshape(-1, 3, 3)
    return camera.K @ Rc @ inner @ Rc.transpose(-1, -2) @ camera.K_inv()


def road_velocity_matrix(camera: Camera, speed: Tensor | float, steering: Tensor | float,
                         wheelbase: Tensor | float) -> Tensor:
    """G (B, 3, 3), the time derivative of the road homography at Δt = 0 (units 1/s)."""
    camera, p, B = _params(camera, {"speed": speed, "steering": steering, "wheelbase": wheelbase})
    _check_velocity_values(p["steering"], p["wheelbase"])
    return _velocity_matrix(camera, camera.mounting(), p["speed"], p["steering"], p["wheelbase"])


def _velocity_matrix(camera: Camera, Rc: Tensor, speed: Tensor, steering: Tensor,
                     wheelbase: Tensor) -> Tensor:
    yaw_rate = speed * torch.tan(steering) / wheelbase
    z = torch.zeros_like(yaw_rate)
    # dR_φ/dt - ḋ nᵀ / h with ḋ = (0, 0, v_r)
    inner = torch.stack([z, z, -yaw_rate,
                         z, z, z,
                         yaw_rate, -speed / camera.height, z], dim=-1).reshape(-1, 3, 3)
    return camera.K @ Rc @ inner @ Rc.transpose(-1, -2) @ camera.K_inv()


def _check_velocity_values(steering: Tensor, wheelbase: Tensor) -> None:
    check_positive(wheelbase, "wheelbase")
    if not tracing() and not bool((steering.abs() < torch.pi / 2).all()):
        raise ValueError(f"steering: expected |δ_f| < π/2 rad, got {steering.tolist()}")


def displacement_flow(camera: Camera, x_d: Tensor | float, z_d: Tensor | float,
                      yaw: Tensor | float, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Road flow of the displacement model (paper eq. 13, with the pitch extension).

    Args:
        camera: intrinsics and mounting (batch 1 or B).
        x_d: lateral ego translation in metres (vehicle frame of time t, positive right), float or (B,).
        z_d: forward ego translation in metres, float or (B,).
        yaw: ego rotation φ in radians about the vehicle's y axis, float or (B,).
        size: ``(H, W)`` of the flow, the resolution K refers to.

    Returns:
        ``flow`` (B, 2, H, W) in pixels (channel 0 = u) and ``valid`` (B, 1, H, W) bool.

    Example:
        >>> cam = Camera(torch.tensor([[700., 0, 600], [0, 700, 180], [0, 0, 1]]), 1.65)
        >>> flow, valid = displacement_flow(cam, 0.0, 1.2, 0.0, (370, 1226))
        >>> flow.shape, bool(valid[0, 0, -1, 600])
        (torch.Size([1, 2, 370, 1226]), True)
    """
    size = check_size(size)
    camera, p, B = _params(camera, {"x_d": x_d, "z_d": z_d, "yaw": yaw})
    Rc = camera.mounting()
    Hmat = _homography(camera, Rc, p["x_d"], p["z_d"], p["yaw"])
    return _flow_from_matrix(Hmat, _vehicle_ray_row(camera, Rc), size, B, velocity=False)


def velocity_flow(camera: Camera, speed: Tensor | float, steering: Tensor | float,
                  wheelbase: Tensor | float, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Road flow of the velocity model (paper eq. 21, with the pitch extension), px/s.

    Args:
        camera: intrinsics and mounting (batch 1 or B).
        speed: rear-axle speed v_r in m/s, float or (B,).
        steering: front-wheel steering angle δ_f in radians (|δ_f| < π/2), float or (B,).
        wheelbase: axle distance l in metres (> 0), float or (B,).
        size: ``(H, W)`` of the flow.

    Returns:
        ``flow`` (B, 2, H, W) in pixels per second and ``valid`` (B, 1, H, W) bool (below the horizon).
    """
    size = check_size(size)
    camera, p, B = _params(camera, {"speed": speed, "steering": steering, "wheelbase": wheelbase})
    _check_velocity_values(p["steering"], p["wheelbase"])
    Rc = camera.mounting()
    G = _velocity_matrix(camera, Rc, p["speed"], p["steering"], p["wheelbase"])
    return _flow_from_matrix(G, _vehicle_ray_row(camera, Rc), size, B, velocity=True)


def _flow_from_matrix(M: Tensor, ray_row: Tensor, size: tuple[int, int], B: int,
                      velocity: bool) -> tuple[Tensor, Tensor]:
    """Evaluate a per-frame 3×3 map on the pixel grid (one batched matmul, then a few passes)."""
    H, W = size
    grid = pixel_grid(size, M.dtype, M.device)
    rows = torch.cat([M, ray_row], dim=1).expand(B, 4, 3)
    q = rows @ grid  # (B, 4, H*W): q_x, q_y, q_z, ray_y
    xy, qz, ray_y = q[:, :2], q[:, 2:3], q[:, 3:4]
    if velocity:
        valid = ray_y > 0
        flow = xy - grid[:2] * qz
    else:
        valid = (ray_y > 0) & (qz > 0)
        flow = xy / torch.where(valid, qz, torch.ones_like(qz)) - grid[:2]
    flow = torch.where(valid, flow, torch.zeros_like(flow))
    return flow.reshape(B, 2, H, W), valid.reshape(B, 1, H, W)


class DisplacementFlow(nn.Module):
    """``nn.Module`` twin of :func:`displacement_flow` for a fixed output size.

    Example:
        >>> model = DisplacementFlow((375, 1242))
        >>> cam = Camera(torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), 1.65)
        >>> flow, valid = model(cam, 0.0, 1.0, 0.01)
    """

    def __init__(self, size: tuple[int, int]) -> None:
        super().__init__()
        self.size = check_size(size)

    def forward(self, camera: Camera, x_d: Tensor | float, z_d: Tensor | float,
                yaw: Tensor | float) -> tuple[Tensor, Tensor]:
        return displacement_flow(camera, x_d, z_d, yaw, self.size)

    def extra_repr(self) -> str:
        return f"size={self.size}"


class VelocityFlow(nn.Module):
    """``nn.Module`` twin of :func:`velocity_flow` for a fixed output size and wheelbase."""

    def __init__(self, size: tuple[int, int], wheelbase: float = 2.7) -> None:
        super().__init__()
        self.size = check_size(size)
        if not (float(wheelbase) > 0):
            raise ValueError(f"wheelbase: expected > 0 metres, got {wheelbase!r}")
        self.wheelbase = float(wheelbase)

    def forward(self, camera: Camera, speed: Tensor | float,
                steering: Tensor | float) -> tuple[Tensor, Tensor]:
        return velocity_flow(camera, speed, steering, self.wheelbase, self.size)

    def extra_repr(self) -> str:
        return f"size={self.size}, wheelbase={self.wheelbase}"


# -- the special cases of the paper (eq. 22-24) ------------------------------------------------

def _centred(camera: Camera, size: tuple[int, int], dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """(u - u_0, v - v_0), each (B, 1, H, W)."""
    H, W = size
    u = torch.arange(W, dtype=dtype, device=camera.device).reshape(1, 1, 1, W)
    v = torch.arange(H, dtype=dtype, device=camera.device).reshape(1, 1, H, 1)
    du = (u - camera.cx.reshape(-1, 1, 1, 1)).expand(-1, 1, H, W)
    dv = (v - camera.cy.reshape(-1, 1, 1, 1)).expand(-1, 1, H, W)
    return du, dv


def _lambda1(camera: Camera, du: Tensor, dv: Tensor) -> Tensor:
    st = torch.sin(camera.roll).reshape(-1, 1, 1, 1)
    ct = torch.cos(camera.roll).reshape(-1, 1, 1, 1)
    return du / camera.fx.reshape(-1, 1, 1, 1) * st + dv / camera.fy.reshape(-1, 1, 1, 1) * ct


def _radial(scale: Tensor, valid: Tensor, du: Tensor, dv: Tensor) -> tuple[Tensor, Tensor]:
    scale = torch.where(valid, scale, torch.zeros_like(scale))
    return torch.cat([scale * du, scale * dv], dim=1), valid


def displacement_flow_straight(camera: Camera, z_d: Tensor | float,
                               size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 22: straight motion (φ = 0, x_d = 0) with roll; the camera's pitch is ignored.

    ``f_d = λ1 / (h / z_d - λ1) · (u - u_0, v - v_0)``.
    """
    size = check_size(size)
    camera, p, B = _params(camera, {"z_d": z_d})
    du, dv = _centred(camera, size, camera.dtype)
    lam1 = _lambda1(camera, du, dv)
    zd = p["z_d"].reshape(-1, 1, 1, 1)
    h = camera.height.reshape(-1, 1, 1, 1)
    den = h - lam1 * zd  # = (h / z_d - λ1) z_d, sign-safe for z_d -> 0
    valid = (lam1 > 0) & (den > 0)
    scale = lam1 * zd / torch.where(valid, den, torch.ones_like(den))
    return _radial(scale.expand(B, 1, *size), valid.expand(B, 1, *size), du.expand(B, 1, *size),
                   dv.expand(B, 1, *size))


def displacement_flow_straight_level(camera: Camera, z_d: Tensor | float,
                                     size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 24 (displacement): straight motion and no roll (the camera's roll and pitch are
    ignored): ``f_d = z_d / (h f_y / (v - v_0) - z_d) · (u - u_0, v - v_0)``."""
    size = check_size(size)
    camera, p, B = _params(camera, {"z_d": z_d})
    du, dv = _centred(camera, size, camera.dtype)
    zd = p["z_d"].reshape(-1, 1, 1, 1)
    hf = (camera.height * camera.fy).reshape(-1, 1, 1, 1)
    den = hf - zd * dv  # = (h f_y / (v - v0) - z_d)(v - v0)
    valid = (dv > 0) & (den > 0)
    scale = zd * dv / torch.where(valid, den, torch.ones_like(den))
    return _radial(scale.expand(B, 1, *size), valid.expand(B, 1, *size), du.expand(B, 1, *size),
                   dv.expand(B, 1, *size))


def velocity_flow_straight(camera: Camera, speed: Tensor | float,
                           size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 23: straight motion (δ_f = 0) with roll: ``f_v = v_r λ1 / h · (u - u_0, v - v_0)``."""
    size = check_size(size)
    camera, p, B = _params(camera, {"speed": speed})
    du, dv = _centred(camera, size, camera.dtype)
    lam1 = _lambda1(camera, du, dv)
    valid = lam1 > 0
    scale = p["speed"].reshape(-1, 1, 1, 1) * lam1 / camera.height.reshape(-1, 1, 1, 1)
    return _radial(scale.expand(B, 1, *size), valid.expand(B, 1, *size), du.expand(B, 1, *size),
                   dv.expand(B, 1, *size))


def velocity_flow_straight_level(camera: Camera, speed: Tensor | float,
                                 size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 24 (velocity): ``f_v = v_r (v - v_0) / (h f_y) · (u - u_0, v - v_0)``, no roll."""
    size = check_size(size)
    camera, p, B = _params(camera, {"speed": speed})
    du, dv = _centred(camera, size, camera.dtype)
    valid = dv > 0
    scale = p["speed"].reshape(-1, 1, 1, 1) * dv / (camera.height * camera.fy).reshape(-1, 1, 1, 1)
    return _radial(scale.expand(B, 1, *size), valid.expand(B, 1, *size), du.expand(B, 1, *size),
                   dv.expand(B, 1, *size))


def vflow_curve(v: Tensor, z_d: Tensor | float, height: Tensor | float, fy: Tensor | float,
                cy: Tensor | float) -> Tensor:
    """The vertical road flow of eq. 24 as a function of the row: ``F_v(v) = z_d (v-v_0)² / (h f_y - z_d (v-v_0))``.

    This is the curve the V-flow analysis fits. Rows at or above the horizon (v ≤ v_0), or where
    the road point is behind the camera at t+1, give 0. Broadcasts like ordinary tensor arithmetic.
    """
    dv = v - cy
    den = height * fy - z_d * dv
    ok = (dv > 0) & (den > 0)
    out = z_d * dv * dv / torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, out, torch.zeros_like(out))
