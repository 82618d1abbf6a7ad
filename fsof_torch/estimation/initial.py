"""Initial guesses for the road fits, without a prior: robust fits of models that are linear in
their unknowns, by the library's one solver (Cauchy kernel, annealed from the spread of the
zero-motion residuals).

- :func:`planar_motion`, the paper's model: with the camera's attitude over the road fixed (its
  roll and pitch), a road pixel and its flow target back-project onto the road plane, where the
  paper's motion is a planar rigid motion ``x' = R_φ (x - d/h)`` on points (X/h, 1, Z/h). Leaving
  cos φ and sin φ free makes it linear in (cos φ, sin φ, t_x, t_z): a 2-D similarity.
- :func:`homography_dlt`, the models with as many parameters as a homography: the direct linear
  transform in calibrated coordinates, whose unknowns are the entries of G = K⁻¹ H K - I (G's
  last entry held at 0: the homography's scale).
- :func:`planar_start`, a predicted flow's planar motion: :func:`planar_motion` on an even
  sample of the mask's pixels, in metres (the start a network's flow gives the image fit).

Both residuals are scaled back into roughly pixel units (by the focal length, and for the plane
by the ray's height), so the kernel's scale is in pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._check import (all_finite, batch_choices, check_float_tensor, check_has_values, check_int, check_mask,
                      check_same_device, check_shape)
from ..geometry.camera import Camera, mounting_matrix
from .sampling import gather_pixels, pixel_coordinates, sample_mask
from .solver import Evaluation, Solution, solve, spd_solve

__all__ = ["LinearProblem", "planar_motion", "planar_start", "homography_dlt"]


class LinearProblem:
    """Residuals linear in the parameters, r = θᵀ J - target, with a constant J, for the solver.

    Args:
        J: (B, P, R, N) the derivatives of R residual components at N points by P parameters.
        target: (B, R, N); use: (B, N) bool, the points that count.
    """

    def __init__(self, J: Tensor, target: Tensor, use: Tensor) -> None:
        B, P, R, N = J.shape
        self.J, self.target, self.use = J.reshape(B, P, R * N), target, use
        self.count = use.sum(1)

    def evaluate(self, params: Tensor) -> Evaluation:
        r = torch.bmm(params.unsqueeze(1), self.J).reshape(self.target.shape) - self.target
        return Evaluation(r.square().sum(1), self.use, r)

    def normal_equations(self, ev: Evaluation, w: Tensor) -> tuple[Tensor, Tensor]:
        B = w.shape[0]
        Jw = self.J * w.repeat(1, ev.residual.shape[1]).unsqueeze(1)
        return torch.bmm(Jw, self.J.transpose(1, 2)), torch.bmm(Jw, ev.residual.reshape(B, -1, 1)).squeeze(-1)


def _robust_linear_fit(J: Tensor, target: Tensor, use: Tensor, scale: float, iterations: int) -> Solution:
    """A robust fit of a :class:`LinearProblem`: least squares in one solve (the first step of
    an annealed fit from any start), then ``iterations`` more with the Cauchy kernel annealed
    from the spread of its residuals (a fixed budget: no host read)."""
    problem = LinearProblem(J, target, use)
    B, P = J.shape[:2]
    A, g = problem.normal_equations(problem.evaluate(J.new_zeros(B, P)), use.to(J.dtype))
    start = spd_solve(A, g.neg().unsqueeze(-1)).squeeze(-1).nan_to_num_(0.0, 0.0, 0.0)  # (0 where singular)
    return solve(problem, start, kernel="cauchy", scale=scale, anneal=True, max_iter=iterations, check_every=None)


def _real_points(pts: Tensor, flow: Tensor, sel: Tensor) -> tuple[Tensor, Tensor]:
    """``pts`` and ``flow`` zeroed at the points that are not real (``sel`` False): padding may hold
    anything, NaN too, which a zero weight does not keep out of the normal equations' sums (0 · NaN
    is NaN) and which would make the whole frame degenerate."""
    real = sel.unsqueeze(1)
    return torch.where(real, pts, 0.0), torch.where(real, flow, 0.0)


def planar_motion(K: Tensor, K_inv: Tensor, roll: Tensor, pitch: Tensor, pts: Tensor, flow: Tensor,
                  sel: Tensor, *, scale: float = 2.0, iterations: int = 2) -> tuple[Tensor, Tensor]:
    """(x_d/h, z_d/h, yaw) (B, 3) of the paper's motion from flow at road pixels.

    Args:
        K, K_inv: (B, 3, 3) float64; roll, pitch: (B,) the camera's attitude over the road.
        pts: (B, 3, N) homogeneous pixels; flow: (B, 2, N) their flow (px); sel: (B, N) real points
            (the others, padding, may hold anything, NaN too).
        scale: the Cauchy kernel's final scale (px); iterations: the solver's budget after the
            least-squares start (a start needs only a few).

    Returns:
        ``(params (B, 3), good (B,))``: good is False where the problem was degenerate (too few
        points below the horizon, collinear points); those frames get zero motion.
    """
    B = pts.shape[0]
    pts, flow = _real_points(pts, flow, sel)
    A = torch.bmm(mounting_matrix(roll, pitch).expand(B, 3, 3).transpose(1, 2), K_inv)  # pixel -> road-aligned ray
    x = torch.bmm(A, pts)
    xp = torch.bmm(A, torch.cat([pts[:, :2] + flow, pts[:, 2:]], dim=1))
    ok = sel & (x[:, 1] > 1e-6) & (xp[:, 1] > 1e-6)
    # road points (X, 1, Z) = x / x_y; ground errors times f_x x_y are about pixel errors: the
    # unknowns' coefficients f_x (x_x, x_z, x_y) and the targets f_x x_y (x'_x, x'_z) / x'_y
    Xf, f, Zf = (x * K[:, 0:1, 0:1]).unbind(1)
    zero = torch.zeros_like(f)
    # x' = c X - s Z + t_x, z' = s X + c Z + t_z: (B, P=4, R=2, N)
    J = torch.stack([Xf, Zf, -Zf, Xf, f, zero, zero, f], dim=1).reshape(B, 4, 2, -1)
    target = xp[:, 0::2] * (f / torch.where(ok, xp[:, 1], 1.0)).unsqueeze(1)
    sol = _robust_linear_fit(J, target, ok, scale, iterations)
    c, s, tx, tz = sol.params.unbind(-1)
    yaw = torch.atan2(s, c)
    cn, sn = torch.cos(yaw), torch.sin(yaw)
    out = torch.stack([-(cn * tx + sn * tz), -(-sn * tx + cn * tz), yaw], dim=-1)
    good = sol.well_conditioned(1e-9) & torch.isfinite(out).all(-1) & (ok.sum(1) >= 4)
    return torch.where(good.unsqueeze(-1), out, 0.0), good


def homography_dlt(K: Tensor, K_inv: Tensor, pts: Tensor, flow: Tensor, sel: Tensor, *,
                   scale: float = 2.0, iterations: int = 4) -> Tensor:
    """The homography (B, 3, 3) taking pixels p̃ to p + flow: a robust direct linear transform.

    In calibrated coordinates x = K⁻¹ p̃ and x' = K⁻¹ (p̃ + flow), the unknowns are the eight
    entries δ of G = K⁻¹ H K - I (its last one 0), and the residuals
    ``(g₁ - x'_x g₃) · x`` and ``(g₂ - x'_y g₃) · x`` (g_k the rows of I + δ) are linear in them;
    times the focal length they are about pixels for the small motions between frames.

    Args:
        K, K_inv: (B, 3, 3) float64; pts: (B, 3, N) homogeneous pixels; flow: (B, 2, N) their
            flow (px); sel: (B, N) real points (the others, padding, may hold anything, NaN too).
        scale: the Cauchy kernel's final scale (px); iterations: the solver's budget after the
            least-squares start.

    Returns:
        (B, 3, 3), the identity where the fit is not finite or not determined (fewer than four
        points, or points that do not fix the eight entries: all on one row or one line).
    """
    B = pts.shape[0]
    pts, flow = _real_points(pts, flow, sel)
    x = torch.bmm(K_inv, pts)
    xp = torch.bmm(K_inv, torch.cat([pts[:, :2] + flow, pts[:, 2:]], dim=1))
    f = K[:, 0, 0].reshape(B, 1, 1)
    xs, xps = x * f, xp[:, :2] * f
    u, v, one = xs.unbind(1)
    zero = torch.zeros_like(u)
    X, Y = xp[:, 0], xp[:, 1]
    # r = (x_x + δ₁·x - x'_x (1 + δ₃·x), x_y + δ₂·x - x'_y (1 + δ₃·x)) f, δ₃₃ = 0: (B, P=8, R=2, N)
    J = torch.stack([u, zero, v, zero, one, zero, zero, u, zero, v, zero, one,
                     -X * u, -Y * u, -X * v, -Y * v], dim=1).reshape(B, 8, 2, -1)
    target = xps - xs[:, :2]
    sol = _robust_linear_fit(J, target, sel, scale, iterations)
    G = torch.cat([sol.params, torch.zeros_like(sol.params[:, :1])], dim=-1).reshape(B, 3, 3)
    G = G + torch.eye(3, dtype=G.dtype, device=G.device)
    H = torch.bmm(torch.bmm(K, G), K_inv)
    eye = torch.eye(3, dtype=H.dtype, device=H.device).expand_as(H)
    # (a system that does not fix H leaves it to rounding, which differs with the batch's other frames)
    good = torch.isfinite(H).all(-1).all(-1) & sol.well_conditioned(1e-9) & (sel.sum(1) >= 4)
    return torch.where(good[:, None, None], H, eye)


def planar_start(flow: Tensor, mask: Tensor, camera: Camera, points: int = 2048) -> dict[str, Tensor]:
    """A quick start from a predicted flow: x_d, z_d, yaw (B,) of the planar motion of its
    back-projected road points (:func:`planar_motion`, robust), at the camera's roll and pitch;
    zero motion where that is degenerate.

    Args:
        flow: (B, 2, H, W) float, forward flow in pixels; pixels where it is NaN or inf are left
            out of the mask.
        mask: (B, 1, H, W) bool road pixels (batch 1 is broadcast).
        camera: the flow's camera (batch 1 or B), taken to the flow's device (the mask must be on
            it: else a ValueError names the mask).
        points: how many of each frame's mask pixels to sample (evenly).

    Returns:
        ``{"x_d", "z_d", "yaw"}`` (B,) float64 (a start for the solvers, which work in float64).
    """
    check_float_tensor(flow, "flow")
    dims = check_shape(flow, "flow", ("B", 2, "H", "W"))
    B, H, W = dims["B"], dims["H"], dims["W"]
    check_mask(mask, "mask")
    if mask.dim() != 4 or mask.shape[0] not in (1, B) or tuple(mask.shape[1:]) != (1, H, W):
        raise ValueError(f"mask: expected shape ({B}, 1, {H}, {W}) (the flow's; batch 1 is broadcast), "
                         f"got {tuple(mask.shape)}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch {batch_choices(B)} (the flow's B), got {camera.batch_size}")
    points = check_int(points, "points", minimum=1)
    check_same_device({"flow": flow, "mask": mask})  # (named before torch's error from inside would come)
    check_has_values(flow, "flow", "to start a fit (the start is a fit)")
    if B == 0:
        raise ValueError(f"flow: expected a non-empty batch, got shape {tuple(flow.shape)}")
    # (a NaN or inf would spread through the normal equations and zero the whole frame's start;
    # the per-pixel test only where the flow holds one: all_finite is one pass and one host read,
    # none for the caller's very tensor where it is known finite)
    finite = all_finite(flow)
    flow = flow.detach()
    mask = mask.expand(B, 1, H, W)
    if not finite:
        mask = mask & torch.isfinite(flow).all(1, keepdim=True)
    pts = sample_mask(mask, points)
    xy = pixel_coordinates(pts.pix, W)
    f = torch.where(pts.sel.unsqueeze(1), gather_pixels(flow, pts.pix).to(torch.float64), 0.0)
    cam = camera.to(device=flow.device, dtype=torch.float64).expand(B)  # (the camera follows the flow's device)
    lin, _ = planar_motion(cam.K, cam.K_inv(), cam.roll, cam.pitch, xy, f, pts.sel)
    h = cam.height
    return {"x_d": lin[:, 0] * h, "z_d": lin[:, 1] * h, "yaw": lin[:, 2]}
