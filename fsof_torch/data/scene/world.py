"""A configured scene: road, ego poses, objects near the ego vehicle, camera matrices and the
value-noise tables of its textures."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ...geometry.camera import Camera
from .config import SceneConfig
from .motion import ego_poses, motion_from_config, rot_y
from .objects import BLOCK, SceneObject, block_objects
from .road import Road


class Scene:
    """A configured scene: road, ego poses, objects, texture tables; renders frames."""

    def __init__(self, cfg: SceneConfig, seed: int, dtype: torch.dtype) -> None:
        self.cfg, self.seed, self.dtype = cfg, int(seed), dtype
        self.motion = motion_from_config(cfg)
        self.road = Road(cfg, self.motion)
        self.h = float(cfg.height)
        base = Camera(torch.tensor(cfg.K, dtype=torch.float64), cfg.height, cfg.roll, cfg.pitch)
        size = tuple(cfg.size) if cfg.size is not None else tuple(cfg.base_size)
        if size != tuple(cfg.base_size):
            base = base.scaled(size[1] / cfg.base_size[1], size[0] / cfg.base_size[0])
        self.size = size
        self.camera64 = base
        self.Rc = base.mounting()[0].tolist()
        self.K = base.K[0].tolist()
        self.K_inv = base.K_inv()[0].tolist()
        g = torch.Generator().manual_seed(self.seed * 2 + 1)
        # value-noise lattices: 12 periodic 128 x 128 tables (one per octave and texture)
        lattice = torch.rand(12, 1, 128, 128, generator=g, dtype=torch.float64) * 2 - 1
        self.noise = F.pad(lattice, (0, 1, 0, 1), mode="circular").to(dtype)
        self._poses = ego_poses(self.motion, 1)
        self._blocks: dict[int, list[SceneObject]] = {}

    # -- poses and objects --------------------------------------------------------------------
    def ego_pose(self, k: int) -> tuple[float, float, float]:
        if k >= len(self._poses):
            self._poses = ego_poses(self.motion, k)
        return self._poses[k]

    def blocks(self, b: int) -> list[SceneObject]:
        if b not in self._blocks:
            self._blocks[b] = block_objects(self.cfg, self.motion, self.seed, b, self.road.kappa)
        return self._blocks[b]

    def object_pose(self, o: SceneObject, k: int) -> tuple[list[float], float]:
        s = o.s0 + o.vs * k * self.motion.dt
        x, z, psi = self.road.to_world(o.e, s)
        if o.reverse:
            psi += math.pi
        # the centre sits `offset` metres along the object's own z axis
        x += o.offset * math.sin(psi)
        z += o.offset * math.cos(psi)
        return [x, o.y, z], psi

    def objects(self, k: int) -> list[SceneObject]:
        """The objects near the ego vehicle at frame k: arc length from 30 m behind to 220 m ahead
        (less on tight circles, so that one lap never overlaps the next)."""
        cx, cz, _ = self.ego_pose(k)
        s_ego = self.road.s_of(cx, cz)
        back, far = 30.0, 220.0
        if self.road.kappa != 0.0:
            # on a closed circle keep less than one lap in view, or laps would overlap
            span = max(2 * math.pi / abs(self.road.kappa) - 25.0, 20.0)
            back = min(back, 0.25 * span)
            far = min(far, span - back)
        lo, hi = s_ego - back, s_ego + far
        t = k * self.motion.dt
        vmax = max(self.motion.speed, 5.0) * self.cfg.speed_factor * 1.5
        b0 = math.floor((lo - vmax * t) / BLOCK)
        b1 = math.floor((hi + vmax * t) / BLOCK)
        out = []
        for b in range(b0, b1 + 1):
            for o in self.blocks(b):
                s = o.s0 + o.vs * t
                if lo - 10 <= s <= hi + 10:
                    out.append(o)
        return out

    # -- camera matrices --------------------------------------------------------------------
    def world_to_camera(self, k: int) -> tuple[list[list[float]], list[float]]:
        """(A, c): p_cam = A (p_world - c) at frame k."""
        cx, cz, psi = self.ego_pose(k)
        R = rot_y(psi)
        A = [[sum(self.Rc[i][m] * R[m][j] for m in range(3)) for j in range(3)] for i in range(3)]
        return A, [cx, 0.0, cz]

    def camera(self) -> Camera:
        return self.camera64.to(self.dtype)

