"""The ego vehicle's motion: its planar motion (odometry per pair from the configuration, and the
chain of world poses (c_x, c_z, ψ) of frames 0..k), and the body's oscillation over the road.

A pose (c, ψ) maps world points into a local frame as ``p_local = R_ψ (p_world - c)`` with
``R_ψ = [[cos ψ, 0, -sin ψ], [0, 1, 0], [sin ψ, 0, cos ψ]]`` (:func:`rot_y`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ...geometry.egomotion import ego_motion_from_ackermann
from .config import SceneConfig, arc_length


@dataclass(frozen=True)
class Motion:
    """Per-pair ego motion (constant over the sequence) and the derived velocity description."""

    x_d: float
    z_d: float
    yaw: float
    speed: float
    steering: float
    wheelbase: float
    dt: float

    @property
    def yaw_rate(self) -> float:
        """ψ̇ = v_r tan δ_f / l (rad/s)."""
        return self.speed * math.tan(self.steering) / self.wheelbase


def motion_from_config(cfg: SceneConfig) -> Motion:
    """The per-pair odometry and velocities of a configuration (explicit odometry, or Ackermann
    motion from speed and steering)."""
    if cfg.x_d is not None:
        x_d, z_d, yaw = float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)
        arc = arc_length(x_d, z_d, yaw)
        speed = arc / cfg.dt
        steering = math.atan(cfg.wheelbase * yaw / arc) if arc != 0 else 0.0
        return Motion(x_d, z_d, yaw, speed, steering, float(cfg.wheelbase), float(cfg.dt))
    speed = cfg.speed * cfg.speed_factor
    ego = ego_motion_from_ackermann(torch.tensor([speed], dtype=torch.float64), cfg.steering,
                                    cfg.wheelbase, cfg.dt)
    # floats, as the pair's ``velocity`` documents, whatever number types the configuration holds
    return Motion(float(ego.x_d[0]), float(ego.z_d[0]), float(ego.yaw[0]), float(speed), float(cfg.steering),
                  float(cfg.wheelbase), float(cfg.dt))


def ego_poses(motion: Motion, last: int) -> list[tuple[float, float, float]]:
    """World poses (c_x, c_z, ψ) of the vehicle at frames 0..last (float64, Python)."""
    poses = [(0.0, 0.0, 0.0)]
    for _ in range(last):
        cx, cz, psi = poses[-1]
        c, s = math.cos(psi), math.sin(psi)
        # c_{k+1} = c_k + R_ψᵀ d,  ψ_{k+1} = ψ_k + φ
        poses.append((cx + c * motion.x_d + s * motion.z_d, cz - s * motion.x_d + c * motion.z_d,
                      psi + motion.yaw))
    return poses


def rot_y(psi: float) -> list[list[float]]:
    """R_ψ (3×3 Python floats) of a heading ψ (rad)."""
    c, s = math.cos(psi), math.sin(psi)
    return [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]



class BodyMotion:
    """Suspension-like oscillation of the body over the road: offsets of the camera's pitch and
    roll (rad) and height (m) relative to the road, each ``a sin(2π f τ + φ)`` at time τ (s), with
    the amplitudes a and frequencies f of the configuration and phases φ drawn from the scene seed.
    """

    def __init__(self, cfg: SceneConfig, seed: int) -> None:
        self.amplitudes = (float(cfg.body_pitch), float(cfg.body_roll), float(cfg.body_height))
        self.frequencies = (float(cfg.body_pitch_hz), float(cfg.body_roll_hz), float(cfg.body_height_hz))
        g = torch.Generator().manual_seed((int(seed) * 1_000_003 + 271_828) % (2 ** 63))
        self.phases = tuple((2 * math.pi * torch.rand(3, generator=g, dtype=torch.float64)).tolist())

    def offsets(self, tau: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(pitch, roll, height) offsets at times ``tau`` (s), differentiable in ``tau``."""
        return tuple(a * torch.sin(2 * math.pi * f * tau + phase)
                     for a, f, phase in zip(self.amplitudes, self.frequencies, self.phases))
