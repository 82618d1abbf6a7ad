"""The ego vehicle's planar motion: odometry per pair from the configuration, and the chain of
world poses (c_x, c_z, ψ) of frames 0..k.

A pose (c, ψ) maps world points into a local frame as ``p_local = R_ψ (p_world - c)`` with
``R_ψ = [[cos ψ, 0, -sin ψ], [0, 1, 0], [sin ψ, 0, cos ψ]]`` (:func:`rot_y`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ...geometry.egomotion import ego_motion_from_ackermann
from .config import SceneConfig


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


def motion_from_config(cfg: SceneConfig) -> Motion:
    """The per-pair odometry and velocities of a configuration (explicit odometry, or Ackermann
    motion from speed and steering)."""
    if cfg.x_d is not None:
        x_d, z_d, yaw = float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)
        chord = math.hypot(x_d, z_d)
        # arc length of the circular arc with this chord and turning angle
        arc = chord * (yaw / 2) / math.sin(yaw / 2) if abs(yaw) > 1e-12 else chord
        arc = math.copysign(arc, z_d)  # backwards when z_d < 0
        speed = arc / cfg.dt
        steering = math.atan(cfg.wheelbase * yaw / arc) if arc != 0 else 0.0
        return Motion(x_d, z_d, yaw, speed, steering, cfg.wheelbase, cfg.dt)
    speed = cfg.speed * cfg.speed_factor
    ego = ego_motion_from_ackermann(torch.tensor([speed], dtype=torch.float64), cfg.steering,
                                    cfg.wheelbase, cfg.dt)
    return Motion(float(ego.x_d[0]), float(ego.z_d[0]), float(ego.yaw[0]), speed, cfg.steering,
                  cfg.wheelbase, cfg.dt)


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

