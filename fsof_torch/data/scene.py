"""Procedural driving scenes with exact ground truth, rendered by vectorised torch ray casting.

The scenes test the road-flow formula instead of repeating it: every ground-truth quantity comes
from the 3D geometry (ray / plane / box intersections, rigid motions, pinhole projection), never
from :func:`fsof_torch.flow_model.displacement_flow`.

Scene: a road (the plane y = h of the vehicle frame) with lane markings, raised pavements behind
kerbs, building façades, parked and moving cars (a body box and a cabin box each) and a sky at
infinity. The road is straight, or an arc whose curvature matches the ego vehicle's steering so
that a turning car stays in its lane. Textures are multi-scale value noise from a seeded
generator, band-limited per pixel (octaves finer than the pixel footprint fade out) so that
frames warp onto each other and optical flow can track the road.

Frames (DESIGN.md §2): the world frame is the vehicle frame of frame 0 (x right, y down,
z forward, origin at the camera, road at y = h). A pose (c, ψ) maps world points into a local
frame as ``p_local = R_ψ (p_world - c)`` with ``R_ψ = [[cos ψ, 0, -sin ψ], [0, 1, 0],
[sin ψ, 0, cos ψ]]``; the ego vehicle, the buildings and the cars all use it. The camera sees
``p_cam = R_roll R_pitch p_vehicle`` (:class:`fsof_torch.camera.Camera`).

Ground truth per pair (frames t = index, t+1):

* ``flow``: each pixel centre's ray at t meets a surface at a 3D point; the point moves with its
  object (static world, or a moving car's rigid motion), is expressed in the camera of t+1 and
  projected; flow = projection − pixel. Sky pixels get the flow of a direction at infinity
  (rotation only) and are not valid.
* ``valid``: a 3D point exists, lies in front of the camera at t+1, projects inside
  [0, W−1] × [0, H−1] and is not occluded there: its inverse depth is compared with the inverse
  depth render of frame t+1 interpolated bilinearly at the projected position (bilinear
  interpolation of inverse depth is exact on planes; at depth edges it errs toward "occluded").
* ``flow_velocity`` (px/s): the analytic time derivative of each point's projection under the
  instantaneous ego motion (forward rate v_r, lateral rate 0, yaw rate v_r tan δ_f / l) and, for
  moving cars, the car's own velocity.
* ``depth``: camera z in metres (0 on the sky); ``labels``: see :data:`LABELS`; ``road``: road
  or marking pixels (the plane y = h, the freespace).

Example:
    >>> from fsof_torch.scene import render_pair
    >>> pair = render_pair("default", 0, size=(96, 320))
    >>> pair["image1"].shape, pair["flow"].shape, pair["road"].dtype
    (torch.Size([3, 96, 320]), torch.Size([2, 96, 320]), torch.bool)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import check_size
from ..geometry.camera import Camera
from ..geometry.egomotion import ego_motion_from_ackermann

__all__ = [
    "LABELS",
    "LABEL_COLORS",
    "PRESETS",
    "SENSOR_NOISE",
    "KITTI_K",
    "KITTI_SIZE",
    "SceneConfig",
    "scene_config",
    "render_pair",
    "render_sequence",
    "collate",
]

#: Semantic label ids of ``labels``.
LABELS: dict[str, int] = {"sky": 0, "road": 1, "marking": 2, "kerb": 3, "pavement": 4,
                          "building": 5, "car": 6}

#: A colour per label id (RGB 0..255), for visualisations.
LABEL_COLORS: dict[int, tuple[int, int, int]] = {
    0: (70, 130, 180), 1: (128, 64, 128), 2: (255, 255, 255), 3: (220, 220, 0),
    4: (244, 35, 232), 5: (70, 70, 70), 6: (0, 0, 142)}

#: KITTI-like intrinsics (pixels) at :data:`KITTI_SIZE` = (H, W).
KITTI_K = ((721.5377, 0.0, 609.5593), (0.0, 721.5377, 172.854), (0.0, 0.0, 1.0))
KITTI_SIZE = (375, 1242)

_SKY, _ROAD, _MARK, _KERB, _PAVE, _BUILD, _CAR = (LABELS[k] for k in
                                                   ("sky", "road", "marking", "kerb", "pavement", "building", "car"))
_BLOCK = 40.0  # metres of road per procedurally generated block of objects
_BUILDING, _CAR_BODY, _CAR_CABIN = 0, 1, 2


@dataclass(frozen=True)
class SceneConfig:
    """Everything a preset fixes; every field can be overridden by keyword in :func:`render_pair`.

    Motion: ``speed`` (m/s, rear axle = camera), ``steering`` (front-wheel angle, rad),
    ``wheelbase`` (m), ``dt`` (s between frames), ``speed_factor`` (multiplies the speed of the
    ego vehicle and of the moving cars: the paper's CVC ×1 / ×4). Or explicit odometry per pair:
    ``x_d``, ``z_d`` (m) and ``yaw`` (rad), all three given (then speed and steering are derived
    from the circular arc through the motion: speed = signed arc length / dt, steering =
    atan(l · yaw / arc length); exact for Ackermann motion, an approximation otherwise).

    Camera: ``height`` (m), ``roll``, ``pitch`` (rad), ``K`` (3×3 at ``base_size``), ``size``
    (rendered (H, W); K is scaled to it). Anti-aliasing: ``supersample`` (ss × ss rays per pixel)
    at geometric edges only when ``adaptive`` (textures and markings are band-limited
    analytically, so pixel centres suffice elsewhere), or at every pixel with ``adaptive=False``.

    Scene: ``lane_width``, ``parking_width`` (a parking strip on each side, 0 for none),
    ``pavement_width``, ``kerb_height`` (m); ``buildings`` (bool); ``parked_cars`` (mean number
    per 40 m and side); ``moving_cars`` (mean number per 40 m, half oncoming); ``texture``
    (contrast multiplier of the procedural textures); ``asphalt`` (grey-level amplitude of each
    of the seven asphalt noise octaves, cells 2 cm, 5 cm, 12 cm, 30 cm, 75 cm, 2 m, 5 m; None for
    the built-in (25, 25, 22, 18, 14, 13, 11)).

    Camera sensor: ``noise`` (standard deviation, grey levels on 0..255, of independent Gaussian
    noise added to every pixel of every frame, the same on the three channels; seeded by the
    scene seed and the frame index, so a frame shared by two pairs has the same noise in both;
    0 for none). It is the noise at ``base_size``; at another ``size`` it is scaled by
    sqrt(H W / (H0 W0)), the noise of the base image area-averaged to that size.
    """

    speed: float = 8.0
    steering: float = 0.0
    wheelbase: float = 2.7
    dt: float = 0.1
    speed_factor: float = 1.0
    x_d: float | None = None
    z_d: float | None = None
    yaw: float | None = None
    height: float = 1.65
    roll: float = 0.0
    pitch: float = 0.0
    K: tuple = KITTI_K
    base_size: tuple = KITTI_SIZE
    size: tuple | None = None
    supersample: int = 2
    adaptive: bool = True
    lane_width: float = 3.5
    parking_width: float = 2.3
    pavement_width: float = 3.5
    kerb_height: float = 0.12
    buildings: bool = True
    parked_cars: float = 2.0
    moving_cars: float = 1.0
    texture: float = 1.0
    asphalt: tuple | None = None
    noise: float = 0.0


_DEG = math.pi / 180.0
# asphalt octave amplitudes of the default preset (cells 2 cm ... 5 m, see SceneConfig.asphalt):
# little contrast at 12-75 cm, where the built-in texture gave real KITTI road about twice its
# band-pass contrast, more at 2-5 m (patches), the 2-5 cm grain kept
_DEFAULT_ASPHALT = (25.0, 24.0, 7.0, 3.0, 8.0, 22.0, 20.0)

#: Sensor noise (grey levels at 375×1242) that, with the default asphalt, matches the fine-scale
#: (1 px band-pass) contrast measured on the real KITTI road (benchmarks/scene_realism.py).
SENSOR_NOISE = 3.8

#: Named scene presets (see the README table). Overrides such as ``speed_factor=4`` or
#: ``roll=math.radians(5)`` apply on top.
PRESETS: dict[str, SceneConfig] = {
    # the refine job's default sequence, made like the real KITTI samples in ../shared/data:
    # 12 m/s at 10 Hz (the KITTI odometry clip moves 1.197 m per frame), asphalt whose grey-level
    # statistics per row band (row-detrended std, band-pass at 1, 2, 4 px, gradient) match those
    # measured inside the road polygons of the real images (README: "Realistic default"); a
    # gentle curve, cars in view, mild mounting. No sensor noise by default: independent noise per
    # frame is a floor under any photometric error that no flow can remove, and would hide what the
    # refiner changes; ``noise=SENSOR_NOISE`` adds the level measured on the real images.
    "default": SceneConfig(speed=12.0, steering=0.02, roll=1.0 * _DEG, pitch=-1.0 * _DEG,
                           parked_cars=2.5, moving_cars=1.5, asphalt=_DEFAULT_ASPHALT, noise=0.0),
    # CVC12-like straight urban road (the paper's displacement-model data): empty or busy
    "cvc-simple": SceneConfig(speed=5.0, dt=0.1, buildings=False, parked_cars=0.0, moving_cars=0.0,
                              parking_width=0.0, height=1.5),
    "cvc-complex": SceneConfig(speed=5.0, dt=0.1, parked_cars=3.0, moving_cars=1.5, height=1.5),
    # CARLA-like (the paper's velocity-model data), roll 0 by default; roll= overrides (±5°, ±10°)
    "carla-straight": SceneConfig(speed=10.0, dt=0.05, parked_cars=1.5, moving_cars=1.0,
                                  height=1.6, wheelbase=2.9),
    "carla-turning": SceneConfig(speed=6.0, dt=0.05, steering=0.18, parked_cars=1.0, moving_cars=0.5,
                                 height=1.6, wheelbase=2.9),
}


def scene_config(preset: str | SceneConfig = "default", **overrides: Any) -> SceneConfig:
    """The configuration of a preset (a name of :data:`PRESETS` or a :class:`SceneConfig`) with
    ``overrides`` applied; unknown names raise TypeError, bad values ValueError."""
    if isinstance(preset, SceneConfig):
        cfg = preset
    elif isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        cfg = PRESETS[preset]
    else:
        raise TypeError(f"preset: expected a preset name or a SceneConfig, got {type(preset).__name__}")
    known = {f.name for f in fields(SceneConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise TypeError(f"render_pair: unknown overrides {unknown}; expected some of {sorted(known)}")
    cfg = replace(cfg, **overrides)
    _validate(cfg)
    return cfg


def _validate(cfg: SceneConfig) -> None:
    def real(name: str) -> float:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{name}: expected a finite number, got {value!r}")
        return float(value)

    for name in ("speed", "steering", "roll", "pitch", "speed_factor", "texture", "noise", "parked_cars",
                 "moving_cars", "lane_width", "parking_width", "pavement_width", "kerb_height"):
        real(name)
    for name in ("wheelbase", "dt", "height", "lane_width"):
        if real(name) <= 0:
            raise ValueError(f"{name}: expected > 0, got {getattr(cfg, name)!r}")
    for name in ("speed_factor", "parked_cars", "moving_cars", "parking_width", "pavement_width",
                 "kerb_height", "texture", "noise"):
        if real(name) < 0:
            raise ValueError(f"{name}: expected >= 0, got {getattr(cfg, name)!r}")
    if not abs(cfg.steering) < math.pi / 2:
        raise ValueError(f"steering: expected |δ_f| < π/2 rad, got {cfg.steering!r}")
    if not (abs(cfg.roll) < math.pi / 4 and abs(cfg.pitch) < math.pi / 4):
        raise ValueError(f"roll, pitch: expected |angle| < π/4 rad, got roll={cfg.roll!r}, pitch={cfg.pitch!r}")
    explicit = [getattr(cfg, n) is not None for n in ("x_d", "z_d", "yaw")]
    if any(explicit) and not all(explicit):
        raise ValueError(f"x_d, z_d, yaw: give all three or none, got x_d={cfg.x_d!r}, z_d={cfg.z_d!r}, yaw={cfg.yaw!r}")
    if all(explicit):
        for n in ("x_d", "z_d", "yaw"):
            real(n)
    if cfg.asphalt is not None:
        amps = cfg.asphalt
        if (not isinstance(amps, (tuple, list)) or len(amps) != len(_ROAD_CELLS)
                or not all(isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) and a >= 0
                           for a in amps)):
            raise ValueError(f"asphalt: expected {len(_ROAD_CELLS)} finite amplitudes >= 0 (one per octave), "
                             f"got {amps!r}")
    if isinstance(cfg.supersample, bool) or not isinstance(cfg.supersample, int) or cfg.supersample < 1:
        raise ValueError(f"supersample: expected an integer >= 1, got {cfg.supersample!r}")
    if cfg.size is not None:
        check_size(cfg.size)
    check_size(cfg.base_size, "base_size")


# -- motion ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Motion:
    """Per-pair ego motion (constant over the sequence) and the derived velocity description."""

    x_d: float
    z_d: float
    yaw: float
    speed: float
    steering: float
    wheelbase: float
    dt: float


def _motion(cfg: SceneConfig) -> _Motion:
    if cfg.x_d is not None:
        x_d, z_d, yaw = float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)
        chord = math.hypot(x_d, z_d)
        # arc length of the circular arc with this chord and turning angle
        arc = chord * (yaw / 2) / math.sin(yaw / 2) if abs(yaw) > 1e-12 else chord
        arc = math.copysign(arc, z_d)  # backwards when z_d < 0
        speed = arc / cfg.dt
        steering = math.atan(cfg.wheelbase * yaw / arc) if arc != 0 else 0.0
        return _Motion(x_d, z_d, yaw, speed, steering, cfg.wheelbase, cfg.dt)
    speed = cfg.speed * cfg.speed_factor
    ego = ego_motion_from_ackermann(torch.tensor([speed], dtype=torch.float64), cfg.steering,
                                    cfg.wheelbase, cfg.dt)
    return _Motion(float(ego.x_d[0]), float(ego.z_d[0]), float(ego.yaw[0]), speed, cfg.steering,
                   cfg.wheelbase, cfg.dt)


def _ego_poses(motion: _Motion, last: int) -> list[tuple[float, float, float]]:
    """World poses (c_x, c_z, ψ) of the vehicle at frames 0..last (float64, Python)."""
    poses = [(0.0, 0.0, 0.0)]
    for _ in range(last):
        cx, cz, psi = poses[-1]
        c, s = math.cos(psi), math.sin(psi)
        # c_{k+1} = c_k + R_ψᵀ d,  ψ_{k+1} = ψ_k + φ
        poses.append((cx + c * motion.x_d + s * motion.z_d, cz - s * motion.x_d + c * motion.z_d,
                      psi + motion.yaw))
    return poses


def _rot_y(psi: float) -> list[list[float]]:
    c, s = math.cos(psi), math.sin(psi)
    return [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]


# -- the road's coordinates ----------------------------------------------------------------------

class _Road:
    """A straight road or an arc of constant curvature; lateral e (m, + right) and arc length s."""

    def __init__(self, cfg: SceneConfig, motion: _Motion) -> None:
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


# -- objects ---------------------------------------------------------------------------------------

@dataclass
class _Object:
    kind: int          # _BUILDING, _CAR_BODY, _CAR_CABIN
    e: float           # lateral road coordinate of the reference point (m)
    s0: float          # arc length at frame 0 (m)
    vs: float          # arc-length speed (m/s), negative for oncoming cars
    half: tuple        # half extents (x, y, z) in the object's frame (m)
    y: float           # world y of the centre (m, down)
    offset: float      # shift of the centre along the object's z axis (m)
    reverse: bool      # facing against the road direction
    colour: tuple      # base RGB 0..255
    seed: int          # texture variation


def _block_objects(cfg: SceneConfig, motion: _Motion, seed: int, block: int,
                   road_kappa: float = 0.0) -> list[_Object]:
    """The objects generated for road block ``block`` (arc length [40 b, 40 (b + 1)) at frame 0)."""
    g = torch.Generator().manual_seed((seed * 1_000_003 + block * 7919 + 12345) % (2 ** 63))

    def uni(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))

    def count(mean: float) -> int:
        return int(torch.poisson(torch.tensor(float(mean), dtype=torch.float64), generator=g)) if mean > 0 else 0

    h = cfg.height
    w_road = cfg.lane_width + cfg.parking_width
    s_start = block * _BLOCK
    objs: list[_Object] = []
    if cfg.buildings:
        for side in (-1.0, 1.0):
            s = s_start + uni(0.0, 3.0)
            while s < s_start + _BLOCK - 4.0:
                length = min(uni(8.0, 22.0), s_start + _BLOCK - s)
                depth, tall = uni(8.0, 14.0), uni(6.0, 22.0)
                setback = uni(0.0, 1.5)
                if road_kappa * side > 0:
                    # inside a bend: keep the block clear of the bend's centre
                    room = 1.0 / abs(road_kappa) - (w_road + cfg.pavement_width + setback)
                    depth = min(depth, max(0.6 * room, 1.0))
                e = side * (w_road + cfg.pavement_width + setback + depth / 2)
                tone = uni(0.0, 1.0)
                colour = (150 + 70 * tone + uni(-15, 15), 120 + 60 * tone + uni(-15, 15), 100 + 50 * tone + uni(-15, 15))
                objs.append(_Object(_BUILDING, e, s + length / 2, 0.0, (depth / 2, tall / 2, length / 2),
                                    h - cfg.kerb_height - tall / 2, 0.0, False, colour, int(uni(0, 1e6))))
                s += length + uni(0.5, 4.0)

    def car(e: float, s0: float, vs: float, reverse: bool) -> None:
        length, width = uni(3.9, 4.8), uni(1.7, 1.9)
        colour = [uni(20, 230) for _ in range(3)]
        clearance, body_h, cabin_h = 0.22, uni(0.7, 0.8), uni(0.5, 0.6)
        seed_tex = int(uni(0, 1e6))
        objs.append(_Object(_CAR_BODY, e, s0, vs, (width / 2, body_h / 2, length / 2),
                            h - clearance - body_h / 2, 0.0, reverse, tuple(colour), seed_tex))
        objs.append(_Object(_CAR_CABIN, e, s0, vs, (width / 2 - 0.08, cabin_h / 2, length * 0.28),
                            h - clearance - body_h - cabin_h / 2, -0.15 * length, reverse, tuple(colour),
                            seed_tex))

    if cfg.parking_width > 0:
        for side in (-1.0, 1.0):
            n = count(cfg.parked_cars)
            slots = sorted(uni(0.0, _BLOCK) for _ in range(n))
            last = -1e9
            for s in slots:
                if s - last < 6.0:  # no overlapping parked cars
                    continue
                last = s
                car(side * (cfg.lane_width + cfg.parking_width / 2), s_start + s, 0.0, side < 0)
    # one speed per lane and scene, cars spaced along s: moving cars never run into each other
    base = max(abs(motion.speed), 5.0) * cfg.speed_factor
    taken: dict[float, list[float]] = {}
    for _ in range(count(cfg.moving_cars)):
        oncoming = uni(0.0, 1.0) < 0.5
        s0 = s_start + uni(3.0, _BLOCK - 3.0)
        lane = -cfg.lane_width / 2 if oncoming else cfg.lane_width / 2
        if not oncoming and s0 < 10.0:
            continue  # same direction, faster than us: only ahead of the ego vehicle
        if any(abs(s0 - other) < 7.0 for other in taken.setdefault(lane, [])):
            continue
        taken[lane].append(s0)
        car(lane, s0, -0.8 * base if oncoming else 1.3 * base, oncoming)
    return objs


class _Scene:
    """A configured scene: road, ego poses, objects, texture tables; renders frames."""

    def __init__(self, cfg: SceneConfig, seed: int, dtype: torch.dtype) -> None:
        self.cfg, self.seed, self.dtype = cfg, int(seed), dtype
        self.motion = _motion(cfg)
        self.road = _Road(cfg, self.motion)
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
        self._poses = _ego_poses(self.motion, 1)
        self._blocks: dict[int, list[_Object]] = {}

    # -- poses and objects --------------------------------------------------------------------
    def ego_pose(self, k: int) -> tuple[float, float, float]:
        if k >= len(self._poses):
            self._poses = _ego_poses(self.motion, k)
        return self._poses[k]

    def blocks(self, b: int) -> list[_Object]:
        if b not in self._blocks:
            self._blocks[b] = _block_objects(self.cfg, self.motion, self.seed, b, self.road.kappa)
        return self._blocks[b]

    def object_pose(self, o: _Object, k: int) -> tuple[list[float], float]:
        s = o.s0 + o.vs * k * self.motion.dt
        x, z, psi = self.road.to_world(o.e, s)
        if o.reverse:
            psi += math.pi
        # the centre sits `offset` metres along the object's own z axis
        x += o.offset * math.sin(psi)
        z += o.offset * math.cos(psi)
        return [x, o.y, z], psi

    def objects(self, k: int) -> list[_Object]:
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
        b0 = math.floor((lo - vmax * t) / _BLOCK)
        b1 = math.floor((hi + vmax * t) / _BLOCK)
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
        R = _rot_y(psi)
        A = [[sum(self.Rc[i][m] * R[m][j] for m in range(3)) for j in range(3)] for i in range(3)]
        return A, [cx, 0.0, cz]

    def camera(self) -> Camera:
        return self.camera64.to(self.dtype)


# -- texture helpers -----------------------------------------------------------------------------

def _fbm(tables: Tensor, x: Tensor, y: Tensor, footprint: Tensor, cells: tuple, amps: tuple,
         first: int = 0) -> Tensor:
    """Multi-octave value noise (bilinear lattices of spacing ``cells`` metres, amplitudes
    ``amps``) at points (x, y); each octave fades out where its cell is finer than about two
    pixel footprints (``footprint``, metres), so the texture is band-limited per pixel.

    ``tables`` (O, 1, n + 1, n + 1): periodic lattices (last row / column repeat the first);
    octave i uses table (first + i) mod O. One ``grid_sample`` call evaluates all octaves.
    """
    shape = x.shape
    x, y, fp = x.reshape(-1), y.reshape(-1), footprint.reshape(-1)
    if x.numel() == 0:
        return torch.zeros(shape, dtype=x.dtype)
    n = tables.shape[-1] - 1
    finest = float(fp.min())
    active = [i for i, cell in enumerate(cells) if cell > finest]
    if not active:
        return torch.zeros(shape, dtype=x.dtype)
    xy = torch.stack([x, y], dim=-1)
    grid = torch.empty(len(active), 1, x.numel(), 2, dtype=x.dtype)
    for j, i in enumerate(active):
        torch.remainder(xy * (1.0 / cells[i]), n, out=grid[j, 0])
    grid = grid * (2.0 / n) - 1.0
    pick = [(first + i) % tables.shape[0] for i in active]
    samples = F.grid_sample(tables[pick], grid, mode="bilinear", align_corners=True)[:, 0, 0]
    cell = torch.tensor([cells[i] for i in active], dtype=x.dtype).unsqueeze(1)
    amp = torch.tensor([amps[i] for i in active], dtype=x.dtype).unsqueeze(1)
    weight = (cell / fp - 1.0).clamp(0.0, 1.0) * amp
    return (weight * samples).sum(0).reshape(shape)


def _stripe(dist: Tensor, half_width: float, footprint: Tensor) -> Tensor:
    """Coverage in [0, 1] of the stripe |dist| < half_width box-filtered over a window of
    ``footprint`` (same unit): the overlap of [dist - fp/2, dist + fp/2] with the stripe, / fp."""
    d = dist.abs()
    half = 0.5 * footprint
    overlap = torch.minimum(d + half, torch.full_like(d, half_width)) - torch.maximum(d - half, torch.full_like(d, -half_width))
    return (overlap.clamp_min(0.0) / footprint).clamp(max=1.0)


def _dashes(s: Tensor, on: float, period: float, footprint: Tensor) -> Tensor:
    """Coverage of dashes [0, on) repeating every ``period`` metres along s, box-filtered over
    ``footprint``: the difference of the pattern's running integral at the window's two ends."""
    def integral(x: Tensor) -> Tensor:
        cycles = torch.floor(x / period)
        return cycles * on + (x - cycles * period).clamp(max=on)

    half = 0.5 * footprint
    return ((integral(s + half) - integral(s - half)) / footprint).clamp(0.0, 1.0)


# -- ray casting ---------------------------------------------------------------------------------

def _grid(size: tuple[int, int], ss: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Sample coordinates u (W ss,) and v (H ss,) in pixels (pixel centres when ss is odd or 1)."""
    H, W = size
    u = (torch.arange(W * ss, dtype=torch.float64) + 0.5) / ss - 0.5
    v = (torch.arange(H * ss, dtype=torch.float64) + 0.5) / ss - 0.5
    return u.to(dtype), v.to(dtype)


class _Hits:
    """Ray-cast results on a (Hs, Ws) grid of samples."""

    def __init__(self, **kw: Tensor) -> None:
        self.__dict__.update(kw)


def _box_slab(o_l: list[float], d_l: list[Tensor], half: tuple) -> tuple[Tensor, Tensor]:
    """Slab test of rays o_l + t d_l against the box |p_a| <= half_a: (t_near, t_far)."""
    t_near = t_far = None
    for a_ in range(3):
        da = d_l[a_]
        inv = 1.0 / torch.where(da.abs() > 1e-12, da, torch.full_like(da, 1e-12))
        ta = (-half[a_] - o_l[a_]) * inv
        tb = (half[a_] - o_l[a_]) * inv
        lo, hi = torch.minimum(ta, tb), torch.maximum(ta, tb)
        t_near = lo if t_near is None else torch.maximum(t_near, lo)
        t_far = hi if t_far is None else torch.minimum(t_far, hi)
    return t_near, t_far


def _ground(scene: _Scene, ox: float, oz: float, dx: Tensor, dy: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
    """Ray parameter and label of the first hit with the road, the kerb faces and the raised
    pavement (inf and sky where a ray goes up)."""
    h, kh = scene.h, scene.cfg.kerb_height
    road = scene.road
    w_road = scene.cfg.lane_width + scene.cfg.parking_width
    down = dy > 1e-9
    dy_safe = torch.where(down, dy, torch.ones_like(dy))
    t_road = h / dy_safe
    e_road = road.lateral(ox + t_road * dx, oz + t_road * dz)
    t_pave = (h - kh) / dy_safe
    e_pave = road.lateral(ox + t_pave * dx, oz + t_pave * dz)
    # the raised pavement is met first: a ray over it at kerb height hits its top
    on_pave = down & (e_pave.abs() >= w_road)
    on_road = down & ~on_pave & (e_road.abs() < w_road)
    kerb = down & ~on_pave & ~on_road
    t = torch.where(on_pave, t_pave, torch.where(on_road, t_road, float("inf")))
    label = torch.where(on_road, _ROAD, torch.where(on_pave, _PAVE, _SKY))
    if bool(kerb.any()):
        idx = kerb.nonzero(as_tuple=True)
        side = torch.sign(e_road[idx])
        tk = road.boundary_hit(side * w_road, ox, oz, dx[idx], dz[idx], t_pave[idx], t_road[idx])
        t = t.index_put(idx, tk)
        label = label.index_put(idx, torch.full_like(tk, _KERB, dtype=torch.int64))
    return t, label


def _cast(scene: _Scene, k: int, u: Tensor, v: Tensor, *, grid: bool = True, details: bool = True) -> _Hits:
    """Cast the rays of samples at frame k; nearest surface per ray.

    ``grid=True``: u (Ws,) and v (Hs,) are the axes of a (Hs, Ws) sample grid (objects are tested
    only on the grid rectangle their projection covers); ``grid=False``: u, v (N,) list N rays,
    sorted by v (objects are tested only on the run of rays within their rows).
    The ray direction has camera z = 1, so the ray parameter t is the camera depth.
    """
    dtype = scene.dtype
    A, c = scene.world_to_camera(k)
    Ki = scene.K_inv
    if grid:
        Hs, Ws = v.shape[0], u.shape[0]
        shape = (Hs, Ws)
        ug, vg = u.reshape(1, Ws), v.reshape(Hs, 1)
    else:
        shape = tuple(u.shape)
        ug, vg = u, v
    # camera direction (K⁻¹ p̃), then world direction Aᵀ d_cam (rank-1 grids in grid mode)
    dcx = Ki[0][0] * ug + Ki[0][1] * vg + Ki[0][2]
    dcy = Ki[1][1] * vg + Ki[1][2]
    dx, dy, dz = ((A[0][j] * dcx + A[1][j] * dcy + A[2][j]).expand(shape) for j in range(3))
    ox, oz = c[0], c[2]

    if grid:
        # rows entirely above the horizon see no ground: skip them
        rows = (dy > 1e-9).any(dim=1)
        r0 = int(rows.to(torch.int8).argmax()) if bool(rows.any()) else Hs
        t = torch.full(shape, float("inf"), dtype=dtype)
        label = torch.full(shape, _SKY, dtype=torch.int64)
        if r0 < Hs:
            t[r0:], label[r0:] = _ground(scene, ox, oz, dx[r0:], dy[r0:], dz[r0:])
    else:
        t, label = _ground(scene, ox, oz, dx, dy, dz)
    obj = torch.full(shape, -1, dtype=torch.int64)
    objects = scene.objects(k)
    if objects:
        centres, psis, boxes = _screen_boxes(scene, objects, k, A, c)
    if grid:
        step_u = (u[1] - u[0]).item() if Ws > 1 else 1.0
        step_v = (v[1] - v[0]).item() if Hs > 1 else 1.0
        u0, v0 = u[0].item(), v[0].item()
    for i, o in enumerate(objects):
        box = boxes[i]
        if box == "behind":
            continue
        if grid:
            j0 = max(int(math.floor((box[0] - u0) / step_u)), 0)
            j1 = min(int(math.ceil((box[1] - u0) / step_u)) + 1, Ws)
            i0 = max(int(math.floor((box[2] - v0) / step_v)), 0)
            i1 = min(int(math.ceil((box[3] - v0) / step_v)) + 1, Hs)
            if j0 >= j1 or i0 >= i1:
                continue
            sel = (slice(i0, i1), slice(j0, j1))
        else:
            # rays come sorted by v: the object's rows are one contiguous run
            lo = int(torch.searchsorted(v, torch.tensor(box[2], dtype=v.dtype)))
            hi = int(torch.searchsorted(v, torch.tensor(box[3], dtype=v.dtype), right=True))
            if lo >= hi:
                continue
            inside = (u[lo:hi] >= box[0]) & (u[lo:hi] <= box[1])
            sel = (inside.nonzero(as_tuple=True)[0] + lo,)
            if sel[0].numel() == 0:
                continue
        ddx, ddy, ddz = dx[sel], dy[sel], dz[sel]
        centre, (cs, sn) = centres[i], psis[i]
        rel = (ox - centre[0], -centre[1], oz - centre[2])
        o_l = [cs * rel[0] - sn * rel[2], rel[1], sn * rel[0] + cs * rel[2]]
        d_l = [cs * ddx - sn * ddz, ddy, sn * ddx + cs * ddz]
        t_near, t_far = _box_slab(o_l, d_l, o.half)
        t_sel = t[sel]
        hit = (t_near <= t_far) & (t_near > 1e-6) & (t_near < t_sel)
        t[sel] = torch.where(hit, t_near, t_sel)
        obj[sel] = torch.where(hit, i, obj[sel])
    out = _Hits(t=t, label=label, obj=obj, dx=dx, dy=dy, dz=dz, objects=objects, origin=c, k=k)
    if objects:
        kinds = torch.tensor([_BUILD if o.kind == _BUILDING else _CAR for o in objects] + [0])
        out.label = torch.where(obj >= 0, kinds[obj], label)
    if details:
        # hit points in the hit object's own frame, and the face they lie on
        idx = (obj >= 0).nonzero(as_tuple=True)
        out.box_idx = idx
        if idx[0].numel():
            oid = obj[idx]
            tt = t[idx]
            table = torch.tensor([[*centres[i], *psis[i], *o.half] for i, o in enumerate(objects)], dtype=dtype)[oid]
            rx = ox + tt * dx[idx] - table[:, 0]
            ry = tt * dy[idx] - table[:, 1]
            rz = oz + tt * dz[idx] - table[:, 2]
            cs, sn = table[:, 3], table[:, 4]
            local = torch.stack([cs * rx - sn * rz, ry, sn * rx + cs * rz], dim=1)
            out.box_local = local
            out.box_face = (local.abs() / table[:, 5:8]).argmax(dim=1)
    return out


def _screen_boxes(scene: _Scene, objects: list, k: int, A: list, c: list):
    """Per object: centre (3 floats), (cos ψ, sin ψ), and the pixel rectangle (u_min, u_max,
    v_min, v_max) that bounds its part in front of the camera, or ``"behind"``."""
    poses = [scene.object_pose(o, k) for o in objects]
    centre = torch.tensor([p[0] for p in poses], dtype=torch.float64)
    psi = torch.tensor([p[1] for p in poses], dtype=torch.float64)
    half = torch.tensor([o.half for o in objects], dtype=torch.float64)
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)
    loc = signs.unsqueeze(0) * half.unsqueeze(1)  # (N, 8, 3)
    cs, sn = torch.cos(psi).unsqueeze(1), torch.sin(psi).unsqueeze(1)
    # world = centre + R_ψᵀ loc
    world = torch.stack([centre[:, 0:1] + cs * loc[..., 0] + sn * loc[..., 2],
                         centre[:, 1:2] + loc[..., 1],
                         centre[:, 2:3] - sn * loc[..., 0] + cs * loc[..., 2]], dim=-1)
    cam = (world - torch.tensor(c, dtype=torch.float64)) @ torch.tensor(A, dtype=torch.float64).T
    Kt = torch.tensor(scene.K, dtype=torch.float64)
    near = 0.05
    # a box straddling the camera plane is bounded by its corners in front and by the points where
    # its 12 edges cross the near plane
    ends = torch.tensor([(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1])
    P1, P2 = cam[:, ends[:, 0]], cam[:, ends[:, 1]]
    Z1, Z2 = P1[..., 2:], P2[..., 2:]
    crosses = ((Z1 - near) * (Z2 - near) < 0)[..., 0]
    w = ((near - Z1) / torch.where(Z2 != Z1, Z2 - Z1, 1.0)).clamp(0, 1)
    points = torch.cat([cam, P1 + w * (P2 - P1)], dim=1)  # (N, 20, 3)
    use = torch.cat([cam[..., 2] > near, crosses], dim=1)
    Z = points[..., 2].clamp_min(near)
    us = (Kt[0, 0] * points[..., 0] + Kt[0, 1] * points[..., 1]) / Z + Kt[0, 2]
    vs = Kt[1, 1] * points[..., 1] / Z + Kt[1, 2]
    big = torch.tensor(1e9, dtype=torch.float64)
    rect = torch.stack([torch.where(use, us, big).amin(1) - 1, torch.where(use, us, -big).amax(1) + 1,
                        torch.where(use, vs, big).amin(1) - 1, torch.where(use, vs, -big).amax(1) + 1], dim=1)
    rect = rect.clamp(-1e6, 1e6).tolist()
    seen = use.any(dim=1).tolist()
    boxes = [tuple(rect[i]) if seen[i] else "behind" for i in range(len(objects))]
    cossin = list(zip(cs[:, 0].tolist(), sn[:, 0].tolist()))
    return [p[0] for p in poses], cossin, boxes


# -- shading ---------------------------------------------------------------------------------------

_ROAD_CELLS = (0.02, 0.05, 0.12, 0.3, 0.75, 2.0, 5.0)
_ROAD_AMPS = (25.0, 25.0, 22.0, 18.0, 14.0, 13.0, 11.0)
_SUN = (0.35, -0.8, 0.45)  # world direction towards which light travels is -this (y down)


def _shade(scene: _Scene, hits: _Hits, *, labels: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """RGB (3, *shape) 0..255 of cast samples; with ``labels=True`` also the labels with the
    marking pixels (paint coverage > 1/2) split off the road."""
    dtype = scene.dtype
    cfg = scene.cfg
    tex = cfg.texture
    rgb = torch.zeros(3, *hits.t.shape, dtype=dtype)
    f = scene.K[0][0]
    tables = scene.noise
    label = hits.label
    ox, oz = hits.origin[0], hits.origin[2]

    # sky: a function of the world direction only (it lies at infinity)
    idx = (label == _SKY).nonzero(as_tuple=True)
    if idx[0].numel():
        dx, dy, dz = hits.dx[idx], hits.dy[idx], hits.dz[idx]
        elev = (-dy / torch.sqrt(dx * dx + dy * dy + dz * dz)).clamp(-1, 1)
        az = torch.atan2(dx, dz)
        cloud = _fbm(tables, az * 4, elev * 8, torch.full_like(elev, 8.0 / f), (0.6, 0.25, 0.1),
                     (0.5, 0.3, 0.2), first=8).clamp_min(0)
        w = elev.clamp(0, 1) ** 0.6
        for ch, (hz, zen) in enumerate(((205.0, 95.0), (215.0, 140.0), (228.0, 205.0))):
            rgb[ch][idx] = hz + (zen - hz) * w + tex * 30.0 * cloud

    # ground: road with markings, pavement slabs, kerb faces (world x, z; road coordinates e, s)
    for kind in (_ROAD, _PAVE, _KERB):
        idx = (label == kind).nonzero(as_tuple=True)
        if idx[0].numel() == 0:
            continue
        t = hits.t[idx]
        dx, dy, dz = hits.dx[idx], hits.dy[idx], hits.dz[idx]
        px, pz = ox + t * dx, oz + t * dz
        dn2 = dx * dx + dy * dy + dz * dz
        if kind == _KERB:
            # a vertical face seen at a grazing angle: blur generously
            fp = (t * torch.sqrt(dn2) * (3.0 / f)).clamp_min(1e-4)
            _, s = scene.road.to_road(px, pz)
            value = 185.0 + tex * 0.6 * _fbm(tables, s, t * dy * 3, fp, _ROAD_CELLS[:4], _ROAD_AMPS[:4])
            colour = (value, value, value + 3.0)
        else:
            # pixel footprint on the plane: distance / f / cos(incidence), metres
            fp = (t * dn2 / (f * dy)).clamp_min(1e-4)
            amps = tuple(cfg.asphalt) if kind == _ROAD and cfg.asphalt is not None else _ROAD_AMPS
            n = _fbm(tables, px, pz, fp, _ROAD_CELLS, amps)
            e, s = scene.road.to_road(px, pz)
            if kind == _ROAD:
                value = 100.0 + tex * n
                paint = _paint(cfg, e, s, fp)
                if labels:
                    marking = (idx, paint > 0.5)
                white = 215.0 + tex * 0.4 * n
                colour = (value + (white - value) * paint, value + 1.0 + (white - value - 1.0) * paint,
                          value + 4.0 + (white - 10.0 - value - 4.0) * paint)
            else:
                w_road = cfg.lane_width + cfg.parking_width
                slab_e = torch.remainder(e.abs() - w_road, 0.6) - 0.3
                slab_s = torch.remainder(s, 0.6) - 0.3
                grout = torch.maximum(_stripe(slab_e.abs() - 0.3, 0.015, fp), _stripe(slab_s.abs() - 0.3, 0.015, fp))
                value = 160.0 + tex * 0.8 * n - 45.0 * grout
                colour = (value + 6.0, value, value - 8.0)
        for ch in range(3):
            rgb[ch][idx] = colour[ch]

    # boxes: buildings and cars, textured in the hit face's own coordinates
    idx = getattr(hits, "box_idx", None)
    if idx is not None and idx[0].numel():
        objs = hits.objects
        oid = hits.obj[idx]
        t = hits.t[idx]
        face = hits.box_face
        lx, ly, lz = hits.box_local.unbind(1)
        table = torch.tensor([[*o.colour, o.kind, *o.half, o.seed % 997,
                               *_face_light(scene, o, hits.origin, hits.k)] for o in objs], dtype=dtype)
        attrs = table[oid]
        col = attrs[:, 0:3]
        kind = attrs[:, 3]
        half = attrs[:, 4:7]
        shift = attrs[:, 7]
        light = attrs[:, 8:11].gather(1, face.unsqueeze(1)).squeeze(1)
        # face coordinates (a, b) in metres: horizontal along the face, vertical (or depth on top)
        a = torch.where(face == 0, lz, lx)
        b = torch.where(face == 1, lz, ly)
        dx, dy, dz = hits.dx[idx], hits.dy[idx], hits.dz[idx]
        fp = (t * torch.sqrt(dx * dx + dy * dy + dz * dz) * (2.0 / f)).clamp_min(1e-4)
        n = _fbm(tables, a + shift, b + 2 * shift, fp, (0.05, 0.15, 0.5, 1.5), (10.0, 10.0, 8.0, 6.0),
                 first=3).unsqueeze(1)
        not_top = (face != 1).to(dtype)
        # buildings: storeys of windows on the walls
        wa = torch.remainder(a + shift, 3.0) - 1.5
        wb = torch.remainder(b + shift * 0.37, 3.2) - 1.6
        window = (_stripe(wa, 0.7, fp) * _stripe(wb, 0.8, fp) * not_top).unsqueeze(1)
        wall = col + tex * n
        win_col = torch.tensor([60.0, 70.0, 85.0], dtype=dtype) + tex * 0.8 * n
        bcol = wall + (win_col - wall) * window
        # cars: painted body with a dark band at the bottom; the cabin's sides are glass
        glass = ((kind == _CAR_CABIN) & (face != 1)).unsqueeze(1)
        glass_col = torch.tensor([40.0, 45.0, 55.0], dtype=dtype) + tex * 0.5 * n
        ccol = torch.where(glass, glass_col, col + tex * 0.6 * n)
        band = (_stripe(ly - half[:, 1] + 0.1, 0.1, fp) * (kind == _CAR_BODY).to(dtype) * not_top).unsqueeze(1)
        ccol = ccol + (30.0 - ccol) * band
        colour = torch.where((kind == _BUILDING).unsqueeze(1), bcol, ccol) * light.unsqueeze(1)
        for ch in range(3):
            rgb[ch][idx] = colour[:, ch]
    rgb = rgb.clamp(0.0, 255.0)
    if not labels:
        return rgb
    out = hits.label.clone()
    if (hits.label == _ROAD).any():
        idx, is_mark = marking
        out[idx] = torch.where(is_mark, _MARK, _ROAD)
    return rgb, out


def _paint(cfg: SceneConfig, e: Tensor, s: Tensor, footprint: Tensor) -> Tensor:
    """Paint coverage in [0, 1] of the lane markings at road coordinates (e, s): a dashed centre
    line and solid lines at the lane / parking-strip border and along the kerbs."""
    # a filter of 1.5 footprints: bilinear warping of near-Nyquist stripes would not be consistent
    footprint = 1.5 * footprint
    w_lane = cfg.lane_width
    paint = _stripe(e, 0.075, footprint) * _dashes(s, 3.0, 9.0, footprint)
    if cfg.parking_width > 0:
        paint = torch.maximum(paint, _stripe(e.abs() - w_lane, 0.06, footprint))
    return torch.maximum(paint, _stripe(e.abs() - (w_lane + cfg.parking_width - 0.25), 0.06, footprint))


def _face_light(scene: _Scene, o: _Object, origin: list[float], k: int) -> tuple[float, float, float]:
    """Lambert factor of the box faces whose normal is along local x, y, z (the face seen)."""
    # The visible face along each axis is the one facing the camera; light depends on that sign.
    centre, psi = scene.object_pose(o, k)
    R = _rot_y(psi)
    rel = [origin[m] - centre[m] for m in range(3)]
    o_l = [sum(R[r][m] * rel[m] for m in range(3)) for r in range(3)]
    sun = _SUN
    norm = math.sqrt(sum(x * x for x in sun))
    out = []
    for a in range(3):
        sign = 1.0 if o_l[a] > 0 else -1.0
        n_world = [R[a][m] * sign for m in range(3)]  # row a of R = local axis a in world
        lam = max(0.0, -sum(n_world[m] * sun[m] for m in range(3)) / norm)
        out.append(0.55 + 0.45 * lam)
    return tuple(out)


# -- ground truth ----------------------------------------------------------------------------------

def _apply(M: list[list[float]], x: Tensor, y: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """M (3×3 Python floats) applied to vectors given by their components."""
    return tuple(M[r][0] * x + M[r][1] * y + M[r][2] * z for r in range(3))


def _moving_object_tables(scene: _Scene, objects: list[_Object], k: int, dtype: torch.dtype):
    """Per object (rows) the rigid motion from frame k to k+1, p' = M p + b (world), and the
    instantaneous velocity field ṗ = v + Ω (p - c) at frame k; static objects get the identity."""
    N = len(objects)
    M = torch.eye(3, dtype=torch.float64).repeat(N, 1, 1)
    b = torch.zeros(N, 3, dtype=torch.float64)
    V = torch.zeros(N, 3, dtype=torch.float64)
    Om = torch.zeros(N, 3, 3, dtype=torch.float64)
    C = torch.zeros(N, 3, dtype=torch.float64)
    J = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    moving = torch.zeros(N, dtype=torch.bool)
    for i, o in enumerate(objects):
        if o.vs == 0.0:
            continue
        moving[i] = True
        c0, p0 = scene.object_pose(o, k)
        c1, p1 = scene.object_pose(o, k + 1)
        R0 = torch.tensor(_rot_y(p0), dtype=torch.float64)
        R1 = torch.tensor(_rot_y(p1), dtype=torch.float64)
        # p_local = R0 (p - c0) = R1 (p' - c1)
        M[i] = R1.T @ R0
        b[i] = torch.tensor(c1, dtype=torch.float64) - M[i] @ torch.tensor(c0, dtype=torch.float64)
        # the reference point on the lane line moves along the arc; the body turns about it
        x, z, psi_s = scene.road.to_world(o.e, o.s0 + o.vs * k * scene.motion.dt)
        speed = o.vs * (1 - scene.road.kappa * o.e)
        yaw_rate = o.vs * scene.road.kappa
        V[i] = torch.tensor([speed * math.sin(psi_s), 0.0, speed * math.cos(psi_s)], dtype=torch.float64)
        # p = c + R_ψᵀ l  =>  ṗ = ċ - ψ̇ J (p - c)
        Om[i] = -yaw_rate * J
        C[i] = torch.tensor([x, 0.0, z], dtype=torch.float64)
    return moving, M.to(dtype), b.to(dtype), V.to(dtype), Om.to(dtype), C.to(dtype)


def _ground_truth(scene: _Scene, k: int, hits: _Hits, next_inv_depth: Tensor) -> dict[str, Tensor]:
    """Flow, validity and px/s flow of pixel-centre hits at frame k (grids (H, W))."""
    dtype = scene.dtype
    H, W = hits.t.shape
    sky = hits.label == _SKY
    t = torch.where(sky, 0.0, hits.t)
    ox, oz = hits.origin[0], hits.origin[2]
    # world points at frame k (sky: the ray direction, a point at infinity)
    Px = torch.where(sky, hits.dx, ox + t * hits.dx)
    Py = torch.where(sky, hits.dy, t * hits.dy)
    Pz = torch.where(sky, hits.dz, oz + t * hits.dz)
    moving, M, b, V, Om, C = _moving_object_tables(scene, hits.objects, k, dtype)
    idx = None
    if bool(moving.any()):
        on_moving = (hits.obj >= 0) & moving[hits.obj.clamp_min(0)]
        if bool(on_moving.any()):
            idx = on_moving.nonzero(as_tuple=True)
            oid = hits.obj[idx]
            P_sel = torch.stack([Px[idx], Py[idx], Pz[idx]], dim=-1)
            P1_sel = (M[oid] @ P_sel.unsqueeze(-1)).squeeze(-1) + b[oid]
            Pdot_sel = V[oid] + (Om[oid] @ (P_sel - C[oid]).unsqueeze(-1)).squeeze(-1)
    P1x, P1y, P1z = Px, Py, Pz
    if idx is not None:
        P1x, P1y, P1z = (q.index_put(idx, P1_sel[:, r]) for r, q in enumerate((Px, Py, Pz)))
    A1, c1 = scene.world_to_camera(k + 1)
    # camera of t+1; directions at infinity are rotated only
    not_sky = (~sky).to(dtype)
    X, Y, Z = _apply(A1, P1x - c1[0] * not_sky, P1y - c1[1] * not_sky, P1z - c1[2] * not_sky)
    Kt = scene.K
    front = Z > 1e-6
    Zs = torch.where(front, Z, 1.0)
    u1 = (Kt[0][0] * X + Kt[0][1] * Y) / Zs + Kt[0][2]
    v1 = Kt[1][1] * Y / Zs + Kt[1][2]
    u = torch.arange(W, dtype=dtype).reshape(1, W)
    v = torch.arange(H, dtype=dtype).reshape(H, 1)
    flow = torch.stack([torch.where(front, u1 - u, 0.0), torch.where(front, v1 - v, 0.0)])
    inside = front & (u1 >= 0) & (u1 <= W - 1) & (v1 >= 0) & (v1 <= H - 1)
    # occlusion: inverse depth at t+1 interpolated at the projected position (exact on planes)
    grid = torch.stack([2 * u1 / max(W - 1, 1) - 1, 2 * v1 / max(H - 1, 1) - 1], dim=-1)
    grid = torch.where(inside.unsqueeze(-1), grid, 0.0)
    seen = F.grid_sample(next_inv_depth.reshape(1, 1, H, W), grid.unsqueeze(0), mode="bilinear",
                         padding_mode="border", align_corners=True)[0, 0]
    visible = (1.0 / Zs) * (1 + 2e-3) + 1e-9 >= seen
    valid = ~sky & inside & visible

    # px/s: p_v = R_ψ (P - c); ṗ_v = ω J p_v - (0, 0, v_r) + R_ψ ṗ_world; p_cam = R_c p_v
    A0, c0 = scene.world_to_camera(k)
    _, _, psi = scene.ego_pose(k)
    Rpsi = _rot_y(psi)
    mot = scene.motion
    omega = mot.speed * math.tan(mot.steering) / mot.wheelbase
    pvx, pvy, pvz = _apply(Rpsi, Px - c0[0] * not_sky, Py - c0[1] * not_sky, Pz - c0[2] * not_sky)
    dvx = -omega * pvz
    dvy = torch.zeros_like(pvy)
    dvz = omega * pvx - mot.speed * not_sky
    if idx is not None:
        wx, wy, wz = _apply(Rpsi, Pdot_sel[:, 0], Pdot_sel[:, 1], Pdot_sel[:, 2])
        dvx, dvy, dvz = dvx.index_put(idx, dvx[idx] + wx), dvy.index_put(idx, wy), dvz.index_put(idx, dvz[idx] + wz)
    Rc = scene.Rc
    Xc, Yc, Zc = _apply(Rc, pvx, pvy, pvz)
    dXc, dYc, dZc = _apply(Rc, dvx, dvy, dvz)
    okc = Zc > 1e-6
    Zc = torch.where(okc, Zc, 1.0)
    dx_ = (dXc * Zc - Xc * dZc) / (Zc * Zc)
    dy_ = (dYc * Zc - Yc * dZc) / (Zc * Zc)
    fu = torch.where(okc, Kt[0][0] * dx_ + Kt[0][1] * dy_, 0.0)
    fv = torch.where(okc, Kt[1][1] * dy_, 0.0)
    return {"flow": flow, "valid": valid.unsqueeze(0), "flow_velocity": torch.stack([fu, fv])}


# -- public API ------------------------------------------------------------------------------------

class _Renderer:
    """Frame cache for one scene: images and pixel-centre casts per frame index."""

    def __init__(self, scene: _Scene) -> None:
        self.scene = scene
        self.H, self.W = scene.size
        self._frames: dict[int, dict[str, Any]] = {}

    def frame(self, k: int) -> dict[str, Any]:
        if k in self._frames:
            return self._frames[k]
        scene = self.scene
        ss = scene.cfg.supersample
        dtype = scene.dtype
        uc, vc = _grid((self.H, self.W), 1, dtype)
        centre = _cast(scene, k, uc, vc)
        centre_rgb, labels = _shade(scene, centre, labels=True)
        if ss > 1 and not scene.cfg.adaptive:
            us, vs = _grid((self.H, self.W), ss, dtype)
            rgb = _shade(scene, _cast(scene, k, us, vs))
            image = rgb.reshape(3, self.H, ss, self.W, ss).mean(dim=(2, 4))
        else:
            image = centre_rgb
            if ss > 1:
                image = self._supersample_edges(k, centre, image)
        if scene.cfg.noise > 0:
            # noise is given at base_size; another size is that image area-averaged:
            # the per-pixel noise scales with the square root of the pixel area, as the
            # band-limited textures do, so a small render is the same camera binned
            H0, W0 = scene.cfg.base_size
            sigma = scene.cfg.noise * math.sqrt(self.H * self.W / (H0 * W0))
            image = _sensor_noise(image, sigma, scene.seed, k)
        depth = torch.where(centre.label == _SKY, torch.zeros_like(centre.t), centre.t)
        inv_depth = torch.where(centre.label == _SKY, torch.zeros_like(centre.t), 1.0 / centre.t)
        out = {"image": image, "centre": centre, "labels": labels, "depth": depth, "inv_depth": inv_depth}
        self._frames = {kk: vv for kk, vv in self._frames.items() if kk >= k - 1}
        self._frames[k] = out
        return out

    def _supersample_edges(self, k: int, centre: _Hits, image: Tensor) -> Tensor:
        """Replace the colour of pixels at geometric edges (a different surface or object next to
        them) by the mean of ss × ss sub-pixel rays. Textures and markings are band-limited
        analytically, so elsewhere the pixel-centre sample is already anti-aliased."""
        ss = self.scene.cfg.supersample
        key = centre.label * 100003 + centre.obj
        edge = torch.zeros_like(key, dtype=torch.bool)
        dh = key[:, 1:] != key[:, :-1]
        dv = key[1:, :] != key[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        ie, je = edge.nonzero(as_tuple=True)
        if ie.numel() == 0:
            return image
        dtype = self.scene.dtype
        offsets = (torch.arange(ss, dtype=torch.float64) + 0.5) / ss - 0.5
        ov, ou = torch.meshgrid(offsets, offsets, indexing="ij")
        u = (je.to(torch.float64).unsqueeze(1) + ou.reshape(1, -1)).reshape(-1).to(dtype)
        v = (ie.to(torch.float64).unsqueeze(1) + ov.reshape(1, -1)).reshape(-1).to(dtype)
        v, order = torch.sort(v, stable=True)
        rgb = torch.empty(3, v.numel(), dtype=dtype)
        rgb[:, order] = _shade(self.scene, _cast(self.scene, k, u[order], v, grid=False))
        mean = rgb.reshape(3, -1, ss * ss).mean(dim=2)
        image = image.clone()
        image[:, ie, je] = mean
        return image

    def pair(self, k: int) -> dict[str, Any]:
        f0, f1 = self.frame(k), self.frame(k + 1)
        scene = self.scene
        centre = f0["centre"]
        gt = _ground_truth(scene, k, centre, f1["inv_depth"])
        labels = f0["labels"]
        is_moving = torch.tensor([o.vs != 0.0 for o in centre.objects] + [False], dtype=torch.bool)
        moving = is_moving[torch.where(centre.obj >= 0, centre.obj, len(centre.objects))]
        mot = scene.motion
        cam0 = scene.world_to_camera(k)
        cam1 = scene.world_to_camera(k + 1)
        return {
            "image1": f0["image"],
            "image2": f1["image"].clone(),  # the next pair's image1: no aliasing between pairs
            "flow": gt["flow"],
            "valid": gt["valid"],
            "flow_velocity": gt["flow_velocity"],
            "road": ((labels == _ROAD) | (labels == _MARK)).unsqueeze(0),
            "labels": labels,
            "depth": f0["depth"].unsqueeze(0),
            "moving": moving.unsqueeze(0),
            "camera": scene.camera(),
            "odometry": {"x_d": mot.x_d, "z_d": mot.z_d, "yaw": mot.yaw},
            "velocity": {"speed": mot.speed, "steering": mot.steering, "wheelbase": mot.wheelbase,
                         "dt": mot.dt},
            "pose1": _camera_to_world(*cam0),
            "pose2": _camera_to_world(*cam1),
            "index": k,
        }


def _sensor_noise(image: Tensor, sigma: float, seed: int, k: int) -> Tensor:
    """``image`` (3, H, W) 0..255 plus independent Gaussian noise of standard deviation ``sigma``
    (grey levels) per pixel, the same on the three channels, clamped to 0..255 (the images stay
    float). The generator depends on (seed, frame index) only, so re-rendering frame k of the
    same scene gives the same noise, and frames shared between pairs agree."""
    g = torch.Generator().manual_seed((int(seed) * 1_000_003 + int(k) * 7_919 + 12_345) % (2**63))
    # one value for the three channels: luminance noise, as a grey camera (or the grey image that
    # flow methods compute) sees it; the measured real statistics are grey-level ones
    noise = torch.randn((1, *image.shape[1:]), generator=g, dtype=torch.float64).to(image.dtype)
    return (image + sigma * noise).clamp(0.0, 255.0)


def _camera_to_world(A: list[list[float]], c: list[float]) -> Tensor:
    """KITTI-style camera-to-world pose (4, 4) float64 from p_cam = A (p_world - c)."""
    T = torch.eye(4, dtype=torch.float64)
    At = torch.tensor(A, dtype=torch.float64)
    T[:3, :3] = At.T
    T[:3, 3] = torch.tensor(c, dtype=torch.float64)
    return T


def _check_dtype(dtype: torch.dtype) -> None:
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")


def render_pair(preset: str | SceneConfig = "default", index: int = 0, *, seed: int = 0,
                size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float32,
                **overrides: Any) -> dict[str, Any]:
    """Render frames ``index`` and ``index + 1`` of a procedural sequence with all ground truth.

    Args:
        preset: a name of :data:`PRESETS` or a :class:`SceneConfig`.
        index: the pair's position in the sequence (frame t = index).
        seed: scene seed (object layout, colours, textures); same seed, same pixels.
        size: ``(H, W)`` of the images; K is scaled from the KITTI-like 375×1242 (default).
        dtype: float32 or float64 for every tensor (geometry is exact either way up to rounding).
        **overrides: fields of :class:`SceneConfig` (``speed_factor=4``, ``roll=math.radians(5)``,
            ``supersample=3``, ``x_d=, z_d=, yaw=`` …).

    Returns:
        dict with ``image1``, ``image2`` (3, H, W) RGB 0..255; ``flow`` (2, H, W) px, forward;
        ``valid`` (1, H, W) bool; ``flow_velocity`` (2, H, W) px/s; ``road`` (1, H, W) bool;
        ``labels`` (H, W) int64 (:data:`LABELS`); ``depth`` (1, H, W) m (camera z, 0 on the sky);
        ``moving`` (1, H, W) bool (pixels on moving cars);
        ``camera`` (:class:`Camera`, batch 1); ``odometry`` dict(x_d, z_d, yaw) floats (m, rad);
        ``velocity`` dict(speed m/s, steering rad, wheelbase m, dt s) floats; ``pose1``, ``pose2``
        (4, 4) float64 camera-to-world poses (KITTI convention, world = vehicle frame of frame 0);
        ``index`` int.
    """
    return render_sequence(preset, 1, seed=seed, size=size, dtype=dtype, start=index, **overrides)[0]


def render_sequence(preset: str | SceneConfig = "default", num_pairs: int = 1, *, seed: int = 0,
                    size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float32,
                    progress: bool = False, start: int = 0, **overrides: Any) -> list[dict[str, Any]]:
    """Render ``num_pairs`` consecutive pairs (frames start..start+num_pairs) of one sequence.

    Consecutive pairs share frames (frame t+1 of pair i is frame t of pair i+1); each pair equals
    ``render_pair(preset, start + i, ...)``. ``progress=True`` shows a tqdm bar. Other arguments
    as in :func:`render_pair`.
    """
    _check_dtype(dtype)
    for name, value in (("num_pairs", num_pairs), ("start", start), ("seed", seed)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name}: expected an int, got {value!r}")
    if num_pairs < 1:
        raise ValueError(f"num_pairs: expected >= 1, got {num_pairs}")
    if start < 0:
        raise ValueError(f"index: expected >= 0, got {start}")
    if size is not None:
        size = check_size(size)
        overrides["size"] = size
    cfg = scene_config(preset, **overrides)
    renderer = _Renderer(_Scene(cfg, seed, dtype))
    indices = range(start, start + num_pairs)
    if progress:
        from tqdm.auto import tqdm
        indices = tqdm(indices, desc=f"render {preset if isinstance(preset, str) else 'scene'}", unit="pair")
    return [renderer.pair(k) for k in indices]


def collate(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack rendered pairs into a batch: tensors get a leading B, cameras are concatenated,
    ``odometry`` / ``velocity`` floats become (B,) tensors (of the cameras' dtype), ints a list.

    The rules of :func:`fsof_torch.datasets.collate`, so rendered pairs and pairs read from disk
    batch alike.
    """
    if not isinstance(pairs, (list, tuple)) or not pairs:
        raise ValueError(f"pairs: expected a non-empty list of rendered pairs, got {type(pairs).__name__}")
    from .datasets import collate as collate_items

    return collate_items(pairs)
