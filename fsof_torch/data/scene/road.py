"""Road coordinates: lateral offset e (m, + right of the centre line) and arc length s (m) of a
straight road or of an arc of constant curvature concentric with the ego vehicle's path."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .config import SceneConfig
from .motion import Motion


class Road:
    """A straight road or an arc of constant curvature; lateral e (m, + right) and arc length s."""

    def __init__(self, cfg: SceneConfig, motion: Motion) -> None:
        self.e0 = cfg.lane_width / 2  # the ego vehicle drives in the centre of the right lane
        # the ego path's curvature; explicit odometry without translation gets a straight road
        kappa_v = math.tan(motion.steering) / motion.wheelbase
        if cfg.x_d is not None:
            arc = motion.speed * motion.dt
            kappa_v = motion.yaw / arc if abs(arc) > 1e-3 else 0.0
        kappa_v = max(-1 / 8.0, min(1 / 8.0, kappa_v))  # keep the lane a drivable arc (radius >= 8 m)
        # concentric with the ego vehicle's circle: 1/κ_road = 1/κ_vehicle + e0
        self.kappa = 0.0 if abs(kappa_v) < 1e-9 else 1.0 / (1.0 / kappa_v + self.e0)
        if self.kappa != 0.0:
            self.R = 1.0 / abs(self.kappa)
            self.sigma = 1.0 if self.kappa > 0 else -1.0
            self.cx = -self.e0 + 1.0 / self.kappa

    def to_road(self, x: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
        """(e, s) of world points (x, z)."""
        if self.kappa == 0.0:
            return x + self.e0, z
        dx = x - self.cx
        r = torch.sqrt(dx * dx + z * z)
        e = self.sigma * (self.R - r)
        s = self.R * torch.atan2(z, -self.sigma * dx)
        return e, s

    def lateral(self, x: Tensor, z: Tensor) -> Tensor:
        if self.kappa == 0.0:
            return x + self.e0
        dx = x - self.cx
        return self.sigma * (self.R - torch.sqrt(dx * dx + z * z))

    def to_world(self, e: float, s: float) -> tuple[float, float, float]:
        """World (x, z) of road coordinates (e, s) and the road's heading ψ there."""
        if self.kappa == 0.0:
            return e - self.e0, s, 0.0
        a = s / self.R
        r = self.R - self.sigma * e
        return self.cx - self.sigma * r * math.cos(a), r * math.sin(a), self.kappa * s

    def s_of(self, x: float, z: float) -> float:
        if self.kappa == 0.0:
            return z
        return self.R * math.atan2(z, -self.sigma * (x - self.cx))

    def boundary_hit(self, e_b: Tensor, ox: float, oz: float, dx: Tensor, dz: Tensor,
                     t_lo: Tensor, t_hi: Tensor) -> Tensor:
        """Ray parameter in [t_lo, t_hi] where the ray's footprint crosses lateral e = e_b."""
        if self.kappa == 0.0:
            safe = torch.where(dx.abs() > 1e-12, dx, torch.full_like(dx, 1e-12))
            t = (e_b - self.e0 - ox) / safe
        else:
            r_b = self.R - self.sigma * e_b
            px = ox - self.cx
            a = dx * dx + dz * dz
            b = 2 * (dx * px + dz * oz)
            c = px * px + oz * oz - r_b * r_b
            root = torch.sqrt((b * b - 4 * a * c).clamp_min(0))
            t1 = (-b - root) / (2 * a)
            t2 = (-b + root) / (2 * a)
            mid = 0.5 * (t_lo + t_hi)
            t = torch.where((t1 - mid).abs() < (t2 - mid).abs(), t1, t2)
        return torch.minimum(torch.maximum(t, t_lo), t_hi)

