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

from .._check import (
    as_batch_param,
    check_all_finite,
    check_positive,
    check_size,
    resolve_batch,
    result_dtype,
    tracing,
)
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
    given = [as_batch_param(v, n, finite=False) for n, v in named.items() if isinstance(v, Tensor)]
    dtype = result_dtype(camera.K, *given)
    # Python floats are converted straight to the common dtype (no float32 round trip).
    tensors = {n: as_batch_param(v, n, dtype, camera.device, finite=False) for n, v in named.items()}
    check_all_finite(tensors)
    B = resolve_batch({"camera": camera.batch_size, **{n: t.shape[0] for n, t in tensors.items()}})
    if camera.dtype != dtype:
        camera = camera.to(dtype)
    if camera.batch_size != B:
        camera = camera.expand(B)
    # every parameter to (B,): the 3×3 maps are built with torch.stack, which does not broadcast
    tensors = {n: t.expand(B) for n, t in tensors.items()}
    return camera, tensors, B


def _vehicle_ray_row(camera: Camera, Rc: Tensor, K_inv: Tensor | None = None) -> Tensor:
    """The row a (B, 1, 3) with ``a · p̃`` = y component of the pixel's vehicle-frame ray.

    The ray meets the road in front of the camera iff this is > 0 (λ1 > 0 of the paper).
    """
    K_inv = camera.K_inv() if K_inv is None else K_inv
    return Rc[:, :, 1:2].transpose(-1, -2) @ K_inv  # row 1 of R_cᵀ K⁻¹


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


def _homography(camera: Camera, Rc: Tensor, x_d: Tensor, z_d: Tensor, yaw: Tensor,
                K_inv: Tensor | None = None) -> Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    h = camera.height
    z, o = torch.zeros_like(c), torch.ones_like(c)
    # R_φ (I - d nᵀ / h): only the middle column changes, by -R_φ d / h.
    a = x_d / h
    b = z_d / h
    inner = torch.stack([c, -(c * a - s * b), -s,
                         z, o, z,
                         s, -(s * a + c * b), c], dim=-1).reshape(-1, 3, 3)
    K_inv = camera.K_inv() if K_inv is None else K_inv
    return camera.K @ Rc @ inner @ Rc.transpose(-1, -2) @ K_inv


def road_velocity_matrix(camera: Camera, speed: Tensor | float, steering: Tensor | float,
                         wheelbase: Tensor | float) -> Tensor:
    """G (B, 3, 3), the time derivative of the road homography at Δt = 0 (units 1/s)."""
    camera, p, B = _params(camera, {"speed": speed, "steering": steering, "wheelbase": wheelbase})
    _check_velocity_values(p["steering"], p["wheelbase"])
    return _velocity_matrix(camera, camera.mounting(), p["speed"], p["steering"], p["wheelbase"])


def _velocity_matrix(camera: Camera, Rc: Tensor, speed: Tensor, steering: Tensor,
                     wheelbase: Tensor, K_inv: Tensor | None = None) -> Tensor:
    yaw_rate = speed * torch.tan(steering) / wheelbase
    z = torch.zeros_like(yaw_rate)
    # dR_φ/dt - ḋ nᵀ / h with ḋ = (0, 0, v_r)
    inner = torch.stack([z, z, -yaw_rate,
                         z, z, z,
                         yaw_rate, -speed / camera.height, z], dim=-1).reshape(-1, 3, 3)
    K_inv = camera.K_inv() if K_inv is None else K_inv
    return camera.K @ Rc @ inner @ Rc.transpose(-1, -2) @ K_inv


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
    Rc, K_inv = camera.mounting(), camera.K_inv()
    Hmat = _homography(camera, Rc, p["x_d"], p["z_d"], p["yaw"], K_inv)
    return _flow_from_matrix(Hmat, _vehicle_ray_row(camera, Rc, K_inv), size, B, velocity=False)


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
    Rc, K_inv = camera.mounting(), camera.K_inv()
    G = _velocity_matrix(camera, Rc, p["speed"], p["steering"], p["wheelbase"], K_inv)
    return _flow_from_matrix(G, _vehicle_ray_row(camera, Rc, K_inv), size, B, velocity=True)


def _flow_from_matrix(M: Tensor, ray_row: Tensor, size: tuple[int, int], B: int,
                      velocity: bool) -> tuple[Tensor, Tensor]:
    """Evaluate a per-frame 3×3 map M on the pixel grid as row terms plus column terms.

    ``q = M p̃`` is separable: ``q_k(u, v) = M[k,0] u + (M[k,1] v + M[k,2])``, so each per-pixel
    quantity is an outer sum (or outer product) of an (H,) and a (W,) vector: no (3, H*W) grid,
    no k=3 matmul (slow), no eager boolean ``torch.where`` (slow on CPU). The flow numerator
    ``q_xy - p q_z`` (p = (u, v)) is, per channel, ``a[v] + b[u] - l[v] r[u]``:

        x: (q_x v-terms) + (q_x u-terms - u q_z u-terms) - (q_z v-terms) u
        y: (q_y v-terms - v q_z v-terms) + (q_y u-terms) - v (q_z u-terms)

    Displacement: ``flow = num / q_z`` where valid; velocity: ``flow = num``. Elsewhere the flow
    is exactly 0, with a denominator that cannot be 0, so neither the value nor the gradient can
    be inf or NaN. Three spellings of the same arithmetic, each the fastest where it runs:
    compiled (selects, fused by inductor), eager with autograd (0/1 float masks), eager without
    autograd (the same, in place).
    """
    H, W = size
    dtype, device = M.dtype, M.device
    M = M.expand(B, 3, 3)
    a = ray_row.expand(B, 1, 3)[:, 0].detach()  # only its sign is used
    u = torch.arange(W, dtype=dtype, device=device)
    v = torch.arange(H, dtype=dtype, device=device)
    col = M[:, :, 0:1] * u                  # (B, 3, W): the u-terms of q
    row = M[:, :, 1:2] * v + M[:, :, 2:3]   # (B, 3, H): the v-terms and constants of q
    a_v = torch.stack([row[:, 0], row[:, 1] - v * row[:, 2]], dim=1)         # (B, 2, H)
    b_u = torch.stack([col[:, 0] - u * col[:, 2], col[:, 1]], dim=1)         # (B, 2, W)
    l_v = torch.stack([row[:, 2], v.expand(B, H)], dim=1)                    # (B, 2, H)
    r_u = torch.stack([u.expand(B, W), col[:, 2]], dim=1)                    # (B, 2, W)
    tiny = torch.finfo(dtype).tiny
    if tracing() or M.requires_grad:
        num = (a_v.unsqueeze(-1) + b_u.unsqueeze(-2)).addcmul_(l_v.unsqueeze(-1), r_u.unsqueeze(-2),
                                                              value=-1.0)    # (B, 2, H, W)
        # y component of the pixel's vehicle-frame ray: > 0 below the horizon (λ1 > 0)
        ray_y = (a[:, 1:2] * v + a[:, 2:3]).unsqueeze(-1) + (a[:, 0:1] * u).unsqueeze(-2)  # (B, H, W)
        qz = None if velocity else row[:, 2].unsqueeze(-1) + col[:, 2].unsqueeze(-2)  # (B, H, W)
    if tracing():
        # Compiled: inductor turns the select into a vector blend, all in one loop over the flow.
        # The condition is used once (a bool used twice would be stored, slowly); the clamped
        # denominator keeps the unused branch and its gradient finite.
        edge = ray_y if velocity else torch.minimum(ray_y, qz.detach())  # valid: both > 0
        cond = (edge > 0).unsqueeze(1)
        valid = _valid_mask(a, row, col, u, v, velocity)
        if velocity:
            return torch.where(cond, num, 0.0), valid
        return torch.where(cond, num / qz.clamp_min(tiny).unsqueeze(1), 0.0), valid
    if M.requires_grad:
        # Eager with autograd: a 0/1 float mask instead of a select (eager CPU selects are slow).
        # sign(.) is 1 on the valid side, 0 or -1 elsewhere: clamped, a 0/1 mask.
        edge = ray_y if velocity else torch.minimum(ray_y, qz.detach())
        mask = torch.sign(edge).clamp_min(0).unsqueeze(1)
        if velocity:
            return num * mask, mask.bool()
        # 1 / q_z on valid pixels, 0 elsewhere (also where q_z = 0); the backward pass never
        # divides 0 by 0 because the clamped denominator is positive.
        return num * (mask / qz.clamp_min(tiny).unsqueeze(1)), mask.bool()
    # Eager without autograd: the same arithmetic in place, frame by frame, with q_z kept in the
    # output's first plane until it is needed there: one (H, W) temporary in all, which stays in
    # cache. Each fresh full-size tensor costs page faults on CPU, often more than the arithmetic.
    flow = torch.empty(B, 2, H, W, dtype=dtype, device=device)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=device)
    ray_v, ray_u = a[:, 1:2] * v + a[:, 2:3], a[:, 0:1] * u
    for b in range(B):
        f = flow[b:b + 1]
        edge = ray_v[b:b + 1].unsqueeze(-1) + ray_u[b:b + 1].unsqueeze(-2)  # the one temporary
        if not velocity:
            qz = torch.add(row[b:b + 1, 2].unsqueeze(-1), col[b:b + 1, 2].unsqueeze(-2), out=f[:, 0])
            torch.minimum(edge, qz, out=edge)
        mask = edge.sign_().clamp_min_(0).unsqueeze(1)
        valid[b:b + 1].copy_(mask)
        if not velocity:
            mask.div_(qz.clamp_min_(tiny).unsqueeze(1))  # now 1 / q_z or 0; q_z's plane is free
        torch.add(a_v[b:b + 1].unsqueeze(-1), b_u[b:b + 1].unsqueeze(-2), out=f)
        f.addcmul_(l_v[b:b + 1].unsqueeze(-1), r_u[b:b + 1].unsqueeze(-2), value=-1.0).mul_(mask)
    return flow, valid


def _valid_mask(a: Tensor, row: Tensor, col: Tensor, u: Tensor, v: Tensor, velocity: bool) -> Tensor:
    """``valid`` (B, 1, H, W) bool for compiled and exported graphs, built to compile cheaply.

    The same sign test as the flow's select (bit for bit: IEEE addition commutes), spelled
    differently (column term first, ceil of a clamp) so that inductor does not merge the two and
    keep a full-size mask in memory for both: recomputing it from the (H,) and (W,) terms is
    cheaper than the round trip. The last step, uint8 to bool, is an opaque custom op running the
    eager cast: inductor's CPU code for any bool result (a comparison, a cast, a bit cast) is an
    element-by-element loop that costs more than the whole flow (torch 2.13).
    """
    edge = (a[:, 0:1] * u).unsqueeze(-2) + (a[:, 1:2] * v + a[:, 2:3]).unsqueeze(-1)
    if not velocity:
        qz = col[:, 2].detach().unsqueeze(-2) + row[:, 2].detach().unsqueeze(-1)
        edge = torch.minimum(qz, edge)
    # ceil(clamp(x, 0, 1)) is 1 for x > 0 and 0 (or -0) for x <= 0
    return _uint8_to_bool(edge.clamp(0, 1).ceil().to(torch.uint8).unsqueeze(1))


@torch.library.custom_op("fsof_torch::uint8_to_bool", mutates_args=())
def _uint8_to_bool(mask: Tensor) -> Tensor:
    """``mask != 0`` as a new bool tensor (the eager cast, vectorised)."""
    return mask.bool()


@_uint8_to_bool.register_fake
def _(mask: Tensor) -> Tensor:
    return torch.empty_like(mask, dtype=torch.bool)


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
