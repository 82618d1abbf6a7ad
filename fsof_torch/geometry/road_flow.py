"""The road's flow under a road-motion model: the paper's displacement (eq. 13) and velocity
(eq. 21) models, and any model of :mod:`fsof_torch.geometry.road_models`.

Every model gives a 3×3 map per frame (:func:`~fsof_torch.geometry.road_models.road_homography`);
this module evaluates it on the pixel grid:

    homography H:        f(p) = π(H p̃) - p                    (pixels per frame)
    time derivative G:   f(p) = (g_x - u g_z, g_y - v g_z),  g = G p̃   (pixels per second)

Convention: pixel (u, v) with origin at the centre of the top-left pixel; flow channel 0 is u,
channel 1 is v; forward flow from frame t to t+1. ``valid`` is True where the model is defined:
the pixel's viewing ray meets the road in front of the camera (below the horizon) and, for a
homography, the road point is in front of the camera at t+1. Elsewhere the flow is 0 (never NaN
or inf) and gradients are finite. Geometry runs in at least float32, also under
``torch.autocast``.
"""

from __future__ import annotations

from typing import Mapping

import torch
from torch import Tensor, nn

from .._check import (
    autocast_off,
    as_batch_param,
    batch_choices,
    check_all_finite,
    check_bool,
    check_device,
    check_float_tensor,
    check_number,
    check_positive,
    check_shape,
    check_size,
    host_path,
    resolve_batch,
    result_dtype,
    tracing,
)
from .camera import Camera, check_camera
from .road_models import RoadModel, get_road_model, pack_params

__all__ = [
    "road_flow",
    "flow_from_map",
    "displacement_flow",
    "velocity_flow",
    "road_velocity_matrix",
    "DisplacementFlow",
    "VelocityFlow",
    "RoadFlow",
    "displacement_flow_straight",
    "displacement_flow_straight_level",
    "velocity_flow_straight",
    "velocity_flow_straight_level",
    "vflow_curve",
    "curve_arguments",
    "pixel_grid",
]


def pixel_grid(size: tuple[int, int], dtype: torch.dtype, device: torch.device | None = None) -> Tensor:
    """Homogeneous pixel coordinates (3, H*W): rows u, v, 1, row-major over the image.

    ``size``: ``(H, W)`` positive ints; ``dtype``: a floating-point dtype, half precision lifted
    to float32 as in the rest of the geometry (bfloat16 holds whole numbers exactly only up to
    256, float16 up to 2048: a bfloat16 grid of a KITTI frame put columns 1237 to 1241 all at 1240);
    ``device``: None (the default device), a ``torch.device``, a device string or index torch can
    place tensors on (else a ValueError or TypeError naming it: :func:`~fsof_torch.devices.check_device`)."""
    H, W = check_size(size)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating-point torch.dtype, got {dtype!r}")
    device = check_device(device)
    if dtype in (torch.float16, torch.bfloat16):
        dtype = torch.float32
    u = torch.arange(W, dtype=dtype, device=device).expand(H, W)
    v = torch.arange(H, dtype=dtype, device=device).unsqueeze(1).expand(H, W)
    return torch.stack([u, v, torch.ones_like(u)]).reshape(3, H * W)


def road_flow(camera: Camera, params: Mapping[str, Tensor | float] | None, size: tuple[int, int], *,
              model: str | RoadModel = "paper") -> tuple[Tensor, Tensor]:
    """The road's flow under any road-motion model.

    Args:
        camera: intrinsics (K at the flow's resolution), height and mounting; batch 1 or B.
        params: the model's named parameters, floats or (B,) tensors (names and units:
            :data:`~fsof_torch.geometry.road_models.ROAD_MODELS`); missing motion parameters are 0,
            missing roll / pitch the camera's.
        size: ``(H, W)`` of the flow.
        model: ``"paper"``, ``"plane"``, ``"homography"`` (pixels per frame) or ``"velocity"``
            (pixels per second).

    Returns:
        ``flow`` (B, 2, H, W) and ``valid`` (B, 1, H, W) bool, in the common dtype of the camera
        and the parameters (at least float32).

    Example:
        >>> cam = Camera(torch.tensor([[700., 0, 600], [0, 700, 180], [0, 0, 1]]), 1.65)
        >>> flow, valid = road_flow(cam, {"z_d": 1.2, "pitch_change": 0.002}, (370, 1226), model="plane")
        >>> flow.shape
        torch.Size([1, 2, 370, 1226])
    """
    size = check_size(size)
    model = get_road_model(model)
    check_camera(camera)
    with autocast_off(camera.K):
        camera, values = pack_params(model, camera, params)
        # the map and the horizon row in one evaluation (one K⁻¹, the mounting's rotations once)
        M, _, horizon = model.evaluate(camera.K, camera.K_inv(), camera.height, values, False)
        _check_map(M, size, model, values)
        if horizon is None:
            horizon = model.horizon_row(camera, values)
        if tracing():
            # A graph reads no values: a frame whose map the eager call refuses (NaN, inf, or
            # overflowing at this size) gets the horizon row 0, nowhere below it, so its flow is 0
            # with ``valid`` all False; the velocity model's validity depends on the horizon
            # alone, and its graph gave a NaN flow marked valid.
            ok = (M.abs() <= _map_bound(M, size)).flatten(1).all(1)
            horizon = torch.where(ok.reshape(-1, 1, 1), horizon, 0.0)
        return flow_from_map(M, horizon, size, velocity=model.velocity)


def _map_bound(M: Tensor, size: tuple[int, int]) -> float:
    """The largest map entry whose flow cannot overflow M's dtype at this image size: per pixel
    the flow multiplies entries by coordinates up to H + W and adds a few such products, so
    entries up to finfo.max / (16 (1 + H + W)²)."""
    return torch.finfo(M.dtype).max / (16.0 * (1.0 + size[0] + size[1]) ** 2)


def _check_map(M: Tensor, size: tuple[int, int], model: RoadModel, values: Tensor) -> None:
    """Reject parameters whose map overflows the dtype at this image size (NaN flow otherwise;
    :func:`_map_bound`). Not while tracing (see :func:`road_flow`) nor on the meta device."""
    if tracing() or M.device.type == "meta":
        return
    bound = _map_bound(M, size)
    if not bool((M.abs() <= bound).all()):  # False for NaN as well
        bad = {n: values[:, i].tolist() for i, n in enumerate(model.params)}
        raise ValueError(f"{', '.join(model.params)}: the {model.name!r} road map overflows {M.dtype} at "
                         f"size {size} (entries beyond {bound:.3g}); got {bad}")


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
    return road_flow(camera, {"x_d": x_d, "z_d": z_d, "yaw": yaw}, size, model="paper")


def _yaw_rate(speed: Tensor | float, steering: Tensor | float, wheelbase: Tensor | float,
              camera: Camera) -> dict[str, Tensor]:
    """Speed and yaw rate φ̇ = v_r tan δ_f / l of the Ackermann model (no side slip)."""
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    named = {"speed": speed, "steering": steering, "wheelbase": wheelbase}
    dtype = result_dtype(camera.K, *[as_batch_param(v, n, finite=False) for n, v in named.items()
                                     if isinstance(v, Tensor)])
    p = {n: as_batch_param(v, n, dtype, camera.device) for n, v in named.items()}
    resolve_batch({"camera": camera.batch_size, **{n: t.shape[0] for n, t in p.items()}})
    check_positive(p["wheelbase"], "wheelbase")
    if not tracing() and p["steering"].device.type != "meta" and not bool((p["steering"].abs() < torch.pi / 2).all()):
        raise ValueError(f"steering: expected |δ_f| < π/2 rad, got {p['steering'].tolist()}")
    return {"speed": p["speed"], "yaw_rate": p["speed"] * torch.tan(p["steering"]) / p["wheelbase"]}


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
    return road_flow(camera, _yaw_rate(speed, steering, wheelbase, camera), size, model="velocity")


def road_velocity_matrix(camera: Camera, speed: Tensor | float, steering: Tensor | float,
                         wheelbase: Tensor | float) -> Tensor:
    """G (B, 3, 3), the time derivative of the road homography at Δt = 0 (1/s), for a speed
    (m/s), a steering angle (rad) and a wheelbase (m): the ``"velocity"`` model's map."""
    from .road_models import road_homography

    return road_homography(camera, _yaw_rate(speed, steering, wheelbase, camera), model="velocity")


def flow_from_map(M: Tensor, horizon: Tensor, size: tuple[int, int], *,
                  velocity: bool = False) -> tuple[Tensor, Tensor]:
    """Evaluate per-frame 3×3 maps on the pixel grid: the flow and where it is defined.

    Args:
        M: (B, 3, 3) float, a road homography (pixels of t -> t+1) or, with ``velocity``, its time
            derivative G (1/s).
        horizon: (B, 1, 3) or (1, 1, 3) float, the row a with ``a · p̃ > 0`` below the horizon
            (:meth:`~fsof_torch.geometry.road_models.RoadModel.horizon_row`); only its sign
            along the grid is used.
        size: ``(H, W)``, positive ints.

    Returns:
        ``flow`` (B, 2, H, W) in M's dtype, half precision lifted to float32 (pixels, or px/s
        with ``velocity``), 0 where not defined, and ``valid`` (B, 1, H, W) bool.

    Types and shapes are checked (errors name ``M``, ``horizon``, ``size``); the values are not
    (the maps come from the fits' loops, which this function must not slow with host reads): a
    NaN or inf entry of M gives NaN flow. :func:`road_flow` checks the parameters it builds M from.

    ``q = M p̃`` is separable: ``q_k(u, v) = M[k,0] u + (M[k,1] v + M[k,2])``, so each per-pixel
    quantity is an outer sum (or product) of an (H,) and a (W,) vector, and the flow numerator
    ``q_xy - p q_z`` is, per channel, ``a[v] + b[u] - l[v] r[u]``:

        x: (q_x v-terms) + (q_x u-terms - u q_z u-terms) - (q_z v-terms) u
        y: (q_y v-terms - v q_z v-terms) + (q_y u-terms) - v (q_z u-terms)

    Where not valid the flow is exactly 0 with a denominator that cannot be 0, so neither the
    value nor its gradient can be inf or NaN.
    """
    check_float_tensor(M, "M")
    check_float_tensor(horizon, "horizon")
    B = check_shape(M, "M", ("B", 3, 3), nonempty=("B",))["B"]
    if horizon.dim() != 3 or tuple(horizon.shape[1:]) != (1, 3) or horizon.shape[0] not in (1, B):
        raise ValueError(f"horizon: expected shape ({batch_choices(B)}, 1, 3) beside M of batch {B}, got "
                         f"{tuple(horizon.shape)}")
    H, W = check_size(size)
    check_bool(velocity, "velocity")
    M = M.to(result_dtype(M))  # (in float16 the flow was 2.5 px off on a KITTI frame)
    dtype, device = M.dtype, M.device
    a = horizon.expand(B, 1, 3)[:, 0].detach()  # only its sign is used
    u = torch.arange(W, dtype=dtype, device=device)
    v = torch.arange(H, dtype=dtype, device=device)
    col = M[:, :, 0:1] * u                  # (B, 3, W): the u-terms of q
    row = M[:, :, 1:2] * v + M[:, :, 2:3]   # (B, 3, H): the v-terms and constants of q
    a_v = torch.stack([row[:, 0], row[:, 1] - v * row[:, 2]], dim=1)         # (B, 2, H)
    b_u = torch.stack([col[:, 0] - u * col[:, 2], col[:, 1]], dim=1)         # (B, 2, W)
    l_v = torch.stack([row[:, 2], v.expand(B, H)], dim=1)                    # (B, 2, H)
    r_u = torch.stack([u.expand(B, W), col[:, 2]], dim=1)                    # (B, 2, W)
    if not tracing() and not M.requires_grad:
        # The fast path of inference (python benchmarks/bench_model.py, "flow_from_map in place"
        # against "general path": about 2x faster at 375x1242 and batch 1, 3x and more at 8).
        return _flow_in_place(a, row, col, u, v, a_v, b_u, l_v, r_u, velocity)
    num = (a_v.unsqueeze(-1) + b_u.unsqueeze(-2)) - l_v.unsqueeze(-1) * r_u.unsqueeze(-2)  # (B, 2, H, W)
    # y component of the pixel's road-aligned ray: > 0 below the horizon (λ1 > 0 of the paper)
    ray_y = (a[:, 1:2] * v + a[:, 2:3]).unsqueeze(-1) + (a[:, 0:1] * u).unsqueeze(-2)   # (B, H, W)
    if velocity:
        edge = ray_y
    else:
        qz = row[:, 2].unsqueeze(-1) + col[:, 2].unsqueeze(-2)                           # (B, H, W)
        edge = torch.minimum(ray_y, qz.detach())  # valid: both > 0
    tiny = torch.finfo(dtype).tiny
    if tracing():
        # Compiled: the condition is used once (a bool used twice would be stored, slowly); see
        # _valid_mask for the mask itself.
        cond = (edge > 0).unsqueeze(1)
        valid = _valid_mask(a, row, col, u, v, velocity)
    else:
        valid = (edge > 0).unsqueeze(1)
        cond = valid
    if velocity:
        return torch.where(cond, num, 0.0), valid
    return torch.where(cond, num / qz.clamp_min(tiny).unsqueeze(1), 0.0), valid


def _flow_in_place(a: Tensor, row: Tensor, col: Tensor, u: Tensor, v: Tensor, a_v: Tensor, b_u: Tensor,
                   l_v: Tensor, r_u: Tensor, velocity: bool) -> tuple[Tensor, Tensor]:
    """:func:`flow_from_map` without autograd: the same arithmetic in place, frame by frame,
    with q_z kept in the output's first plane until it is needed there: one (H, W) temporary in
    all, which stays in cache. Each fresh full-size tensor costs page faults on CPU, often more
    than the arithmetic.

    On the CPU only the rows that can hold a valid pixel are computed; the others are zeroed.
    Both tests of validity are linear in the row, so those rows are one band, found from each
    test's largest value along the row (one host read, free on the CPU; on other devices every
    row is computed). python benchmarks/bench_model.py, "flow_from_map in place" against "in
    place, every row": at 375×1242 with the KITTI camera 167 of the 375 rows lie above the
    horizon, and the band makes the path about a quarter faster at batch 1, a third at batch 8.
    """
    B, H, W = row.shape[0], v.shape[0], u.shape[0]
    tiny = torch.finfo(row.dtype).tiny
    flow = torch.empty(B, 2, H, W, dtype=row.dtype, device=row.device)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=row.device)
    ray_v, ray_u = a[:, 1:2] * v + a[:, 2:3], a[:, 0:1] * u
    bands = _valid_rows(ray_v, ray_u, None if velocity else row[:, 2], None if velocity else col[:, 2])
    for b in range(B):
        top, end = bands[b] if bands is not None else (0, H)
        if top > 0 or end < H:
            flow[b, :, :top].zero_()
            flow[b, :, end:].zero_()
            valid[b, :, :top].zero_()
            valid[b, :, end:].zero_()
            if top >= end:
                continue
        rows = slice(top, end)
        f = flow[b:b + 1, :, rows]
        edge = ray_v[b:b + 1, rows].unsqueeze(-1) + ray_u[b:b + 1].unsqueeze(-2)  # the one temporary
        if not velocity:
            qz = torch.add(row[b:b + 1, 2, rows].unsqueeze(-1), col[b:b + 1, 2].unsqueeze(-2), out=f[:, 0])
            torch.minimum(edge, qz, out=edge)
        mask = edge.sign_().clamp_min_(0).unsqueeze(1)  # 1 on the valid side, else 0
        valid[b:b + 1, :, rows].copy_(mask)
        if not velocity:
            mask.div_(qz.clamp_min_(tiny).unsqueeze(1))  # now 1 / q_z or 0; q_z's plane is free
        torch.add(a_v[b:b + 1, :, rows].unsqueeze(-1), b_u[b:b + 1].unsqueeze(-2), out=f)
        f.addcmul_(l_v[b:b + 1, :, rows].unsqueeze(-1), r_u[b:b + 1].unsqueeze(-2), value=-1.0).mul_(mask)
    return flow, valid


def _valid_rows(ray_v: Tensor, ray_u: Tensor, qz_v: Tensor | None, qz_u: Tensor | None) -> list | None:
    """Per frame ``(top, end)``: rows outside ``top:end`` hold no valid pixel (a pixel is valid
    where ``ray_v[v] + ray_u[u] > 0`` and, unless None, ``qz_v[v] + qz_u[u] > 0``); None off the
    CPU. Each test's largest value along row v is its row term plus the largest column term
    (the same sum as the pixel's own at that column), so a row where it is not positive holds no
    valid pixel; both are linear in v, so the other rows form one band."""
    if not host_path(ray_v):
        return None
    rows = ray_v + ray_u.amax(-1, keepdim=True) > 0
    if qz_v is not None:
        rows &= qz_v + qz_u.amax(-1, keepdim=True) > 0
    H = rows.shape[-1]
    any_row = rows.any(-1)
    top = torch.where(any_row, rows.to(torch.uint8).argmax(-1), H)
    end = torch.where(any_row, H - rows.flip(-1).to(torch.uint8).argmax(-1), H)
    return torch.stack([top, end], dim=-1).tolist()


def _valid_mask(a: Tensor, row: Tensor, col: Tensor, u: Tensor, v: Tensor, velocity: bool) -> Tensor:
    """``valid`` (B, 1, H, W) bool for compiled and exported graphs, built to compile cheaply.

    The same sign test as the flow's select, spelled differently (column term first, ceil of a
    clamp) so that inductor does not merge the two and keep a full-size mask in memory for both.
    The last step, uint8 to bool, is an opaque custom op running the eager cast: inductor's CPU
    code for a bool result is an element-by-element loop that costs more than the whole flow
    (torch 2.13; python benchmarks/bench_model.py, "displacement_flow compiled" against "compiled,
    plain bool cast": about 3x faster with it).
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


class RoadFlow(nn.Module):
    """``nn.Module`` twin of :func:`road_flow` for one model and output size:
    ``forward(camera, params) -> (flow, valid)``."""

    def __init__(self, size: tuple[int, int], *, model: str = "paper") -> None:
        super().__init__()
        self.size = check_size(size)
        self.model = get_road_model(model).name

    def forward(self, camera: Camera, params: Mapping[str, Tensor | float] | None = None) -> tuple[Tensor, Tensor]:
        """``(flow (B, 2, H, W), valid (B, 1, H, W) bool)`` of the model for ``params``: :func:`road_flow`."""
        return road_flow(camera, params, self.size, model=self.model)

    def extra_repr(self) -> str:
        return f"size={self.size}, model={self.model!r}"


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
        """``(flow (B, 2, H, W) px, valid (B, 1, H, W) bool)`` for x_d, z_d (m) and yaw (rad): :func:`displacement_flow`."""
        return displacement_flow(camera, x_d, z_d, yaw, self.size)

    def extra_repr(self) -> str:
        return f"size={self.size}"


class VelocityFlow(nn.Module):
    """``nn.Module`` twin of :func:`velocity_flow` for a fixed output size and wheelbase.

    ``wheelbase`` (metres, finite, > 0) as :func:`velocity_flow` takes it: a float, or a (B,)
    tensor (then a buffer that moves with the module, not saved in its state dict). A cast of the
    module to half precision (``.half()``, ``.bfloat16()``, ``.to(dtype)``) leaves the wheelbase
    in its precision, as the geometry runs in at least float32 (``.double()`` widens it)."""

    def __init__(self, size: tuple[int, int], wheelbase: Tensor | float = 2.7) -> None:
        super().__init__()
        self.size = check_size(size)
        if isinstance(wheelbase, Tensor):
            wheelbase = as_batch_param(wheelbase, "wheelbase")
            check_positive(wheelbase, "wheelbase")
            self.register_buffer("wheelbase", wheelbase, persistent=False)
        else:
            self.wheelbase = check_number(wheelbase, "wheelbase", positive=True)

    def _apply(self, fn, recurse=True):  # (nn.Module's casts and moves go through here)
        before = self.wheelbase
        super()._apply(fn, recurse)
        after = self.wheelbase
        if isinstance(before, Tensor) and after.dtype in (torch.float16, torch.bfloat16) and after is not before:
            # (rounded to half precision, 2.7 m is 2.6992 or 2.7031: the flow off by up to 1e-3)
            self.wheelbase = before.to(device=after.device, dtype=result_dtype(before))
        return self

    def forward(self, camera: Camera, speed: Tensor | float,
                steering: Tensor | float) -> tuple[Tensor, Tensor]:
        """``(flow (B, 2, H, W) px/s, valid (B, 1, H, W) bool)`` for speed (m/s), steering (rad): :func:`velocity_flow`."""
        return velocity_flow(camera, speed, steering, self.wheelbase, self.size)

    def extra_repr(self) -> str:
        return f"size={self.size}, wheelbase={self.wheelbase}"


# -- the special cases of the paper (eq. 22-24) ------------------------------------------------

def _params(camera: Camera, named: dict[str, object]) -> tuple[Camera, dict[str, Tensor], int]:
    """Validate per-frame parameters, resolve the batch size and the common dtype."""
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    given = [as_batch_param(v, n, finite=False) for n, v in named.items() if isinstance(v, Tensor)]
    dtype = result_dtype(camera.K, *given)
    tensors = {n: as_batch_param(v, n, dtype, camera.device, finite=False) for n, v in named.items()}
    check_all_finite(tensors)
    B = resolve_batch({"camera": camera.batch_size, **{n: t.shape[0] for n, t in tensors.items()}})
    camera = camera.to(dtype).expand(B)
    return camera, {n: t.expand(B) for n, t in tensors.items()}, B


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


def _radial(scale: Tensor, valid: Tensor, du: Tensor, dv: Tensor, B: int) -> tuple[Tensor, Tensor]:
    """The radial flow ``scale · (u - u_0, v - v_0)`` (B, 2, H, W), 0 where not ``valid``, and
    ``valid`` (B, 1, H, W), from broadcastable (·, 1, H, W) pieces."""
    shape = (B, 1, *du.shape[-2:])
    scale, valid = scale.expand(shape), valid.expand(shape)
    scale = torch.where(valid, scale, torch.zeros_like(scale))
    return torch.cat([scale * du.expand(shape), scale * dv.expand(shape)], dim=1), valid


def displacement_flow_straight(camera: Camera, z_d: Tensor | float,
                               size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 22: straight motion (φ = 0, x_d = 0) with roll; the camera's pitch is ignored, and
    so is its skew (as in all four special cases: the paper's equations).

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
    return _radial(scale, valid, du, dv, B)


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
    return _radial(scale, valid, du, dv, B)


def velocity_flow_straight(camera: Camera, speed: Tensor | float,
                           size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 23: straight motion (δ_f = 0) with roll: ``f_v = v_r λ1 / h · (u - u_0, v - v_0)``."""
    size = check_size(size)
    camera, p, B = _params(camera, {"speed": speed})
    du, dv = _centred(camera, size, camera.dtype)
    lam1 = _lambda1(camera, du, dv)
    valid = lam1 > 0
    scale = p["speed"].reshape(-1, 1, 1, 1) * lam1 / camera.height.reshape(-1, 1, 1, 1)
    return _radial(scale, valid, du, dv, B)


def velocity_flow_straight_level(camera: Camera, speed: Tensor | float,
                                 size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Paper eq. 24 (velocity): ``f_v = v_r (v - v_0) / (h f_y) · (u - u_0, v - v_0)``, no roll."""
    size = check_size(size)
    camera, p, B = _params(camera, {"speed": speed})
    du, dv = _centred(camera, size, camera.dtype)
    valid = dv > 0
    scale = p["speed"].reshape(-1, 1, 1, 1) * dv / (camera.height * camera.fy).reshape(-1, 1, 1, 1)
    return _radial(scale, valid, du, dv, B)


def vflow_curve(v: Tensor | float, z_d: Tensor | float, height: Tensor | float, fy: Tensor | float,
                cy: Tensor | float) -> Tensor:
    """The vertical road flow of eq. 24 as a function of the row: ``F_v(v) = z_d (v-v_0)² / (h f_y - z_d (v-v_0))``.

    This is the curve the V-flow analysis fits. Rows at or above the horizon (v ≤ v_0), or where
    the road point is behind the camera at t+1, give 0. Each argument is a tensor, a number or a
    sequence of numbers; they broadcast like ordinary tensor arithmetic. The result is in the
    promoted dtype of the tensor arguments with half precision lifted to float32, as the rest of
    the geometry (the default dtype when none is a float tensor), on their device: a half
    precision row index computed in its own precision overflows (z_d (v-v_0)² beyond 65504).

    Shapes that do not broadcast together are a ValueError quoting them. Every value must be
    finite, ``height`` and ``fy`` positive: else a ValueError naming the argument (a NaN row or a negative height would read as "no road flow" there; the values are
    not checked while tracing).
    """
    args = curve_arguments({"v": v, "z_d": z_d, "height": height, "fy": fy, "cy": cy})
    check_positive(args["height"], "height")
    check_positive(args["fy"], "fy")
    dv = args["v"] - args["cy"]
    den = args["height"] * args["fy"] - args["z_d"] * dv
    ok = (dv > 0) & (den > 0)
    out = args["z_d"] * dv * dv / torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, out, torch.zeros_like(out))


def curve_arguments(named: dict[str, object]) -> dict[str, Tensor]:
    """The arguments of a curve of the row (name -> a tensor, a number or a sequence of numbers) as
    tensors of their promoted float dtype, half precision lifted to float32 (the default dtype
    where none is a float tensor), each on its own device (numbers on the first tensor's, else on
    the CPU, not the default device). A bool, complex, string or None argument is a TypeError
    naming it; a NaN or inf value, or shapes that do not broadcast together, a ValueError (values
    not checked while tracing)."""
    floats = [x for x in named.values() if isinstance(x, Tensor) and x.is_floating_point()]
    dtype = result_dtype(*floats) if floats else torch.get_default_dtype()
    device = next((x.device for x in named.values() if isinstance(x, Tensor)), torch.device("cpu"))
    args = {}
    for name, x in named.items():
        if isinstance(x, Tensor) and (x.dtype == torch.bool or x.is_complex()):
            raise TypeError(f"{name}: expected a real tensor or number, got dtype {x.dtype}")
        if isinstance(x, (bool, str, bytes)) or x is None:
            raise TypeError(f"{name}: expected a tensor or a number, got {type(x).__name__} {x!r:.60}")
        try:
            args[name] = torch.as_tensor(x, dtype=dtype, device=x.device if isinstance(x, Tensor) else device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{name}: expected a tensor or a number, got {type(x).__name__} {x!r:.60}") from None
    check_all_finite(args)
    try:
        torch.broadcast_shapes(*(t.shape for t in args.values()))
    except RuntimeError:  # (torch's own error names no argument)
        shapes = ", ".join(f"{n} {tuple(t.shape)}" for n, t in args.items())
        raise ValueError(f"{', '.join(named)}: expected shapes that broadcast together, got {shapes}") from None
    return args
