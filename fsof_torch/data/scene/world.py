"""A configured scene: road, ego poses, objects near the ego vehicle, camera poses and the
value-noise tables of its textures.

The camera at frame k (time τ = k dt) sees ``p_cam = A (p_world - c)`` with

    A = R_roll(θ) R_pitch(β + α) R_ψ,    c = G - H n

where ψ is the heading of the planar ego motion, (x, z) its position and G = (x, h - g(z), z) the
road point under it (a grade needs a straight road along z and no yaw, so the vehicle heads along
the road); n = (0, 1, g'(z)) / sqrt(1 + g'²) the road's downward unit normal at G and
α = atan g'(z) its slope, by which the vehicle pitches; θ = roll + body roll offset and
β = pitch + body pitch offset the camera's attitude relative to the road's tangent plane at G,
H = h + body height offset its height over that plane. On a level road α = 0 and G = (x, h, z).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ...geometry.camera import Camera, mounting_matrix, pitch_matrix
from .config import SceneConfig, traffic_speed
from .motion import BodyMotion, ego_poses, motion_from_config, rot_y
from .objects import BLOCK, SceneObject, block_objects
from .road import Grade, Road


def on_host() -> contextlib.AbstractContextManager:
    """Where the renderer creates its tensors: on the CPU, whatever torch's default device
    (``torch.set_default_device`` or a ``with torch.device(...)`` block); a no-op where that is
    the CPU already."""
    return contextlib.nullcontext() if torch.empty(0).device.type == "cpu" else torch.device("cpu")


@dataclass(frozen=True)
class CameraPose:
    """The camera at one frame: ``p_cam = A (p_world - c)`` (A 3×3, c 3, Python floats);
    ``mount`` the attitude relative to the heading frame (A = mount R_ψ); ``roll``, ``pitch``
    (rad) relative to the road's tangent plane under the vehicle and ``height`` (m) over it."""

    A: list
    c: list
    mount: list
    roll: float
    pitch: float
    height: float


class Scene:
    """A configured scene: road, ego poses, objects, texture tables; renders frames."""

    def __init__(self, cfg: SceneConfig, seed: int, dtype: torch.dtype) -> None:
        with on_host():  # (the renderer works on the CPU: its generators are CPU generators)
            self.cfg, self.seed, self.dtype = cfg, int(seed), dtype
            self.motion = motion_from_config(cfg)
            self.road = Road(cfg)
            self.grade = Grade(cfg)
            self.body = BodyMotion(cfg, self.seed)
            # the camera's attitude, centre or height change beyond the planar motion
            self.rides = cfg.has_grade or cfg.has_body_motion
            self.h = float(cfg.height)
            base = Camera(torch.tensor(cfg.K, dtype=torch.float64), cfg.height, cfg.roll, cfg.pitch)
            size = tuple(cfg.size) if cfg.size is not None else tuple(cfg.base_size)
            if size != tuple(cfg.base_size):
                base = base.scaled(size[1] / cfg.base_size[1], size[0] / cfg.base_size[0])
            self.size = size
            self.camera64 = base
            # the mounting as the Camera holds it ((1,) float64), for the poses
            self.roll, self.pitch = base.roll.clone(), base.pitch.clone()
            self.K = base.K[0].tolist()
            self.K_inv = base.K_inv()[0].tolist()
            g = torch.Generator().manual_seed(self.seed * 2 + 1)
            # value-noise lattices: 12 periodic 128 x 128 tables (one per octave and texture)
            lattice = torch.rand(12, 1, 128, 128, generator=g, dtype=torch.float64) * 2 - 1
            self.noise = F.pad(lattice, (0, 1, 0, 1), mode="circular").to(dtype)
            self._poses = ego_poses(self.motion, 1)
            self._camera_poses: dict[int, CameraPose] = {}
            self._blocks: dict[int, list[SceneObject]] = {}

    # -- poses and objects --------------------------------------------------------------------
    def ego_pose(self, k: int) -> tuple[float, float, float]:
        if k >= len(self._poses):
            self._poses = ego_poses(self.motion, k)
        return self._poses[k]

    def blocks(self, b: int) -> list[SceneObject]:
        if b not in self._blocks:
            self._blocks[b] = block_objects(self.cfg, self.seed, b, self.road.kappa)
        return self._blocks[b]

    def object_pose(self, o: SceneObject, k: int) -> tuple[list[float], float]:
        s = o.s0 + o.vs * k * self.motion.dt
        x, z, psi = self.road.to_world(o.e, s)
        if o.reverse:
            psi += math.pi
        # the centre sits `offset` metres along the object's own z axis
        x += o.offset * math.sin(psi)
        z += o.offset * math.cos(psi)
        # on a grade the object keeps its height over the road at its reference point
        y = o.y - self.grade.elevation_at(s) if self.grade.active else o.y
        return [x, y, z], psi

    def objects(self, k: int) -> list[SceneObject]:
        """The objects near the ego vehicle at frame k: arc length from 30 m behind to 220 m ahead
        (less on tight circles, so that one lap never overlaps the next)."""
        cx, cz, psi = self.ego_pose(k)
        # the ego vehicle heads along the road: at s = ψ / κ, counted on from lap to lap (the
        # angle about the bend's centre wraps at half a lap; the objects of s beyond it must not)
        s_ego = self.road.s_of(cx, cz, near=psi / self.road.kappa if self.road.kappa != 0.0 else 0.0)
        back, far = 30.0, 220.0
        if self.road.kappa != 0.0:
            # on a closed circle keep less than one lap in view, or laps would overlap
            span = max(2 * math.pi / abs(self.road.kappa) - 25.0, 20.0)
            back = min(back, 0.25 * span)
            far = min(far, span - back)
        lo, hi = s_ego - back, s_ego + far
        t = k * self.motion.dt
        vmax = traffic_speed(self.cfg) * 1.5  # the fastest car: 1.3 times the base speed
        b0 = math.floor((lo - vmax * t) / BLOCK)
        b1 = math.floor((hi + vmax * t) / BLOCK)
        out = []
        for b in range(b0, b1 + 1):
            for o in self.blocks(b):
                s = o.s0 + o.vs * t
                if lo - 10 <= s <= hi + 10:
                    out.append(o)
        return out

    # -- camera poses --------------------------------------------------------------------
    def _mounting(self, x: Tensor, z: Tensor, psi: Tensor, tau: Tensor) -> tuple[Tensor, ...]:
        """The camera's attitude relative to the heading frame (3, 3), its centre (3,) in the
        world, and θ, β, H (module docstring) for the planar pose (x, z, ψ) at time τ; (1,)
        float64 inputs, differentiable (:meth:`pose_rates` takes its derivative)."""
        d_pitch, d_roll, d_height = self.body.offsets(tau)
        theta, beta, height = self.roll + d_roll, self.pitch + d_pitch, self.h + d_height
        # the road's slope under the vehicle (ψ = 0 on a graded road: no cross slope)
        q = self.grade.slope(z)
        N = torch.sqrt(1 + q * q)
        mount = mounting_matrix(theta, beta) @ pitch_matrix(torch.atan(q))
        normal = torch.stack([torch.zeros_like(q), torch.ones_like(q), q], dim=-1) / N.unsqueeze(-1)
        ground = torch.stack([x, self.h - self.grade.elevation(z), z], dim=-1)
        centre = ground - height.unsqueeze(-1) * normal
        return mount[0], centre[0], theta[0], beta[0], height[0]

    def _planar_state(self, k: int) -> tuple[Tensor, ...]:
        x, z, psi = self.ego_pose(k)
        return tuple(torch.tensor([v], dtype=torch.float64) for v in (x, z, psi, k * self.motion.dt))

    def pose(self, k: int) -> CameraPose:
        """The camera pose at frame k."""
        if k not in self._camera_poses:
            mount, centre, theta, beta, height = self._mounting(*self._planar_state(k))
            mount = mount.tolist()
            R = rot_y(self.ego_pose(k)[2])
            # Python sums in the order of R_c R_ψ: on a level road without body motion the pose
            # is exactly the planar model's (mount = R_c), to the bit
            A = [[sum(mount[i][m] * R[m][j] for m in range(3)) for j in range(3)] for i in range(3)]
            self._camera_poses = {kk: v for kk, v in self._camera_poses.items() if kk >= k - 2}
            self._camera_poses[k] = CameraPose(A, centre.tolist(), mount, float(theta), float(beta), float(height))
        return self._camera_poses[k]

    def world_to_camera(self, k: int) -> tuple[list[list[float]], list[float]]:
        """(A, c): p_cam = A (p_world - c) at frame k."""
        pose = self.pose(k)
        return pose.A, pose.c

    def pose_rates(self, k: int) -> tuple[Tensor, Tensor]:
        """Time derivatives at frame k of the camera's attitude relative to the heading frame
        (3, 3, per s) and of its centre (3,, m/s, world), along the instantaneous ego motion
        (speed v along the heading, yaw rate ω) and the body oscillation; float64. The same in
        every grad mode: under ``torch.no_grad()`` or ``torch.inference_mode()`` (an evaluation
        loop) the derivative is taken with autograd switched on locally, on tensors made here."""
        mot = self.motion
        psi = self.ego_pose(k)[2]
        rates = (mot.speed * math.sin(psi), mot.speed * math.cos(psi), mot.yaw_rate, 1.0)
        # d/ds of the pose along the motion (x + s ẋ, z + s ż, ψ + s ω, τ + s) at s = 0, by
        # reverse mode twice: g(w) = Jᵀ w, then dg/dw = J (forward-mode AD would load torch's
        # TorchScript decompositions on first use)
        with torch.inference_mode(False), torch.enable_grad():
            s = torch.zeros(1, dtype=torch.float64, requires_grad=True)
            mount, centre = self._mounting(*(p + r * s for p, r in zip(self._planar_state(k), rates)))[:2]
            out = torch.cat([mount.reshape(-1), centre])
            w = torch.zeros_like(out, requires_grad=True)
            (g,) = torch.autograd.grad(out, s, grad_outputs=w, create_graph=True)
            (rate,) = torch.autograd.grad(g, w, torch.ones_like(g))
        return rate[:9].reshape(3, 3), rate[9:]

    def camera(self) -> Camera:
        """The calibrated camera in the scene's dtype, a copy of its own per call (a pair's camera
        is the caller's to change)."""
        return self.camera64.to(self.dtype, copy=True)
