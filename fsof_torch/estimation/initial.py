"""Initial guesses for the road fits, without a prior: the planar motion of back-projected points.

With the camera's attitude over the road fixed (its roll and pitch), a road pixel and its flow
target back-project onto the road plane, where the paper's motion is a planar rigid motion:
``x' = R_φ (x - d/h)`` on points (X/h, 1, Z/h). Leaving cos φ and sin φ free makes it linear in
(cos φ, sin φ, t_x, t_z): a 2-D similarity, fitted robustly (Cauchy, annealed) by the library's one
solver. Residuals are scaled back into roughly pixel units (by f_x times the ray's height), so
the kernel's scale is in pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..geometry.camera import mounting_matrix
from .solver import ResidualProblem, solve

__all__ = ["planar_motion", "homography_dlt"]


def planar_motion(K: Tensor, K_inv: Tensor, roll: Tensor, pitch: Tensor, pts: Tensor, flow: Tensor,
                  sel: Tensor, *, scale: float = 2.0, iterations: int = 3) -> tuple[Tensor, Tensor]:
    """(x_d/h, z_d/h, yaw) (B, 3) of the paper's motion from flow at road pixels.

    Args:
        K, K_inv: (B, 3, 3) float64; roll, pitch: (B,) the camera's attitude over the road.
        pts: (B, 3, N) homogeneous pixels; flow: (B, 2, N) their flow (px); sel: (B, N) real points.
        scale: the Cauchy kernel's final scale (px); iterations: the solver's budget.

    Returns:
        ``(params (B, 3), good (B,))``: good is False where the problem was degenerate (too few
        points below the horizon, collinear points); those frames get zero motion.
    """
    B = pts.shape[0]
    A = mounting_matrix(roll, pitch).transpose(-1, -2) @ K_inv   # pixel -> road-aligned ray
    x = A @ pts
    xp = A @ torch.cat([pts[:, :2] + flow, pts[:, 2:]], dim=1)
    ok = sel & (x[:, 1] > 1e-6) & (xp[:, 1] > 1e-6)
    y0 = torch.where(ok, x[:, 1], 1.0)
    y1 = torch.where(ok, xp[:, 1], 1.0)
    X, Z = x[:, 0] / y0, x[:, 2] / y0
    Xp, Zp = xp[:, 0] / y1, xp[:, 2] / y1
    # ground errors times f_x y0 are roughly pixel errors
    f = K[:, 0, 0].unsqueeze(-1) * y0
    one, zero = torch.ones_like(X), torch.zeros_like(X)
    # x' = c X - s Z + t_x, z' = s X + c Z + t_z: (B, P=4, R=2, N)
    J = torch.stack([torch.stack([X, Z], 1), torch.stack([-Z, X], 1), torch.stack([one, zero], 1),
                     torch.stack([zero, one], 1)], dim=1) * f.unsqueeze(1).unsqueeze(1)
    target = torch.stack([Xp, Zp], dim=1) * f.unsqueeze(1)

    Jf = J.reshape(B, 4, -1)

    def residual(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return (theta.unsqueeze(1) @ Jf).reshape(target.shape) - target, J, ok

    start = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=pts.dtype, device=pts.device).expand(B, 4)
    sol = solve(ResidualProblem(residual, ok.sum(1)), start, kernel="cauchy", scale=scale, anneal=True,
                max_iter=iterations, check_every=None)
    c, s, tx, tz = sol.params.unbind(-1)
    yaw = torch.atan2(s, c)
    cn, sn = torch.cos(yaw), torch.sin(yaw)
    out = torch.stack([-(cn * tx + sn * tz), -(-sn * tx + cn * tz), yaw], dim=-1)
    good = sol.well_conditioned(1e-9) & torch.isfinite(out).all(-1) & (ok.sum(1) >= 4)
    return torch.where(good.unsqueeze(-1), out, 0.0), good


def homography_dlt(pts: Tensor, flow: Tensor, sel: Tensor, *, scale: float = 3.0) -> Tensor:
    """The homography (B, 3, 3) taking pixels p̃ to p + flow, by kornia's iteratively re-weighted
    DLT (Gaussian weights of the transfer error, standard deviation ``scale`` px) over the real
    points ``sel``: a start for the models with as many parameters as a homography."""
    from kornia.geometry.homography import find_homography_dlt_iterated

    p1 = pts[:, :2].transpose(1, 2)
    p2 = (pts[:, :2] + flow).transpose(1, 2)
    H = find_homography_dlt_iterated(p1, p2, sel.to(pts.dtype), soft_inl_th=scale, n_iter=5)
    eye = torch.eye(3, dtype=H.dtype, device=H.device).expand_as(H)
    return torch.where(torch.isfinite(H).all(-1).all(-1)[:, None, None], H, eye)
