"""The road's geometry: its coordinates (lateral offset e, m, + right of the centre line, and arc
length s, m) on a straight road or an arc of constant curvature concentric with the ego vehicle's
path, and its vertical profile (the grade) along s."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .config import SceneConfig, path_curvature


class Road:
    """A straight road or an arc of constant curvature; lateral e (m, + right) and arc length s."""

    def __init__(self, cfg: SceneConfig) -> None:
        self.e0 = cfg.lane_width / 2  # the ego vehicle drives in the centre of the right lane
        # the ego path's curvature (0 standing still: scene_config refuses a turn on the spot).
        # scene_config keeps the path's radius >= MIN_TURN_RADIUS and > e0, so the road below bends
        # the way the vehicle turns and the vehicle stays in the centre of its lane
        kappa_v = path_curvature(cfg)
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

    def s_of(self, x: float, z: float, near: float = 0.0) -> float:
        """The arc length s of the world point (x, z): on a bend (a full circle) the s of the lap
        nearest ``near`` (m), unwrapped past the half lap where the angle jumps from π to -π."""
        if self.kappa == 0.0:
            return z
        s = self.R * math.atan2(z, -self.sigma * (x - self.cx))
        lap = 2 * math.pi * self.R
        return s + lap * round((near - s) / lap)

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



class Grade:
    """The road's elevation g(s) (m, up) along the arc length s: the surface is y = h - g(s).

    The grade g'(s) is ``before`` up to ``start``, then changes linearly to ``after`` over
    ``length`` metres (a parabolic vertical curve: a crest when it falls, a dip when it rises),
    and stays there; g(0) = 0, so the ego vehicle starts at the height of a level road.
    All methods take float64 tensors and are differentiable (piecewise polynomials).
    """

    def __init__(self, cfg: SceneConfig) -> None:
        self.before, self.after = float(cfg.grade_before), float(cfg.grade_after)
        self.start, self.length = float(cfg.grade_start), float(cfg.grade_length)
        self.change = self.after - self.before
        self.active = bool(cfg.has_grade)
        self._q0 = float(self._curve(torch.tensor(0.0, dtype=torch.float64)))

    def _curve(self, s: Tensor) -> Tensor:
        """The vertical curve's share of the elevation per unit grade change: 0 before it,
        (s - s0)² / (2 L) on it, s - s0 - L/2 after it."""
        u = (s - self.start).clamp(0.0, self.length)
        return u * u / (2 * self.length) + (s - self.start - self.length).clamp_min(0.0)

    def elevation(self, s: Tensor) -> Tensor:
        """g(s) in metres."""
        return self.before * s + self.change * (self._curve(s) - self._q0)

    def slope(self, s: Tensor) -> Tensor:
        """g'(s), metres of rise per metre."""
        return self.before + self.change * (s - self.start).clamp(0.0, self.length) / self.length

    def elevation_at(self, s: float) -> float:
        """g(s) of a Python float."""
        return float(self.elevation(torch.tensor(s, dtype=torch.float64)))

    def slope_at(self, s: float) -> float:
        """g'(s) of a Python float."""
        return float(self.slope(torch.tensor(s, dtype=torch.float64)))

    def first_hit(self, oy: float, oz: float, dy: Tensor, dz: Tensor, level: float) -> Tensor:
        """Ray parameter t > 0 (float64) where the ray (y, z) = (oy + t dy, oz + t dz) first
        meets the surface y = level - g(z) of a straight road (s = z); inf where it never does.

        Closed form: g is linear before and after the vertical curve and quadratic on it, so on
        each piece the condition is a polynomial of degree <= 2 in t; its roots inside the
        piece's range of z are candidates, the smallest wins.
        """
        dy, dz = dy.double(), dz.double()
        g1, g2, dg, s0, L = self.before, self.after, self.change, self.start, self.length
        base = oy - level - dg * self._q0
        # (a, b, c) of F(t) = y_ray - y_surface = a t² + b t + c on each piece, and its z range
        pieces = (
            (None, dy + g1 * dz, base + g1 * oz, -math.inf, s0),
            (dg * dz * dz / (2 * L), dy + g1 * dz + dg * (oz - s0) * dz / L,
             base + g1 * oz + dg * (oz - s0) ** 2 / (2 * L), s0, s0 + L),
            (None, dy + g2 * dz, base + g2 * oz - dg * (s0 + L / 2), s0 + L, math.inf),
        )
        tol = 1e-7  # metres of z: a root on a piece boundary belongs to both pieces
        best = torch.full_like(dy, math.inf)
        for a, b, c, lo, hi in pieces:
            a = torch.zeros_like(b) if a is None else a
            for t in _quadratic_roots(a, b, torch.as_tensor(c, dtype=torch.float64).expand_as(b)):
                z = oz + t * dz
                ok = (t > 1e-6) & (z >= lo - tol) & (z <= hi + tol)
                best = torch.where(ok, torch.minimum(best, t), best)
        return best


def _quadratic_roots(a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """The real roots of a t² + b t + c (a may be 0: then the one root of b t + c), inf where
    there is none; the cancellation-free form q = -(b + sign(b) sqrt(b² - 4ac)) / 2, roots q / a
    and c / q."""
    disc = b * b - 4 * a * c
    q = -0.5 * (b + torch.copysign(torch.sqrt(disc.clamp_min(0.0)), b))
    inf = torch.full_like(b, math.inf)
    r1 = torch.where((a != 0) & (disc >= 0), q / torch.where(a != 0, a, 1.0), inf)
    r2 = torch.where((q != 0) & (disc >= 0), c / torch.where(q != 0, q, 1.0), inf)
    return r1, r2
