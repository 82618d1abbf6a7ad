"""Fitting the freespace flow models to a flow field: ego-motion, roll and pitch, robustly.

Only d / h is observable from flow (DESIGN.md §5): the camera height h is taken from the
camera and the translation is reported in metres under it. The unknowns are

- displacement model (:func:`fit_displacement`): x_d, z_d (metres), yaw φ (radians), and
  optionally the mounting roll θ and pitch β (radians);
- velocity model (:func:`fit_velocity`): the rear-axle speed v_r (m/s) and the yaw rate
  (hence the steering angle δ_f = atan(φ̇ l / v_r) for a wheelbase l), optionally roll and pitch.

Method: the road flow is the plane-induced homography H of the road (velocity model: its time
derivative G), a 3×3 matrix per frame whose derivatives with respect to the parameters are
written out below. Each frame is fitted by Levenberg–Marquardt on the end-point residuals with
the IRLS weights of a robust kernel (Cauchy by default), the normal equations in float64,
batched over frames. The scale of the kernel is annealed from the spread of the residuals of
the initial guess down to ``scale`` so that a wrong start is not locked in by its own weights.
The initial guess needs no prior: with the mounting fixed (at the camera's roll and pitch),
the pixels and their flow targets back-project onto the road plane, where the motion is a
planar rigid motion; a weighted linear least-squares fit of a 2-D similarity there (re-weighted
a few times) gives yaw and translation. After the robust fit, a few iterations with Tukey's
biweight cut at the inlier threshold (``polish``) stop far outliers (other vehicles) from
pulling on the estimate. JᵀWJ is accumulated without a per-pixel Jacobian: the residual
depends on the parameters only through the 9 entries of the 3×3 map (see
:func:`_normal_equations`).

Fitting is iterative and data dependent (convergence tests, accept/reject steps): it is not
differentiable and not meant for ``torch.compile``; its results are detached tensors.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._check import check_finite, check_float_tensor, check_positive, check_shape, result_dtype
from ..geometry.camera import Camera, mounting_matrix
from ..geometry.road_flow import _flow_from_matrix, displacement_flow  # noqa: F401  (docstring example)

__all__ = [
    "FitResult",
    "VelocityFitResult",
    "fit_displacement",
    "fit_velocity",
    "robust_weight",
    "ROBUST_KERNELS",
]

ROBUST_KERNELS = ("cauchy", "huber", "soft_l1", "tukey", "l2")


# -- results -----------------------------------------------------------------------------------

@dataclass
class FitResult:
    """The displacement model fitted to B frames.

    Attributes:
        x_d, z_d: ego translation in metres under the camera height used (B,).
        yaw: ego yaw φ in radians (B,).
        roll, pitch: the mounting angles in radians (B,) (fitted, or the fixed ones).
        flow: the model flow (B, 2, H, W) in pixels at the full resolution (0 where not defined).
        valid: where the model is defined (B, 1, H, W) bool.
        inliers: mask pixels whose flow agrees with the model (B, 1, H, W) bool: the robust
            weight's residual ‖model − flow‖ ≤ ``inlier_threshold`` px.
        residual: mean end-point error over the inliers in pixels (B,) (NaN-free; 0 when none).
        success: (B,) bool: the fit converged, on enough well-spread inliers making up at least
            ``min_inlier_fraction`` of the mask, with a well-conditioned problem. Where False
            the parameters are finite but not to be trusted.
        camera: the input camera with the fitted roll and pitch (B frames).
        iterations: Levenberg–Marquardt iterations done (B,) int64.
    """

    x_d: Tensor
    z_d: Tensor
    yaw: Tensor
    roll: Tensor
    pitch: Tensor
    flow: Tensor
    valid: Tensor
    inliers: Tensor
    residual: Tensor
    success: Tensor
    camera: Camera
    iterations: Tensor

    def odometry(self) -> dict[str, Tensor]:
        """``dict(x_d=, z_d=, yaw=)`` of (B,) tensors, the form the refiner and flow model take."""
        return dict(x_d=self.x_d, z_d=self.z_d, yaw=self.yaw)


@dataclass
class VelocityFitResult:
    """The velocity model fitted to B frames of flow in pixels per second.

    Attributes:
        speed: rear-axle speed v_r in m/s (B,); steering: front-wheel angle δ_f in radians (B,)
            (0 where the speed is 0); yaw_rate: φ̇ in rad/s (B,); roll, pitch in radians (B,);
        flow (B, 2, H, W) px/s, valid, inliers (B, 1, H, W) bool, residual (B,) px/s,
        success (B,) bool, camera, iterations: as in :class:`FitResult`; wheelbase (B,) metres.
    """

    speed: Tensor
    steering: Tensor
    yaw_rate: Tensor
    roll: Tensor
    pitch: Tensor
    flow: Tensor
    valid: Tensor
    inliers: Tensor
    residual: Tensor
    success: Tensor
    camera: Camera
    iterations: Tensor
    wheelbase: Tensor

    def velocity(self) -> dict[str, Tensor]:
        """``dict(speed=, steering=, wheelbase=)`` of (B,) tensors."""
        return dict(speed=self.speed, steering=self.steering, wheelbase=self.wheelbase)


# -- robust kernels --------------------------------------------------------------------------

def robust_weight(r2: Tensor, scale: Tensor | float, kind: str = "cauchy") -> Tensor:
    """IRLS weight w(r) = ρ'(r²)/… of a robust kernel for squared residual norms ``r2``.

    ``kind``: "cauchy" (1/(1+r²/c²)), "huber" (min(1, c/r)), "soft_l1" (1/sqrt(1+r²/c²), SciPy's),
    "tukey" ((1−r²/c²)² for r < c, else 0), "l2" (1). ``scale`` c in the residual's unit.
    """
    if kind == "l2":
        return torch.ones_like(r2)
    z = r2 / (scale * scale)
    if kind == "cauchy":
        return 1.0 / (1.0 + z)
    if kind == "soft_l1":
        return torch.rsqrt(1.0 + z)
    if kind == "huber":
        return torch.where(z <= 1.0, torch.ones_like(z), torch.rsqrt(z.clamp_min(1e-300)))
    if kind == "tukey":
        return torch.where(z < 1.0, (1.0 - z) ** 2, torch.zeros_like(z))
    raise ValueError(f"robust: expected one of {ROBUST_KERNELS}, got {kind!r}")


def _robust_cost(r2: Tensor, scale: Tensor, kind: str) -> Tensor:
    """ρ(r²) (same shape), with ρ'(0) = 1, matching :func:`robust_weight`."""
    c2 = scale * scale
    z = r2 / c2
    if kind == "l2":
        return r2
    if kind == "cauchy":
        return c2 * torch.log1p(z)
    if kind == "soft_l1":
        return 2.0 * c2 * (torch.sqrt(1.0 + z) - 1.0)
    if kind == "huber":
        return torch.where(z <= 1.0, r2, c2 * (2.0 * torch.sqrt(z.clamp_min(1e-300)) - 1.0))
    if kind == "tukey":
        return torch.where(z < 1.0, c2 / 3.0 * (1.0 - (1.0 - z) ** 3), torch.full_like(z, 1.0) * c2 / 3.0)
    raise ValueError(f"robust: expected one of {ROBUST_KERNELS}, got {kind!r}")


def _cost_sum(r2: Tensor, scale: Tensor, kind: str) -> Tensor:
    """Σ_N ρ(r²) (B,) of :func:`_robust_cost` for r2 (B, N) and scale (B,), with the scale's
    factor taken out of the sum: fewer passes over the pixels in the fitting loop."""
    c2 = scale * scale
    if kind == "cauchy":
        return torch.log1p(r2 / c2.unsqueeze(-1)).sum(1) * c2
    if kind == "tukey":
        t = torch.rsub(r2 / c2.unsqueeze(-1), 1.0).clamp_min_(0.0)  # 1 − z where z < 1, else 0
        return torch.rsub(t.pow_(3), 1.0).sum(1) * (c2 / 3.0)
    return _robust_cost(r2, scale.unsqueeze(-1), kind).sum(1)


# -- the model matrices and their derivatives ------------------------------------------------

# The maps are assembled with one matmul of a few per-frame monomials by a constant basis, not
# entry by entry: fitting evaluates them once per iteration, and on CPU each small op costs more
# than its arithmetic. Every entry of X (and its derivatives), of R_c = R_θ R_β and of the
# mounting generators is linear in the monomials below.
#
# Displacement: X = R_φ (I − d nᵀ / h) = [[c, −u, −s], [0, 1, 0], [s, −v, c]] with c, s = cos φ,
# sin φ and u = c a − s b, v = s a + c b; dX/da = [[0, −c, 0], [0, 0, 0], [0, −s, 0]],
# dX/db = [[0, s, 0], [0, 0, 0], [0, −c, 0]], dX/dφ = [[−s, v, −c], [0, 0, 0], [c, −u, −s]].
# Velocity: G = Ω − ḋ nᵀ / h = [[0, 0, −ω], [0, 0, 0], [ω, −k, 0]] (k = v_r / h, ω = φ̇);
# dG/dk = [[0, 0, 0], [0, 0, 0], [0, −1, 0]], dG/dω = [[0, 0, −1], [0, 0, 0], [1, 0, 0]].
# Mounting: R_c = [[cθ, sθ cβ, sθ sβ], [−sθ, cθ cβ, cθ sβ], [0, −sβ, cβ]]; the roll's generator
# dR_θ/dθ R_θᵀ = [[0, 1, 0], [−1, 0, 0], [0, 0, 0]] and the pitch's seen through the roll,
# R_θ G_β R_θᵀ = [[0, 0, sθ], [0, 0, cθ], [−sθ, −cθ, 0]].
_MOUNT_MONOMIALS = ("ct", "st", "cb", "sb", "ct*cb", "ct*sb", "st*cb", "st*sb")
_MOUNT_MAPS = (
    ("ct", "st*cb", "st*sb", "-st", "ct*cb", "ct*sb", "0", "-sb", "cb"),  # R_c
    ("0", "1", "0", "-1", "0", "0", "0", "0", "0"),                      # G_θ
    ("0", "0", "st", "0", "0", "ct", "-st", "-ct", "0"),                 # R_θ G_β R_θᵀ
)
_DISP_MONOMIALS = ("1", "c", "s", "c*a", "c*b", "s*a", "s*b") + _MOUNT_MONOMIALS
_DISP_MAPS = (
    ("c", "-u", "-s", "0", "1", "0", "s", "-v", "c"),     # X
    ("0", "-c", "0", "0", "0", "0", "0", "-s", "0"),      # dX/da
    ("0", "s", "0", "0", "0", "0", "0", "-c", "0"),       # dX/db
    ("-s", "v", "-c", "0", "0", "0", "c", "-u", "-s"),    # dX/dφ
)
_VEL_MONOMIALS = ("1", "k", "w") + _MOUNT_MONOMIALS
_VEL_MAPS = (
    ("0", "0", "-w", "0", "0", "0", "w", "-k", "0"),      # G
    ("0", "0", "0", "0", "0", "0", "0", "-1", "0"),       # dG/dk
    ("0", "0", "-1", "0", "0", "0", "1", "0", "0"),       # dG/dω
)
_LINEAR = {"u": {"c*a": 1.0, "s*b": -1.0}, "v": {"s*a": 1.0, "c*b": 1.0}}
# the factors of the monomials, in the order _homography_jac / _velocity_jac compute them: 1, the
# cosines and sines of the angles, then the parameters that enter linearly
_DISP_FACTORS = ("1", "c", "ct", "cb", "s", "st", "sb", "a", "b")
_VEL_FACTORS = ("1", "ct", "cb", "st", "sb", "k", "w")


def _factor_index(monomials: tuple[str, ...], factors: tuple[str, ...]) -> list[list[int]]:
    """For each monomial the positions of its two factors in ``factors`` (1 for a lone one)."""
    pairs = [(m.split("*") + ["1"])[:2] for m in monomials]
    return [[factors.index(x) for x, _ in pairs], [factors.index(y) for _, y in pairs]]

_CONSTANTS: dict = {}


def _map_basis(monomials: tuple[str, ...], maps: tuple[tuple[str, ...], ...]) -> list[list[float]]:
    """(len(monomials), 9 · len(maps)) coefficients: map entry = Σ monomial × coefficient."""
    basis = [[0.0] * (9 * len(maps)) for _ in monomials]
    for col, entry in enumerate(e for m in maps for e in m):
        sign = -1.0 if entry.startswith("-") else 1.0
        name = entry.lstrip("-")
        if name == "0":
            continue
        for mono, coef in _LINEAR.get(name, {name: 1.0}).items():
            basis[monomials.index(mono)][col] += sign * coef
    return basis


def _constants(dtype: torch.dtype, device: torch.device) -> dict[str, Tensor]:
    """Constant bases (see above and :func:`_normal_equations`), cached per dtype and device."""
    key = (dtype, device)
    if key not in _CONSTANTS:
        # AH (9×9) of _normal_equations from the four moment sums (4 × 6): blocks
        # [[S0, 0, −S1], [0, S0, −S2], [−S1, −S2, S3]], S_k symmetric from (uu, uv, vv, u, v, 1)
        sym = ((0, 1, 3), (1, 2, 4), (3, 4, 5))
        blocks = {(0, 0): (0, 1.0), (1, 1): (0, 1.0), (0, 2): (1, -1.0), (2, 0): (1, -1.0),
                  (1, 2): (2, -1.0), (2, 1): (2, -1.0), (2, 2): (3, 1.0)}
        ah = torch.zeros(24, 81, dtype=dtype)
        for (bi, bj), (k, sign) in blocks.items():
            for i in range(3):
                for j in range(3):
                    ah[6 * k + sym[i][j], (3 * bi + i) * 9 + 3 * bj + j] = sign
        _CONSTANTS[key] = dict(
            disp=torch.tensor(_map_basis(_DISP_MONOMIALS, _DISP_MAPS + _MOUNT_MAPS), dtype=dtype, device=device),
            vel=torch.tensor(_map_basis(_VEL_MONOMIALS, _VEL_MAPS + _MOUNT_MAPS), dtype=dtype, device=device),
            disp_index=torch.tensor(_factor_index(_DISP_MONOMIALS, _DISP_FACTORS), device=device),
            vel_index=torch.tensor(_factor_index(_VEL_MONOMIALS, _VEL_FACTORS), device=device),
            ah=ah.to(device))
    return _CONSTANTS[key]


def _sandwich_jac(K: Tensor, Kinv: Tensor, monomials: Tensor, basis: Tensor, Q: int,
                  ray: bool = False) -> tuple[Tensor, ...]:
    """M = K R_c X R_cᵀ K⁻¹ and its derivatives, R_c = R_θ R_β.

    ``monomials`` (B, m) @ ``basis`` (m, 9 (Q + 4)) give X and its derivatives by the Q motion
    parameters, R_c and the two mounting generators; returns M (B, 3, 3) and dM (B, Q + 2, 3, 3)
    by (motion parameters..., θ, β), and with ``ray`` also the y row (B, 1, 3) of R_cᵀ K⁻¹ (the
    vehicle-frame ray's height test). The derivative of C = R_c X R_cᵀ by a mounting angle is a
    commutator [G, C] with the angle's generator G.
    """
    B = monomials.shape[0]
    maps = (monomials @ basis).reshape(B, Q + 4, 3, 3)
    inner, Rc, G = maps[:, : Q + 1], maps[:, Q + 1], maps[:, Q + 2:]
    C = Rc.unsqueeze(1) @ inner @ Rc.transpose(-1, -2).unsqueeze(1)  # camera-frame maps
    C0 = C[:, :1]
    out = K.unsqueeze(1) @ torch.cat([C, G @ C0 - C0 @ G], dim=1) @ Kinv.unsqueeze(1)
    if ray:
        return out[:, 0], out[:, 1:], Rc[:, :, 1:2].transpose(-1, -2) @ Kinv
    return out[:, 0], out[:, 1:]


def _monomials(params: Tensor, n_lin: int, index: Tensor) -> Tensor:
    """(B, m) monomials as products of two factors each: the factors (B, f) are 1, cos and sin of
    ``params[:, n_lin:]`` (the angles), then ``params[:, :n_lin]``; ``index`` (2, m) picks them.
    Two gathers and one product instead of a cos, sin, stack and outer product per group (the
    fitting loop evaluates this once per iteration, where each small op costs more than its
    arithmetic)."""
    ang = params[:, n_lin:]
    f = torch.cat([torch.ones_like(params[:, :1]), torch.cos(ang), torch.sin(ang), params[:, :n_lin]],
                  dim=-1)
    return f[:, index[0]] * f[:, index[1]]


def _homography_jac(K: Tensor, Kinv: Tensor, params: Tensor, ray: bool = False) -> tuple[Tensor, ...]:
    """H (B, 3, 3) and dH/dparams (B, 5, 3, 3) for params (a = x_d/h, b = z_d/h, φ, θ, β)
    (and the ray row with ``ray``, see :func:`_sandwich_jac`)."""
    const = _constants(params.dtype, params.device)
    mono = _monomials(params, 2, const["disp_index"])
    return _sandwich_jac(K, Kinv, mono, const["disp"], 3, ray)


def _fixed_mount_homography_jac(K: Tensor, Kinv: Tensor, roll: Tensor, pitch: Tensor):
    """:func:`_homography_jac` for a mounting that is not fitted (the refiner's case).

    With R_c fixed, M = (K R_c) X (R_cᵀ K⁻¹) and its derivatives by (a, b, φ) are linear in the
    seven motion monomials: the products with K R_c and R_cᵀ K⁻¹ are taken once per fit, and
    each evaluation is one (B, 7) @ (B, 7, 36) matmul. The derivatives by θ, β are 0 (those
    parameters are fixed: their rows of the normal equations are replaced anyway).
    """
    B = K.shape[0]
    const = _constants(K.dtype, K.device)
    Rc = mounting_matrix(roll, pitch)
    X = const["disp"][:7, :36].reshape(1, 7, 4, 3, 3)
    left, right = (K @ Rc).reshape(B, 1, 1, 3, 3), (Rc.transpose(-1, -2) @ Kinv).reshape(B, 1, 1, 3, 3)
    T = (left @ X @ right).reshape(B, 7, 36)
    ray_row = Rc[:, :, 1:2].transpose(-1, -2) @ Kinv
    index = const["disp_index"][:, :7]
    zeros = K.new_zeros(B, 2, 3, 3)

    def jac(K_: Tensor, Kinv_: Tensor, params: Tensor, ray: bool = False) -> tuple[Tensor, ...]:
        maps = (_monomials(params, 2, index).unsqueeze(1) @ T).reshape(B, 4, 3, 3)
        dM = torch.cat([maps[:, 1:], zeros], dim=1)
        return (maps[:, 0], dM, ray_row) if ray else (maps[:, 0], dM)
    return jac


def _velocity_jac(K: Tensor, Kinv: Tensor, params: Tensor, ray: bool = False) -> tuple[Tensor, ...]:
    """G (B, 3, 3) and dG/dparams (B, 4, 3, 3) for params (s = v_r/h, ω = φ̇, θ, β)
    (and the ray row with ``ray``, see :func:`_sandwich_jac`)."""
    const = _constants(params.dtype, params.device)
    mono = _monomials(params, 2, const["vel_index"])
    return _sandwich_jac(K, Kinv, mono, const["vel"], 2, ray)


# -- evaluation on the sampled pixels ----------------------------------------------------------

def _evaluate(M: Tensor, ray_row: Tensor, pts: Tensor, velocity: bool,
              dM: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
    """Model flow (B, 2, N), model validity (B, N) and optionally the Jacobian (B, P, 2, N).

    ``pts`` (B, 3, N) homogeneous pixels; ``ray_row`` (B, 1, 3) the vehicle-frame ray's y row.
    """
    B = M.shape[0]
    rows = [M, ray_row] if dM is None else [M, ray_row, dM.reshape(B, -1, 3)]
    q = torch.cat(rows, dim=1) @ pts  # one matmul for the map, the ray test and the derivatives
    ray_y, qz = q[:, 3], q[:, 2]
    if velocity:
        valid = ray_y > 0
        flow = q[:, :2] - pts[:, :2] * qz.unsqueeze(1)
    else:
        valid = (ray_y > 0) & (qz > 1e-9)
        inv_z = torch.where(valid, qz, torch.ones_like(qz)).reciprocal().unsqueeze(1)
        proj = q[:, :2] * inv_z
        flow = proj - pts[:, :2]
    if dM is None:
        return flow, valid, None
    P = dM.shape[1]
    dq = q[:, 4:].reshape(B, P, 3, -1)
    if velocity:
        J = dq[:, :, :2] - pts[:, None, :2] * dq[:, :, 2:3]
    else:
        J = (dq[:, :, :2] - proj.unsqueeze(1) * dq[:, :, 2:3]) * inv_z.unsqueeze(1)
    return flow, valid, J


# -- input handling ------------------------------------------------------------------------------

def _check_inputs(flow: Tensor, mask: Tensor, camera: Camera, valid: Tensor | None) -> tuple[dict, Camera, Tensor]:
    check_float_tensor(flow, "flow")
    dims = check_shape(flow, "flow", ("B", 2, "H", "W"))
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask: expected a bool tensor of shape (B, 1, H, W), got {type(mask).__name__}")
    if mask.dim() == 4 and mask.shape[0] == 1 and dims["B"] != 1:
        mask = mask.expand(dims["B"], -1, -1, -1)
    check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
    if mask.dtype != torch.bool:
        raise TypeError(f"mask: expected dtype torch.bool, got {mask.dtype}")
    if valid is not None:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            raise TypeError(f"valid: expected a bool tensor of shape (B, 1, H, W), got "
                            f"{valid.dtype if isinstance(valid, Tensor) else type(valid).__name__}")
        check_shape(valid, "valid", ("B", 1, "H", "W"), dims)
        mask = mask & valid
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size not in (1, dims["B"]):
        raise ValueError(f"camera: expected batch 1 or {dims['B']} (the flow's B), got {camera.batch_size}")
    if camera.batch_size != dims["B"]:
        camera = camera.expand(dims["B"])
    if camera.device != flow.device:
        camera = camera.to(device=flow.device)
    # one reduction decides the common case (a NaN or inf anywhere makes the sum non-finite);
    # only then look inside the mask
    if not bool(torch.isfinite(flow.detach().sum())):
        inside = flow.masked_select(mask.expand_as(flow))
        n = int((~torch.isfinite(inside)).sum())
    else:
        n = 0
    if n:
        raise ValueError(f"flow: expected finite values inside mask, got {n} NaN/inf values there "
                         f"(exclude them with valid=)")
    return dims, camera, mask


def _mask_indices(mask: Tensor, max_points: int | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Every mask pixel and a deterministic subsample of them.

    Returns ``pix`` (B, N) per-frame flat indices (y W + x) of at most ``max_points`` mask pixels
    per frame, ``sel`` (B, N) the flags of real points (the rest is padding), ``counts`` (B,) the
    per-frame number of mask pixels, and ``every`` (M,) the flat indices into (B·H·W) of all
    M mask pixels of the batch, sorted (frame by frame, raster order).
    """
    B, _, H, W = mask.shape
    HW = H * W
    # one flat nonzero: a 2-D nonzero splits each index into (frame, pixel) by an int64 division
    # per mask pixel, which costs more than the nonzero itself
    every = mask.reshape(-1).nonzero().squeeze(1)
    # the frames' boundaries in the sorted indices give counts and starts (no pass over the mask)
    bounds = torch.searchsorted(every, torch.arange(B + 1, device=mask.device) * HW)
    counts, start = bounds.diff(), bounds[:-1]
    n_max = int(counts.max()) if B else 0
    N = n_max if max_points is None else min(n_max, int(max_points))
    N = max(N, 1)
    # the j-th kept pixel of a frame with n > N mask pixels is its floor(j n / N)-th one: an even
    # stride over raster order; frames with n <= N keep all and pad the rest
    j = torch.arange(N, device=mask.device).expand(B, N)
    n = counts.unsqueeze(1)
    rank = torch.where(n > N, (j * n) // N, j)
    sel = rank < n
    if every.numel():
        frame0 = torch.arange(B, device=mask.device).unsqueeze(1) * HW
        pix = every[(start.unsqueeze(1) + rank).clamp_max(every.numel() - 1)] - frame0
        pix = torch.where(sel, pix, torch.zeros_like(pix))
    else:
        pix = torch.zeros(B, N, dtype=torch.long, device=mask.device)
    return pix, sel, counts, every


def _mask_sample(mask: Tensor, max_points: int | None) -> tuple[Tensor, Tensor, Tensor]:
    """Flat pixel indices (B, N) of the mask, deterministically subsampled to at most
    ``max_points`` per frame, the flags of real points (B, N) (the rest is padding) and the
    per-frame count of mask pixels (B,)."""
    return _mask_indices(mask, max_points)[:3]


def _pixels(pix: Tensor, W: int) -> Tensor:
    """Homogeneous pixel coordinates (B, 3, N) float64 of flat indices (B, N)."""
    u = (pix % W).to(torch.float64)
    v = torch.div(pix, W, rounding_mode="floor").to(torch.float64)
    return torch.stack([u, v, torch.ones_like(u)], dim=1)


def _sample(flow: Tensor, mask: Tensor, max_points: int | None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The mask's pixels (see :func:`_mask_indices`): pts (B, 3, N) float64 homogeneous pixels,
    obs (B, 2, N) float64 flow there, sel (B, N) bool, counts (B,), every (M,)."""
    B, _, H, W = flow.shape
    pix, sel, counts, every = _mask_indices(mask, max_points)
    N = pix.shape[1]
    obs = flow.reshape(B, 2, H * W).gather(2, pix.unsqueeze(1).expand(B, 2, N)).to(torch.float64)
    obs = torch.where(sel.unsqueeze(1), obs, torch.zeros_like(obs))
    return _pixels(pix, W), obs, sel, counts, every


def _init_value(init: object, name: str, B: int, default: Tensor) -> Tensor:
    """A per-frame start value from ``init`` (a FitResult, a dict, or None) as (B,) float64."""
    if init is None:
        return default
    value = getattr(init, name, None) if not isinstance(init, dict) else init.get(name)
    if value is None:
        return default
    t = torch.as_tensor(value, dtype=torch.float64, device=default.device).detach().reshape(-1)
    if t.numel() not in (1, B):
        raise ValueError(f"init: expected {name} of batch 1 or {B}, got {t.numel()} values")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"init: expected a finite {name}, got {t.tolist()}")
    return t.expand(B).clone()


# -- the initial guess from the road plane ------------------------------------------------

def _planar_init(K: Tensor, Kinv: Tensor, roll: Tensor, pitch: Tensor, pts: Tensor, obs: Tensor,
                 sel: Tensor, iters: int = 3) -> tuple[Tensor, Tensor]:
    """Yaw and (x_d, z_d)/h from a 2-D similarity of back-projected road points.

    A road pixel back-projects (mounting fixed) to the vehicle-frame ray x = R_cᵀ K⁻¹ p̃, scaled
    to x_y = 1: (X/h, 1, Z/h) of its road point; its flow target p + F back-projects likewise.
    The model moves road points by x' = R_φ (x − d/h), linear in (cos φ, sin φ, t) when cos and
    sin are left free; weights ~ (x_y of the ray)² turn ground errors back into roughly equal
    pixel errors, and a few Cauchy re-weightings drop outliers. Returns params (B, 3) =
    (a, b, φ) and a bool (B,) that is False where the linear system was degenerate.
    """
    B = pts.shape[0]
    Rc = mounting_matrix(roll, pitch)
    A = Rc.transpose(-1, -2) @ Kinv
    x = A @ pts
    tgt = torch.cat([pts[:, :2] + obs, pts[:, 2:]], dim=1)
    xp = A @ tgt
    ok = sel & (x[:, 1] > 1e-6) & (xp[:, 1] > 1e-6)
    y0 = torch.where(ok, x[:, 1], torch.ones_like(x[:, 1]))
    y1 = torch.where(ok, xp[:, 1], torch.ones_like(xp[:, 1]))
    X, Z = x[:, 0] / y0, x[:, 2] / y0
    Xp, Zp = xp[:, 0] / y1, xp[:, 2] / y1
    # x' = c X - s Z + tx ; z' = s X + c Z + tz  (tx, tz = -R_φ d/h): rows (X, -Z, 1, 0) and
    # (Z, X, 0, 1) of the design matrix, both with the point's weight; its normal matrix and
    # right-hand side are made of eight weighted sums (one matmul per re-weighting, no (2N, 4)
    # design matrix): N = Σ w [[X²+Z², 0, X, Z], [0, X²+Z², -Z, X], [X, -Z, 1, 0], [Z, X, 0, 1]],
    # g = Σ w (X X' + Z Z', X Z' - Z X', X', Z')
    feats = torch.stack([X * X + Z * Z, X, Z, torch.ones_like(X), X * Xp + Z * Zp, X * Zp - Z * Xp,
                         Xp, Zp], dim=-1)  # (B, N, 8)
    base = torch.where(ok, y0 * y0, torch.zeros_like(y0))
    w = base
    theta = torch.zeros(B, 4, dtype=pts.dtype, device=pts.device)
    good = torch.ones(B, dtype=torch.bool, device=pts.device)
    fx2 = (K[:, 0, 0].unsqueeze(-1) * y0) ** 2  # residuals back in (roughly) pixel units
    for it in range(iters):
        S = (w.unsqueeze(1) @ feats).squeeze(1)  # (B, 8)
        rr, sx, sz, s1 = S[:, 0], S[:, 1], S[:, 2], S[:, 3]
        zero = torch.zeros_like(rr)
        N = torch.stack([rr, zero, sx, sz, zero, rr, -sz, sx, sx, -sz, s1, zero, sz, sx, zero, s1],
                        dim=-1).reshape(B, 4, 4)
        g = S[:, 4:]
        scale = N.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()
        Nn = N / (scale.unsqueeze(-1) * scale.unsqueeze(-2))
        Nn = Nn + torch.eye(4, dtype=N.dtype, device=N.device) * 1e-12
        theta = torch.linalg.solve(Nn, (g / scale).unsqueeze(-1)).squeeze(-1) / scale
        c_, s_, tx_, tz_ = theta.unsqueeze(-1).unbind(1)
        rx = c_ * X - s_ * Z + tx_ - Xp
        rz = s_ * X + c_ * Z + tz_ - Zp
        rp2 = (rx * rx + rz * rz) * fx2
        rp2 = torch.where(ok, rp2, torch.full_like(rp2, float("nan")))
        spread = torch.nanmedian(rp2, dim=1).values.clamp_min(1.0)
        wr = 1.0 / (1.0 + rp2 / (4.0 * spread.unsqueeze(-1)))
        wr = torch.where(ok, wr, torch.zeros_like(wr))
        w = base * wr
    good = torch.linalg.eigvalsh(Nn)[:, 0] > 1e-9
    c, s, tx, tz = theta.unbind(-1)
    yaw = torch.atan2(s, c)
    cn, sn = torch.cos(yaw), torch.sin(yaw)
    a = -(cn * tx + sn * tz)
    b = -(-sn * tx + cn * tz)
    out = torch.stack([a, b, yaw], dim=-1)
    good = good & torch.isfinite(out).all(-1) & (ok.sum(1) >= 4)
    return torch.where(good.unsqueeze(-1), out, torch.zeros_like(out)), good


def _velocity_init(K: Tensor, Kinv: Tensor, roll: Tensor, pitch: Tensor, pts: Tensor, obs: Tensor,
                   sel: Tensor, kind: str, scale: float, iters: int = 4) -> tuple[Tensor, Tensor]:
    """(v_r/h, φ̇) by re-weighted linear least squares with the mounting fixed (the velocity
    flow is linear in both). Returns (B, 2) and a bool (B,) False where degenerate."""
    B = pts.shape[0]
    zero = torch.zeros(B, dtype=pts.dtype, device=pts.device)
    params = torch.stack([zero, zero, roll, pitch], dim=-1)
    M, dM = _velocity_jac(K, Kinv, params)
    ray_row = (mounting_matrix(roll, pitch).transpose(-1, -2) @ Kinv)[:, 1:2, :]
    _, valid, J = _evaluate(M, ray_row, pts, True, dM[:, :2])
    J = J.reshape(B, 2, -1)  # flow = J^T theta exactly (linear, zero at theta = 0)
    w = (sel & valid).to(pts.dtype)
    r_obs = obs.reshape(B, -1)
    theta = torch.zeros(B, 2, dtype=pts.dtype, device=pts.device)
    good = torch.ones(B, dtype=torch.bool, device=pts.device)
    for it in range(iters):
        ww = torch.cat([w, w], dim=1).unsqueeze(1)
        N = (J * ww) @ J.transpose(1, 2)
        g = ((J * ww) * r_obs.unsqueeze(1)).sum(-1)
        sc = N.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()
        Nn = N / (sc.unsqueeze(-1) * sc.unsqueeze(-2))
        Nn = Nn + torch.eye(2, dtype=N.dtype, device=N.device) * 1e-12
        theta = torch.linalg.solve(Nn, (g / sc).unsqueeze(-1)).squeeze(-1) / sc
        res = (theta.unsqueeze(1) @ J).squeeze(1) - r_obs
        r2 = res[:, : res.shape[1] // 2] ** 2 + res[:, res.shape[1] // 2:] ** 2
        r2m = torch.where(sel & valid, r2, torch.full_like(r2, float("nan")))
        spread = torch.nanmedian(r2m, dim=1).values.clamp_min(scale * scale)
        w = robust_weight(r2, (4.0 * spread.unsqueeze(-1)).sqrt(), "cauchy") * (sel & valid)
    good = (torch.linalg.eigvalsh(Nn)[:, 0] > 1e-9) & torch.isfinite(theta).all(-1)
    return torch.where(good.unsqueeze(-1), theta, torch.zeros_like(theta)), good


# -- Levenberg–Marquardt with robust weights ----------------------------------------------------

def _moments(pts: Tensor) -> Tensor:
    """The six distinct entries of p̃ p̃ᵀ per pixel, (B, 6, N): uu, uv, vv, u, v, 1 (p̃ last).

    Stored moment-major: the sums against them (:func:`_normal_equations`) are then dot products
    along contiguous rows, which the skinny matmul does faster than with (B, N, 6)."""
    u, v, one = pts.unbind(1)
    return torch.stack([u * u, u * v, v * v, u, v, one], dim=1)


def _normal_equations(dM: Tensor, pts: Tensor, mom: Tensor, proj: Tensor, inv_z: Tensor | None,
                      w: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """Jᵀ W J (B, P, P) and Jᵀ W r (B, P) without forming the per-pixel Jacobian.

    The end-point residual depends on the parameters only through the 3×3 matrix M: per pixel
    ∂r/∂M = (1/q_z) [[p̃ᵀ, 0, −x′ p̃ᵀ], [0, p̃ᵀ, −y′ p̃ᵀ]] with (x′, y′) the projected point
    (velocity model: q_z = 1 and (x′, y′) the pixel itself). So Jᵀ W J in M's 9 entries is made of
    four weighted sums of p̃ p̃ᵀ (weights w/q_z² × 1, x′, y′, x′²+y′²) and Jᵀ W r of three weighted
    sums of p̃ (weights w/q_z × (r_x, r_y, −(x′ r_x + y′ r_y))): the seven weights are written
    into one (B, 7, N) buffer and summed against the moments (B, 6, N) by one skinny matmul (p̃
    is the moments' last three rows), instead of a (P, 2, N) Jacobian; the 9×9 matrix is assembled
    from the 4 × 6 distinct sums by one matmul with a constant basis, and the chain rule through
    dM/dp (B, P, 3, 3) is applied to 9×9 and 9-vectors. ``pts`` (B, 3, N) only gives B and N.
    """
    B, P = dM.shape[:2]
    N = pts.shape[-1]
    # in place into one buffer: on CPU each per-pixel temporary and cat costs a pass over memory
    wts = torch.empty(B, 7, N, dtype=w.dtype, device=w.device)
    a, ax, ay, app, br, gz = wts[:, 0], wts[:, 1], wts[:, 2], wts[:, 3], wts[:, 4:6], wts[:, 6]
    if inv_z is None:
        a.copy_(w)
        br.copy_(r).mul_(w.unsqueeze(1))
    else:
        wi = w * inv_z
        torch.mul(wi, inv_z, out=a)
        torch.mul(r, wi.unsqueeze(1), out=br)
    torch.mul(proj, a.unsqueeze(1), out=wts[:, 1:3])
    torch.mul(proj[:, 0], ax, out=app).addcmul_(proj[:, 1], ay)        # (x′² + y′²) a
    torch.mul(proj[:, 0], br[:, 0], out=gz).neg_().addcmul_(proj[:, 1], br[:, 1], value=-1.0)
    S = wts @ mom.transpose(1, 2)  # (B, 7, 6)
    AH = (S[:, :4].reshape(B, 24) @ _constants(w.dtype, w.device)["ah"]).reshape(B, 9, 9)
    gH = S[:, 4:, 3:].reshape(B, 9, 1)  # (B, 3, 3) against p̃: rows x, y, z of M
    D = dM.reshape(B, P, 9)
    return D @ AH @ D.transpose(1, 2), (D @ gH).squeeze(-1)


def _lm(jac_fn, velocity: bool, K: Tensor, Kinv: Tensor, params: Tensor, free: Tensor, pts: Tensor,
        obs: Tensor, sel: Tensor, *, stages: list[tuple[str, float, bool, float]],
        max_iter: int) -> list[tuple]:
    """Robust Levenberg–Marquardt (IRLS weights, Marquardt scaling) over the free parameters.

    ``stages``: (kernel, scale, anneal, tol, tol_res) run one after the other, each from where the previous
    one ended, sharing the per-pixel set-up and the residuals at the hand-over. Each iteration
    evaluates the model once, at the candidate; a frame whose robust cost went up keeps its
    previous state and damps more. Returns per stage: params, converged (B,), iterations (B,),
    and a function computing a conditioning measure (B,) (> 1: well posed) at the stage's end
    (only evaluated where needed: it costs a pass over the pixels).
    """
    B, P = params.shape
    dt = params.dtype
    dev = params.device
    eye = torch.eye(P, dtype=dt, device=dev)
    fixed = ~free
    fixed_rc = fixed.unsqueeze(-1) | fixed.unsqueeze(-2)
    eye_fixed = (eye * fixed.unsqueeze(-1)).expand(B, P, P)
    n_sel = sel.sum(1).clamp_min(1)
    mom = _moments(pts).to(dt)
    pxy = pts[:, :2]
    # the observed flow's target point: the residual is then one subtraction per evaluation
    target = obs if velocity else pxy + obs

    def residuals(p: Tensor):
        M, dM, ray_row = jac_fn(K, Kinv, p, ray=True)
        q = torch.cat([M, ray_row], dim=1) @ pts
        qz = q[:, 2]
        if velocity:
            use = sel & (q[:, 3] > 0)
            inv_z = None
            proj = pxy
            r = torch.addcmul(q[:, :2], pxy, qz.unsqueeze(1), value=-1.0) - target
        else:
            use = sel & (q[:, 3] > 0) & (qz > 1e-9)
            # in place on the fresh products (q is ours): each per-pixel temporary costs a pass
            inv_z = torch.where(use, qz, 1.0).reciprocal_()
            proj = q[:, :2].mul_(inv_z.unsqueeze(1))
            r = proj - target
        r2 = torch.mul(r[:, 0], r[:, 0]).addcmul_(r[:, 1], r[:, 1])
        r2 = torch.where(use, r2, 0.0)
        return r, r2, use, (dM, proj, inv_z)

    def cost(r2: Tensor, use: Tensor, s: Tensor, kind: str) -> Tensor:
        # a mask pixel where the model is undefined costs as much as a far outlier, so that the
        # fit cannot shrink the model's domain to escape its residuals (r2 is 0 there: ρ(0) = 0)
        rho = _cost_sum(r2, s, kind)
        return (rho + far_cost * (n_sel - use.sum(1))) / n_sel

    def normal_equations(r: Tensor, r2: Tensor, use: Tensor, lin, s: Tensor, kind: str):
        w = robust_weight(r2, s.unsqueeze(-1), kind).mul_(use)
        dM, proj, inv_z = lin
        A, g = _normal_equations(dM, pts, mom, proj, inv_z, w, r)
        A = torch.where(fixed_rc, eye_fixed, A)  # fixed parameters: identity rows, no gradient
        g = torch.where(fixed, 0.0, g)
        return A, g, w

    def scaled(A: Tensor) -> tuple[Tensor, Tensor]:
        diag = A.diagonal(dim1=-2, dim2=-1)
        # a relative floor: a direction the data do not see (roll without motion) must not be
        # blown up to unit size by the Marquardt scaling
        sc = torch.maximum(diag, 1e-12 * diag.amax(-1, keepdim=True)).clamp_min(1e-300).sqrt()
        return A / (sc.unsqueeze(-1) * sc.unsqueeze(-2)), sc

    def conditioning(r: Tensor, r2: Tensor, use: Tensor, lin, s: Tensor, kind: str) -> Tensor:
        A, g, w = normal_equations(r, r2, use, lin, s, kind)
        An, _ = scaled(A)
        # the smallest eigenvalue of the scaled normal matrix (collinear parameters), and of the
        # unscaled one per unit weight (a parameter the flow barely depends on: (px per unit of
        # parameter)², parameters being radians or d/h)
        wsum = w.sum(1).clamp_min(1e-300)
        Ab = torch.where(fixed_rc, eye_fixed, A / wsum.reshape(B, 1, 1))
        eig = torch.linalg.eigvalsh(torch.stack([An, Ab]))[..., 0]
        return torch.minimum(eig[0] / 1e-9, eig[1] / 1e-6)

    r, r2, use, lin = residuals(params)
    out = []
    for kind, scale, anneal, tol, tol_res in stages:
        lam = torch.full((B,), 1e-4, dtype=dt, device=dev)
        done = torch.zeros(B, dtype=torch.bool, device=dev)
        iters = torch.zeros(B, dtype=torch.long, device=dev)
        s_eff = torch.full((B,), float(scale), dtype=dt, device=dev)
        if anneal:
            med = torch.nanmedian(torch.where(use, r2, float("nan")), dim=1).values
            s_eff = torch.maximum(s_eff, 3.0 * torch.nan_to_num(med, nan=0.0).sqrt())
        far_cost = _robust_cost(1e4 * s_eff * s_eff, s_eff, kind)
        c = cost(r2, use, s_eff, kind)
        A, g, w = normal_equations(r, r2, use, lin, s_eff, kind)
        annealing = anneal  # some frame's kernel scale may still be above ``scale``
        for it in range(max_iter):
            An, sc = scaled(A)
            delta = -torch.linalg.solve(An + lam.reshape(B, 1, 1) * eye, (g / sc).unsqueeze(-1)).squeeze(-1) / sc
            delta = torch.where(fixed | done.unsqueeze(-1), 0.0, delta)
            delta = torch.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0)
            cand = params + delta
            rc, r2c, usec, linc = residuals(cand)
            c1 = cost(r2c, usec, s_eff, kind)
            ok = torch.isfinite(c1) & (c1 <= c) & ~done
            if tol_res > 0:
                # below resolution: the step moved the model flow (RMS over the points) by at
                # most tol_res times the robust RMS residual, below the estimate's own
                # uncertainty (of the order of RMS sqrt(parameters / points)); with exact data
                # the residual goes to 0 and the parameter tolerance decides
                moved = (rc - r).square_().sum(1).mul_(use).sum(1)
                spread = (w * r2).sum(1) / w.sum(1).clamp_min(1e-300)
                resolved = ok & (moved <= (tol_res * tol_res) * spread * use.sum(1))
            else:
                resolved = torch.zeros_like(ok)
            if bool(ok.all()):  # the common case: no per-frame selection (no copies)
                params, r, r2, use, lin = cand, rc, r2c, usec, linc
            else:
                params = torch.where(ok.unsqueeze(-1), cand, params)
                r = torch.where(ok.reshape(B, 1, 1), rc, r)
                r2 = torch.where(ok.unsqueeze(-1), r2c, r2)
                use = torch.where(ok.unsqueeze(-1), usec, use)
                lin = tuple(None if x is None else torch.where(ok.reshape(B, *[1] * (x.dim() - 1)), xc, x)
                            for xc, x in zip(linc, lin))
            active = ~done
            iters += active.long()
            # converged: a negligible step (accepted, or rejected while nearly undamped: at
            # rounding level the cost can tick up) or a negligible relative decrease of the cost
            tiny = (delta.abs() <= tol * (1.0 + params.abs())).all(-1)
            small = (tiny & (ok | (lam <= 1e-2))) | (ok & (c - c1 <= tol * c)) | resolved
            c = torch.where(ok, c1, c)
            lam = torch.where(ok, (lam / 3.0).clamp_min(1e-12), lam * 8.0)
            stuck = ~ok & (lam > 1e8)
            # (done | (active & x) is done | x: a frame that is not active is done already)
            if annealing:
                at_scale = s_eff <= scale * (1 + 1e-12)
                done = done | (at_scale & (small | stuck))
                # the scales only come down to ``scale``: once all are there, they stay
                annealing = not bool(at_scale.all())
                if annealing:
                    s_eff = torch.maximum(torch.full_like(s_eff, float(scale)), s_eff * 0.5)
                    far_cost = _robust_cost(1e4 * s_eff * s_eff, s_eff, kind)
                    c = cost(r2, use, s_eff, kind)
            else:
                done = done | small | stuck
            if bool(done.all()):
                break
            A, g, w = normal_equations(r, r2, use, lin, s_eff, kind)
        out.append((params, done, iters, functools.partial(conditioning, r, r2, use, lin, s_eff, kind)))
    return out


# relative step / cost-decrease tolerance of the robust stage when a polish follows it
_ROBUST_STAGE_TOL = 1e-4
# Resolution tolerance: an accepted step that moves the model flow by at most this fraction of
# the robust RMS residual (RMS over the points) ends a stage. The estimate's own uncertainty is
# of the order of that RMS times sqrt(parameters / points) (3 and 8192: 2 %), so steps below
# 1 % change nothing the data can resolve; the robust stage before a polish only has to land
# in the polish's basin (10 %).
# With exact data the residual goes to 0 and ``tol`` decides (see bench_fit / bench_refine).
_RESOLUTION_TOL = 0.01
_ROBUST_STAGE_RESOLUTION = 0.1
# the robust stage before a polish runs on an even stride of about this many of the points
_ROBUST_STAGE_POINTS = 2048


def _robust_lm(jac_fn, velocity: bool, K: Tensor, Kinv: Tensor, params: Tensor, free: Tensor,
               pts: Tensor, obs: Tensor, sel: Tensor, *, kind: str, scale: float, max_iter: int,
               tol: float, anneal: bool, polish: bool,
               inlier_threshold: float | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The robust fit, then (``polish``) a few iterations with Tukey's biweight cut at the
    inlier threshold: a kernel with unbounded support (Cauchy, Huber) still lets far outliers
    pull on the estimate; a redescending one started near the answer ignores them."""
    stages = [(kind, scale, anneal, tol, _RESOLUTION_TOL)]
    if polish and kind not in ("tukey", "l2"):
        # the polish moves the estimate by more than the robust stage's last iterations would
        # (it drops the outliers' pull), so that stage only needs to land in the polish's basin:
        # a looser tolerance there saves iterations; the polish converges to ``tol``
        stages = [(kind, scale, anneal, max(tol, _ROBUST_STAGE_TOL), _ROBUST_STAGE_RESOLUTION),
                  ("tukey", 3.0 * scale if inlier_threshold is None else float(inlier_threshold), False, tol,
                   _RESOLUTION_TOL)]
    if len(stages) == 1:
        ((params, done, iters, min_eig),) = _lm(jac_fn, velocity, K, Kinv, params, free, pts, obs, sel,
                                                stages=stages, max_iter=max_iter)
        return params, done, iters, min_eig()
    # the robust stage only has to land in the polish's basin: an even stride of the points does
    # (its statistical error stays far below the polish's cut); the polish uses them all
    k = max(1, pts.shape[-1] // _ROBUST_STAGE_POINTS)
    ((params, done, iters, min_eig),) = _lm(
        jac_fn, velocity, K, Kinv, params, free, pts[..., ::k].contiguous(), obs[..., ::k].contiguous(),
        sel[..., ::k].contiguous(), stages=stages[:1], max_iter=max_iter)
    ((p2, done2, iters2, min_eig2),) = _lm(jac_fn, velocity, K, Kinv, params, free, pts, obs, sel,
                                           stages=stages[1:], max_iter=max_iter)
    # keep the polished estimate only where it converged to a finite answer
    take = done2 & torch.isfinite(p2).all(-1)
    params = torch.where(take.unsqueeze(-1), p2, params)
    cond = min_eig2() if bool(take.all()) else torch.where(take, min_eig2(), min_eig())
    return params, done & (done2 | ~take), iters + iters2, cond


def _finish(flow: Tensor, every: Tensor, counts: Tensor, model: Tensor, model_valid: Tensor,
            scale: float, inlier_threshold: float | None,
            min_points: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Inliers (B, 1, H, W), residual (B,), a per-frame "enough well-spread inliers" flag, and
    the inliers' share of the mask pixels where the model is defined (B,).

    Works on the M mask pixels only (``every``, their sorted flat indices into B·H·W, with
    ``counts`` per frame): gathered once, so no full-size difference, norm or comparison.
    """
    thr = 3.0 * scale if inlier_threshold is None else float(inlier_threshold)
    B, _, H, W = flow.shape
    HW = H * W
    inliers = torch.zeros(B, HW, dtype=torch.bool, device=flow.device)
    n_in, n_use, epe_sum = [], [], []
    start = 0
    # frame by frame: each frame's gathers stay in cache, and a gather along the pixels is much
    # faster on CPU than one take() with (2, M) offsets into the whole batch
    for b, n in enumerate(counts.tolist()):
        idx = every[start:start + n]
        idx = idx - b * HW if b else idx
        start += n
        idx2 = idx.expand(2, -1)
        # in place where the tensors are fresh: a new buffer of this size costs more (page
        # faults of a fresh allocation) than the arithmetic
        diff = model[b].reshape(2, HW).gather(1, idx2).sub_(flow[b].reshape(2, HW).gather(1, idx2))
        epe = torch.hypot(diff[0], diff[1], out=diff[0])  # (vector_norm over 2 is far slower)
        use = model_valid[b].reshape(HW).gather(0, idx)
        inl = torch.le(epe, thr).logical_and_(use)
        inliers[b].scatter_(0, idx, inl)
        # (count_nonzero and masked_fill_: a bool sum or product first converts the flags)
        n_in.append(torch.count_nonzero(inl))
        n_use.append(torch.count_nonzero(use))
        epe_sum.append(_sum64(epe.masked_fill_(inl.logical_not(), 0.0)))
    inliers = inliers.reshape(B, 1, H, W)
    n_in, n_use, epe_sum = torch.stack(n_in), torch.stack(n_use), torch.stack(epe_sum)
    residual = epe_sum / n_in.clamp_min(1)
    # max over a uint8 view: a bool any() along a dimension is ten times slower on CPU
    in8 = inliers.view(torch.uint8)
    n_rows = in8.amax(3).flatten(1).sum(1)
    n_cols = in8.amax(2).flatten(1).sum(1)
    spread = (n_in >= min_points) & (n_rows >= 3) & (n_cols >= 3)
    fraction = n_in / n_use.clamp_min(1)
    return inliers, residual.to(flow.dtype), spread, fraction


def _sum64(x: Tensor, block: int = 1024) -> Tensor:
    """Sum of a 1-D tensor accumulated in float64 (a 0-d tensor), without a float64 copy of it:
    float32 partial sums over blocks of ``block`` (each a few ulp), then those in float64. A
    fresh float64 copy of a mask's worth of values costs more (page faults) than the sum."""
    if x.dtype == torch.float64:
        return x.sum()
    m = x.numel() // block
    tail = x[m * block:].sum(dtype=torch.float64)
    return x[: m * block].view(m, block).sum(1).sum(dtype=torch.float64) + tail if m else tail


def _check_fraction(value: float) -> None:
    if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
        raise ValueError(f"min_inlier_fraction: expected a number in [0, 1], got {value!r}")


def _check_options(robust: str, scale: float, max_iter: int, tol: float, max_points: int | None) -> None:
    if robust not in ROBUST_KERNELS:
        raise ValueError(f"robust: expected one of {ROBUST_KERNELS}, got {robust!r}")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale: expected a finite number > 0 (pixels), got {scale!r}")
    if not (isinstance(max_iter, int) and max_iter >= 1):
        raise ValueError(f"max_iter: expected an int >= 1, got {max_iter!r}")
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise ValueError(f"tol: expected a number > 0, got {tol!r}")
    if max_points is not None and not (isinstance(max_points, int) and max_points >= 16):
        raise ValueError(f"max_points: expected None or an int >= 16, got {max_points!r}")


# -- public API ----------------------------------------------------------------------------------

@torch.no_grad()
def fit_displacement(flow: Tensor, mask: Tensor, camera: Camera, *, fit_roll: bool = True,
                     fit_pitch: bool = False, init: "FitResult | dict | None" = None,
                     valid: Tensor | None = None, robust: str = "cauchy", scale: float = 1.0,
                     max_iter: int = 50, tol: float = 1e-6, max_points: int | None = 8192,
                     inlier_threshold: float | None = None, min_points: int = 30,
                     min_inlier_fraction: float = 0.25, polish: bool = True) -> FitResult:
    """Fit the displacement model (paper eq. 13) to a flow field inside a road mask.

    Args:
        flow: forward flow (B, 2, H, W) in pixels (channel 0 = u), any float dtype.
        mask: road pixels to fit (B, 1, H, W) bool (batch 1 broadcasts).
        camera: intrinsics at the flow's resolution, height (known; only d/h is observable),
            and the mounting roll/pitch used where they are not fitted and as the start.
        fit_roll, fit_pitch: also fit the mounting roll θ / pitch β (radians).
        init: a start (a :class:`FitResult` or a dict with any of x_d, z_d, yaw, roll, pitch);
            default: the linear road-plane fit described in the module docstring.
        valid: optional (B, 1, H, W) bool validity of the flow (e.g. KITTI's); ANDed with mask.
        robust: kernel of the IRLS weights, one of ``ROBUST_KERNELS``; "l2" for plain least squares.
        scale: the kernel's scale in pixels (residuals well above it are down-weighted).
        max_iter, tol: Levenberg–Marquardt iteration cap (per stage) and step / cost-decrease
            tolerance (relative) of the final stage; with ``polish``, the robust stage before it
            stops at max(tol, 1e-4) (the polish then moves the estimate further than that).
            A stage also ends when a step moves the model flow by at most 1 % of the robust RMS
            residual (the robust stage before a polish: 10 %), below what the points resolve;
            with exact data the residual vanishes and ``tol`` decides.
        max_points: at most this many mask pixels per frame enter the iterations (an even,
            deterministic stride over the mask in raster order); None uses all. The model flow,
            inliers and residual are always computed on every mask pixel.
        inlier_threshold: end-point residual in px below which a mask pixel is an inlier
            (default 3 × scale).
        min_points: fewer inliers than this (or inliers on fewer than 3 rows or columns) mark
            the frame as failed.
        min_inlier_fraction: so does an inlier share of the mask (where the model is defined)
            below this: the flow does not look like road motion (e.g. a flow method that failed
            on the road: DIS on the shared KITTI pair gives 13%).
        polish: after the robust fit, iterate with Tukey's biweight cut at the inlier
            threshold, so that far outliers (other vehicles) stop pulling on the estimate.

    Returns:
        :class:`FitResult`; parameters (B,) in float64 if the flow is float64, else the camera's
        dtype promoted with the flow's; ``flow``/``valid``/``inliers`` at (H, W).

    Raises:
        ValueError: wrong shapes, NaN/inf flow inside the mask, bad options. A frame whose
        mask is empty, tiny, on one row, or whose geometry leaves the parameters undetermined
        gets ``success=False`` (its parameters stay finite).

    Example:
        >>> cam = Camera(torch.tensor([[700., 0, 320], [0, 700, 90], [0, 0, 1]], dtype=torch.float64), 1.65)
        >>> flow, valid = displacement_flow(cam, 0.05, 1.0, 0.01, (192, 640))
        >>> fit = fit_displacement(flow, valid, cam)
        >>> round(float(fit.z_d), 6), bool(fit.success)
        (1.0, True)
    """
    _check_options(robust, scale, max_iter, tol, max_points)
    _check_fraction(min_inlier_fraction)
    dims, camera, mask = _check_inputs(flow, mask, camera, valid)
    B, H, W = dims["B"], dims["H"], dims["W"]
    out_dtype = result_dtype(flow, camera.K)
    K, Kinv, h = (t.to(torch.float64) for t in (camera.K, camera.K_inv(), camera.height))
    pts, obs, sel, counts, every = _sample(flow.detach(), mask, max_points)

    roll0 = _init_value(init, "roll", B, camera.roll.to(torch.float64, copy=True))
    pitch0 = _init_value(init, "pitch", B, camera.pitch.to(torch.float64, copy=True))
    # the start needs few points: every k-th of the sample (zero motion where degenerate)
    k = max(1, pts.shape[-1] // 2048)
    lin, _ = _planar_init(K, Kinv, roll0, pitch0, pts[..., ::k], obs[..., ::k], sel[..., ::k])
    a0 = _init_value(init, "x_d", B, lin[:, 0] * h) / h
    b0 = _init_value(init, "z_d", B, lin[:, 1] * h) / h
    yaw0 = _init_value(init, "yaw", B, lin[:, 2])
    params = torch.stack([a0, b0, yaw0, roll0, pitch0], dim=-1)
    free = torch.tensor([True, True, True, bool(fit_roll), bool(fit_pitch)], device=flow.device)
    jac = (_homography_jac if fit_roll or fit_pitch
           else _fixed_mount_homography_jac(K, Kinv, roll0, pitch0))
    params, converged, iters, min_eig = _robust_lm(
        jac, False, K, Kinv, params, free, pts, obs, sel, kind=robust, scale=scale,
        max_iter=max_iter, tol=tol, anneal=init is None, polish=polish,
        inlier_threshold=inlier_threshold)

    finite = torch.isfinite(params).all(-1)
    params = torch.where(finite.unsqueeze(-1), params, torch.stack([a0, b0, yaw0, roll0, pitch0], -1))
    x_d, z_d = params[:, 0] * h, params[:, 1] * h
    yaw, roll, pitch = params[:, 2], params[:, 3], params[:, 4]
    cam_fit = Camera._checked(camera.K.to(out_dtype), camera.height.to(out_dtype), roll.to(out_dtype),
                              pitch.to(out_dtype))
    model, model_valid = _full_flow(_homography_jac(K, Kinv, params)[0], Kinv, roll, pitch, H, W,
                                    out_dtype, velocity=False)
    inliers, residual, spread, fraction = _finish(flow.detach().to(out_dtype), every, counts, model,
                                                  model_valid, scale, inlier_threshold, min_points)
    success = (finite & converged & spread & (min_eig > 1.0) & (counts >= min_points)
               & (fraction >= min_inlier_fraction))
    return FitResult(
        x_d=x_d.to(out_dtype), z_d=z_d.to(out_dtype), yaw=yaw.to(out_dtype),
        roll=roll.to(out_dtype), pitch=pitch.to(out_dtype), flow=model, valid=model_valid,
        inliers=inliers, residual=residual, success=success, camera=cam_fit,
        iterations=iters)


@torch.no_grad()
def fit_velocity(flow: Tensor, mask: Tensor, camera: Camera, wheelbase: Tensor | float, *,
                 fit_roll: bool = True, fit_pitch: bool = False,
                 init: "VelocityFitResult | dict | None" = None, valid: Tensor | None = None,
                 robust: str = "cauchy", scale: float = 10.0, max_iter: int = 50,
                 tol: float = 1e-6, max_points: int | None = 8192,
                 inlier_threshold: float | None = None, min_points: int = 30,
                 min_inlier_fraction: float = 0.25, polish: bool = True) -> VelocityFitResult:
    """Fit the velocity model (paper eq. 21) to a flow field in pixels per second.

    Args:
        flow: flow (B, 2, H, W) in px/s (a displacement flow divided by the frame interval).
        mask, camera, valid, robust, max_iter, tol, max_points, inlier_threshold, min_points,
            min_inlier_fraction, polish: as in :func:`fit_displacement`.
        wheelbase: axle distance l in metres (> 0), float or (B,): only converts the fitted yaw
            rate into a steering angle δ_f = atan(φ̇ l / v_r).
        fit_roll, fit_pitch: also fit the mounting roll / pitch (radians).
        init: a start (a :class:`VelocityFitResult` or a dict with any of speed, steering (needs
            wheelbase), yaw_rate, roll, pitch); default: the linear fit with the mounting fixed.
        scale: the robust kernel's scale in px/s (default 10 px/s: 1 px at 10 Hz).

    Returns:
        :class:`VelocityFitResult` (speed m/s, steering rad, yaw_rate rad/s, ...).
    """
    _check_options(robust, scale, max_iter, tol, max_points)
    _check_fraction(min_inlier_fraction)
    dims, camera, mask = _check_inputs(flow, mask, camera, valid)
    B, H, W = dims["B"], dims["H"], dims["W"]
    out_dtype = result_dtype(flow, camera.K)
    if isinstance(wheelbase, Tensor):
        check_float_tensor(wheelbase, "wheelbase")
        wb = wheelbase.detach().to(torch.float64, copy=True).reshape(-1)
    else:
        if isinstance(wheelbase, bool) or not isinstance(wheelbase, (int, float)):
            raise TypeError(f"wheelbase: expected a float or a (B,) tensor, got {type(wheelbase).__name__}")
        wb = torch.tensor([float(wheelbase)], dtype=torch.float64)
    if wb.numel() not in (1, B):
        raise ValueError(f"wheelbase: expected batch 1 or {B}, got {wb.numel()} values")
    check_finite(wb, "wheelbase")
    check_positive(wb, "wheelbase")
    wb = wb.to(flow.device).expand(B)
    K, Kinv, h = (t.to(torch.float64) for t in (camera.K, camera.K_inv(), camera.height))
    pts, obs, sel, counts, every = _sample(flow.detach(), mask, max_points)

    roll0 = _init_value(init, "roll", B, camera.roll.to(torch.float64, copy=True))
    pitch0 = _init_value(init, "pitch", B, camera.pitch.to(torch.float64, copy=True))
    lin, _ = _velocity_init(K, Kinv, roll0, pitch0, pts, obs, sel, robust, scale)
    s0 = _init_value(init, "speed", B, lin[:, 0] * h) / h
    w_default = lin[:, 1]

    def given(name: str) -> bool:
        value = init.get(name) if isinstance(init, dict) else getattr(init, name, None)
        return value is not None

    if init is not None and given("steering") and not given("yaw_rate"):
        # a start given as a steering angle: its yaw rate at the start speed
        steer = _init_value(init, "steering", B, w_default)
        w_default = s0 * h * torch.tan(steer) / wb
    w0 = _init_value(init, "yaw_rate", B, w_default)
    params = torch.stack([s0, w0, roll0, pitch0], dim=-1)
    free = torch.tensor([True, True, bool(fit_roll), bool(fit_pitch)], device=flow.device)
    params, converged, iters, min_eig = _robust_lm(
        _velocity_jac, True, K, Kinv, params, free, pts, obs, sel, kind=robust, scale=scale,
        max_iter=max_iter, tol=tol, anneal=init is None, polish=polish,
        inlier_threshold=inlier_threshold)
    finite = torch.isfinite(params).all(-1)
    params = torch.where(finite.unsqueeze(-1), params, torch.stack([s0, w0, roll0, pitch0], -1))
    speed, yaw_rate, roll, pitch = params[:, 0] * h, params[:, 1], params[:, 2], params[:, 3]
    moving = speed.abs() > 1e-12
    steering = torch.where(moving, torch.atan(yaw_rate * wb / torch.where(moving, speed, torch.ones_like(speed))),
                           torch.zeros_like(speed))
    cam_fit = Camera._checked(camera.K.to(out_dtype), camera.height.to(out_dtype), roll.to(out_dtype),
                              pitch.to(out_dtype))
    # evaluate G directly: a steering of ±π/2 (a yaw rate at zero speed) is outside velocity_flow
    model, model_valid = _full_flow(_velocity_jac(K, Kinv, params)[0], Kinv, roll, pitch, H, W,
                                    out_dtype, velocity=True)
    inliers, residual, spread, fraction = _finish(flow.detach().to(out_dtype), every, counts, model,
                                                  model_valid, scale, inlier_threshold, min_points)
    success = (finite & converged & spread & (min_eig > 1.0) & (counts >= min_points)
               & (fraction >= min_inlier_fraction))
    return VelocityFitResult(
        speed=speed.to(out_dtype), steering=steering.to(out_dtype), yaw_rate=yaw_rate.to(out_dtype),
        roll=roll.to(out_dtype), pitch=pitch.to(out_dtype), flow=model, valid=model_valid,
        inliers=inliers, residual=residual, success=success, camera=cam_fit,
        iterations=iters, wheelbase=wb.to(out_dtype))


def _full_flow(M: Tensor, Kinv: Tensor, roll: Tensor, pitch: Tensor, H: int, W: int,
               dtype: torch.dtype, velocity: bool) -> tuple[Tensor, Tensor]:
    """The model flow and validity on the full (H, W) grid from the fitted 3×3 map (float64),
    evaluated in ``dtype`` (what :func:`displacement_flow` / :func:`velocity_flow` compute)."""
    ray_row = (mounting_matrix(roll, pitch).transpose(-1, -2) @ Kinv)[:, 1:2, :]
    return _flow_from_matrix(M.to(dtype), ray_row.to(dtype), (H, W), M.shape[0], velocity=velocity)
