"""Shading: colours of cast samples from band-limited procedural textures (multi-scale value
noise whose octaves finer than the pixel footprint fade out, box-filtered lane paint), Lambert
light on boxes, and seeded sensor noise."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .config import ASPHALT_CELLS, KERB, MARKING, PAVEMENT, ROAD, SKY, SceneConfig
from .motion import rot_y
from .objects import BUILDING_BOX, CAR_BODY, CAR_CABIN, SceneObject
from .raycast import Hits
from .world import Scene

_ROAD_AMPS = (25.0, 25.0, 22.0, 18.0, 14.0, 13.0, 11.0)
_SUN = (0.35, -0.8, 0.45)  # world direction towards which light travels is -this (y down)

def shade(scene: Scene, hits: Hits, *, labels: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """RGB (3, *shape) 0..255 of cast samples; with ``labels=True`` also the labels with the
    marking pixels (paint coverage > 1/2) split off the road."""
    dtype = scene.dtype
    cfg = scene.cfg
    tex = cfg.texture
    rgb = torch.zeros(3, *hits.t.shape, dtype=dtype)
    f = scene.K[0][0]
    tables = scene.noise
    label = hits.label
    ox, oy, oz = hits.origin
    graded = scene.grade.active

    # sky: a function of the world direction only (it lies at infinity)
    idx = (label == SKY).nonzero(as_tuple=True)
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
    for kind in (ROAD, PAVEMENT, KERB):
        idx = (label == kind).nonzero(as_tuple=True)
        if idx[0].numel() == 0:
            continue
        t = hits.t[idx]
        dx, dy, dz = hits.dx[idx], hits.dy[idx], hits.dz[idx]
        px, pz = ox + t * dx, oz + t * dz
        dn2 = dx * dx + dy * dy + dz * dz
        if kind == KERB:
            # a vertical face seen at a grazing angle: blur generously
            fp = (t * torch.sqrt(dn2) * (3.0 / f)).clamp_min(1e-4)
            _, s = scene.road.to_road(px, pz)
            height = oy + t * dy  # world y, and on a grade relative to the road there
            if graded:
                height = height + scene.grade.elevation(pz.double()).to(dtype)
            value = 185.0 + tex * 0.6 * _fbm(tables, s, height * 3, fp, ASPHALT_CELLS[:4], _ROAD_AMPS[:4])
            colour = (value, value, value + 3.0)
        else:
            # pixel footprint on the plane: distance / f / cos(incidence), metres; the ray's
            # component along the surface normal (0, 1, g') / sqrt(1 + g'²) is dy on a level road
            facing = dy
            if graded:
                q = scene.grade.slope(pz.double()).to(dtype)
                facing = (dy + q * dz) / torch.sqrt(1 + q * q)
            fp = (t * dn2 / (f * facing)).clamp_min(1e-4)
            amps = tuple(cfg.asphalt) if kind == ROAD and cfg.asphalt is not None else _ROAD_AMPS
            n = _fbm(tables, px, pz, fp, ASPHALT_CELLS, amps)
            e, s = scene.road.to_road(px, pz)
            if kind == ROAD:
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
        glass = ((kind == CAR_CABIN) & (face != 1)).unsqueeze(1)
        glass_col = torch.tensor([40.0, 45.0, 55.0], dtype=dtype) + tex * 0.5 * n
        ccol = torch.where(glass, glass_col, col + tex * 0.6 * n)
        band = (_stripe(ly - half[:, 1] + 0.1, 0.1, fp) * (kind == CAR_BODY).to(dtype) * not_top).unsqueeze(1)
        ccol = ccol + (30.0 - ccol) * band
        colour = torch.where((kind == BUILDING_BOX).unsqueeze(1), bcol, ccol) * light.unsqueeze(1)
        for ch in range(3):
            rgb[ch][idx] = colour[:, ch]
    rgb = rgb.clamp(0.0, 255.0)
    if not labels:
        return rgb
    out = hits.label.clone()
    if (hits.label == ROAD).any():
        idx, is_mark = marking
        out[idx] = torch.where(is_mark, MARKING, ROAD)
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


def _face_light(scene: Scene, o: SceneObject, origin: list[float], k: int) -> tuple[float, float, float]:
    """Lambert factor of the box faces whose normal is along local x, y, z (the face seen)."""
    # The visible face along each axis is the one facing the camera; light depends on that sign.
    centre, psi = scene.object_pose(o, k)
    R = rot_y(psi)
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


def sensor_noise(image: Tensor, sigma: float, seed: int, k: int) -> Tensor:
    """``image`` (3, H, W) 0..255 plus independent Gaussian noise of standard deviation ``sigma``
    (grey levels) per pixel, the same on the three channels, clamped to 0..255 (the images stay
    float). The generator depends on (seed, frame index) only, so re-rendering frame k of the
    same scene gives the same noise, and frames shared between pairs agree."""
    g = torch.Generator().manual_seed((int(seed) * 1_000_003 + int(k) * 7_919 + 12_345) % (2**63))
    # one value for the three channels: luminance noise, as a grey camera (or the grey image that
    # flow methods compute) sees it; the measured real statistics are grey-level ones
    noise = torch.randn((1, *image.shape[1:]), generator=g, dtype=torch.float64).to(image.dtype)
    return (image + sigma * noise).clamp(0.0, 255.0)

